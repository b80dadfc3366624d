"""Small scene dictionaries shared by the tests (parsed with jaxdem.scene.parse_scene)."""

from __future__ import annotations

import math

import numpy as np

ROCK = {"E": 1.0e7, "nu": 0.25, "unit_weight": 25.0}


def incline_frame(alpha_deg: float):
    """Unit tangent (down-slope is -t) and normal of a slope rising to the right."""
    a = math.radians(alpha_deg)
    t = np.array([math.cos(a), math.sin(a)])
    n = np.array([-math.sin(a), math.cos(a)])
    return t, n


def slope_base(alpha_deg: float, length: float = 12.0):
    """Fixed quadrilateral whose top face is the slope y = x tan(alpha), x in [-1, length]."""
    ta = math.tan(math.radians(alpha_deg))
    return [[-1.0, -ta - 2.0], [length, -ta - 2.0], [length, length * ta], [-1.0, -ta]]


def rect_on_slope(alpha_deg: float, s0: float, width: float, height: float):
    """Rectangle ``width`` along the slope, ``height`` normal to it, from slope coordinate s0."""
    t, n = incline_frame(alpha_deg)
    p0 = s0 * t
    corners = [p0, p0 + width * t, p0 + width * t + height * n, p0 + height * n]
    return [list(c) for c in corners]


def _block_on_slope(name: str, alpha_deg: float, width: float, height: float, joint: tuple,
                    solver: dict, *, stop_at: float | None = None) -> dict:
    """A free block on a fixed slope (from slope coordinate 4 m), a point monitor at its
    centroid; ``joint`` = (name, properties); ``stop_at``: a fixed 1 m block from there."""
    blk = rect_on_slope(alpha_deg, 4.0, width, height)
    blocks = [
        {"vertices": slope_base(alpha_deg), "material": "rock", "fixed": True},
        {"vertices": blk, "material": "rock"},
    ]
    if stop_at is not None:
        blocks.append({"vertices": rect_on_slope(alpha_deg, stop_at, 1.0, 1.0),
                       "material": "rock", "fixed": True})
    return {
        "scene": {"name": name},
        "solver": solver,
        "materials": {"rock": dict(ROCK)},
        "joints": {joint[0]: joint[1]},
        "blocks": blocks,
        "monitors": [{"name": "block", "point": np.mean(np.array(blk), axis=0).tolist()}],
    }


def block_on_incline(alpha_deg: float, friction_deg: float, *, cohesion: float = 0.0,
                     width: float = 1.0, height: float = 1.0, kn: float = 1e6, ks: float = 5e5,
                     load_steps: int = 1, **solver) -> dict:
    """A block resting on a fixed slope, with a point monitor at its centroid."""
    joint = {"kn": kn, "ks": ks, "friction_deg": friction_deg, "cohesion": cohesion}
    return _block_on_slope(f"incline {alpha_deg}/{friction_deg}", alpha_deg, width, height,
                           ("base", joint), {"load_steps": load_steps, **solver})


def stack(n_blocks: int = 3, *, kn: float = 1e6, ks: float = 1e6, width: float = 1.0,
          height: float = 1.0, load_steps: int = 1) -> dict:
    """A column of square blocks on a fixed base block, monitor at the top block."""
    blocks = [{"vertices": [[-2, -1], [3, -1], [3, 0], [-2, 0]], "material": "rock", "fixed": True}]
    for k in range(n_blocks):
        y0 = k * height
        blocks.append({"vertices": [[0, y0], [width, y0], [width, y0 + height], [0, y0 + height]],
                       "material": "rock"})
    top = [0.5 * width, (n_blocks - 0.5) * height]
    return {
        "scene": {"name": f"stack of {n_blocks}"},
        "solver": {"load_steps": load_steps},
        "materials": {"rock": dict(ROCK)},
        "joints": {"j": {"kn": kn, "ks": ks, "friction_deg": 35.0}},
        "blocks": blocks,
        "monitors": [{"name": "top", "point": top}],
    }


def slide_and_stop(gap: float = 1.0, alpha: float = 30.0, phi: float = 15.0) -> dict:
    """Seed example 1: a block slides down a slope until it meets a fixed block."""
    joint = {"kn": 1e6, "ks": 5e5, "friction_deg": phi}
    return _block_on_slope("seed example 1", alpha, 1.0, 1.0, ("j", joint),
                           # Tight tolerance: the tests check the global balance to 1e-8.
                           {"load_steps": 1, "max_displacement": 3.0 * gap, "tolerance": 1e-9},
                           stop_at=4.0 - gap - 1.0)


def tall_block(width: float, height: float, alpha: float = 20.0, phi: float = 40.0) -> dict:
    """A block on a slope with friction high enough to stop sliding."""
    joint = {"kn": 1e6, "ks": 5e5, "friction_deg": phi}
    return _block_on_slope(f"toppling {width}x{height}", alpha, width, height, ("j", joint),
                           {"load_steps": 1, "max_displacement": 0.3 * height})


def jointed_tunnel(*, spacing: float = 3.0, half: float = 9.0, water: bool = True,
                   bolts: bool = True, support: float = 100.0, load_steps: int = 1,
                   top: str = "traction") -> dict:
    """A small jointed tunnel: two joint sets, gravity in-situ stress, a horseshoe opening,
    a roof bolt, a support pressure and a water table; a crown point and a section monitor.
    ``top``: "traction" (the overburden as a load) or "roller" (a wall, which holds any
    in-situ stress in equilibrium)."""
    d = {
        "scene": {"name": "small jointed tunnel"},
        # Tight tolerance: the tests compare derivatives with central differences and
        # the solver paths with each other to 1e-7.
        "solver": {"load_steps": load_steps, "tolerance": 1e-9},
        "materials": {"rock": {"E": 2.0e7, "nu": 0.25, "unit_weight": 26.0, "cohesion": 2000.0,
                               "friction_deg": 45.0, "tensile_strength": 1000.0}},
        "joints": {
            "set1": {"kn": 2.0e6, "ks": 5.0e5, "friction_deg": 35.0, "cohesion": 20.0,
                     "dip_deg": 30.0, "spacing": spacing},
            "set2": {"kn": 1.0e6, "ks": 4.0e5, "friction_deg": 30.0, "cohesion": 20.0,
                     "dip_deg": 120.0, "spacing": spacing},
        },
        "domain": {"outline": [[-half, -half], [half, -half], [half, half], [-half, half]],
                   "material": "rock"},
        "excavations": [{"name": "tunnel", "shape": "horseshoe", "center": [0.0, -2.0],
                         "width": 4.0, "height": 4.0}],
        # The overburden above the model (surface at 40 m) as a traction on top.
        "boundaries": [{"side": s, "condition": "roller"} for s in ("left", "right", "bottom")]
        + [{"side": "top", "condition": "traction", "traction": [0.0, -26.0 * (40.0 - half)]}
           if top == "traction" else {"side": "top", "condition": "roller"}],
        "in_situ": {"mode": "gravity", "k0": 0.8, "surface_y": 40.0},
        "monitors": [{"name": "crown", "point": [0.0, 2.05]},
                     {"name": "span", "from": [-2.05, -1.0], "to": [2.05, -1.0]}],
    }
    if support:
        d["supports"] = [{"excavation": "tunnel", "pressure": support}]
    if bolts:
        d["bolts"] = [{"from": [0.0, 2.1], "to": [0.0, 6.0], "stiffness": 5.0e4,
                       "yield_force": 200.0, "anchor_capacity": 300.0}]
    if water:
        d["water"] = {"table": [[-half, 30.0], [half, 32.0]]}
    return d
