"""Metamorphic tests: the answer follows the scene when the scene is mirrored or moved.

No closed form is needed: plane strain has no preferred left or right and no origin,
so mirroring a scene about a vertical line must mirror every answer (ux negated, uy
and every section's convergence kept, rotations negated), and translating it must
leave every answer unchanged. They catch what closed forms miss: a kernel that
favours one side (a contact search in one order, a generator that cuts a symmetric
domain into asymmetric pieces, a tolerance in absolute coordinates).

Scenes: explicit blocks (a bolted asymmetric key block, a bolted block on an incline,
a stack) and jointed tunnels generated from joint sets with random dips and
spacings, with and without bolts, water and supports.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scenes import block_on_incline, jointed_tunnel, stack
from verification.test_bolts import incline_with_bolt, key_block

import jaxdem
from jaxdem.scene import parse_scene


def _map_points(obj, f):
    return [f(np.asarray(p, float)).tolist() for p in obj]


def transform(d: dict, point, *, mirror: bool, dy: float = 0.0) -> dict:
    """The scene ``d`` with every coordinate mapped by ``point`` (a mirror about a vertical
    line when ``mirror``: polygons reversed to keep their orientation, trace angles and
    shear stresses and tractions turned accordingly; ``dy`` the vertical shift, which
    moves the ground surface and water tables with the rock)."""
    d = copy.deepcopy(d)

    def poly(vs):
        out = _map_points(vs, point)
        return out[::-1] if mirror else out

    for b in d.get("blocks", []):
        b["vertices"] = poly(b["vertices"])
    if "domain" in d:
        d["domain"]["outline"] = poly(d["domain"]["outline"])
    for j in d.get("joints", {}).values():
        if "dip_deg" in j and mirror:
            j["dip_deg"] = 180.0 - j["dip_deg"]
        if "origin" in j:
            j["origin"] = point(np.asarray(j["origin"], float)).tolist()
    for key in ("discontinuities", "bolts"):
        for item in d.get(key, []):
            item["from"], item["to"] = (point(np.asarray(item[k], float)).tolist()
                                        for k in ("from", "to"))
    for e in d.get("excavations", []):
        if "center" in e:
            e["center"] = point(np.asarray(e["center"], float)).tolist()
        if "vertices" in e:
            e["vertices"] = poly(e["vertices"])
    for bd in d.get("boundaries", []):
        if mirror and bd.get("side") in ("left", "right"):
            bd["side"] = {"left": "right", "right": "left"}[bd["side"]]
        if "from" in bd:
            bd["from"], bd["to"] = (point(np.asarray(bd[k], float)).tolist()
                                    for k in ("from", "to"))
        if mirror and "traction" in bd:
            bd["traction"] = [-bd["traction"][0], bd["traction"][1]]
    ins = d.get("in_situ")
    if ins is not None:
        if "surface_y" in ins:
            ins["surface_y"] += dy
        if mirror and "sigma_xy" in ins:
            ins["sigma_xy"] = -ins["sigma_xy"]
    if "water" in d:
        table = _map_points(d["water"]["table"], point)
        d["water"]["table"] = table[::-1] if mirror else table
    for m in d.get("monitors", []):
        for k in ("point", "from", "to"):
            if k in m:
                m[k] = point(np.asarray(m[k], float)).tolist()
    return d


def mirrored(d: dict, x0: float = 0.0) -> dict:
    return transform(d, lambda p: np.array([2 * x0 - p[0], p[1]]), mirror=True)


def translated(d: dict, dx: float, dy: float) -> dict:
    return transform(d, lambda p: p + np.array([dx, dy]), mirror=False, dy=dy)


def answers(d: dict) -> dict:
    r = jaxdem.solve(parse_scene(d))
    out = {"status": r.status, "stable": r.stable,
           "bolts": [round(b["force"], 6) for b in r.bolts]}
    for name, m in r.monitors.items():
        out[name] = np.asarray(m.get("displacement", [m.get("convergence", 0.0)]), float)
    return out


def _scale(ans: dict) -> float:
    return max([float(np.max(np.abs(v))) for v in ans.values() if isinstance(v, np.ndarray)]
               + [1e-12])


def _random_tunnel(seed: int, bolts: bool) -> dict:
    """A jointed tunnel with two joint sets of random dips and spacings."""
    rng = np.random.default_rng(seed)
    d = jointed_tunnel(spacing=3.0, water=bool(seed % 2), bolts=bolts,
                       support=50.0 if seed % 3 == 0 else 0.0)
    d["solver"]["tolerance"] = 1e-10
    d["joints"]["set1"]["dip_deg"] = float(rng.uniform(10, 80))
    d["joints"]["set2"]["dip_deg"] = float(rng.uniform(100, 170))
    for name in ("set1", "set2"):
        d["joints"][name]["spacing"] = float(rng.uniform(2.2, 3.5))
        d["joints"][name]["origin"] = [float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1))]
    return d


SCENES = {
    "key block on two bolts": key_block([((-0.5, 0.15), (-0.5, 2.6)), ((0.5, 0.15), (0.5, 2.6))],
                                        (0.4, 1.5)),
    "bolted block on incline": incline_with_bolt(40.0, 30.0, 45.0),
    "block on incline": block_on_incline(25.0, 30.0),
    "sliding block": block_on_incline(35.0, 30.0),
    "stack": stack(3),
    "jointed tunnel 1, bolted": _random_tunnel(1, True),
    "jointed tunnel 2": _random_tunnel(2, False),
    "jointed tunnel 3, bolted": _random_tunnel(3, True),
}


def _compare(a: dict, b: dict, flip: bool, rtol: float = 1e-6):
    assert (a["status"], a["stable"]) == (b["status"], b["stable"])
    np.testing.assert_allclose(a["bolts"], b["bolts"], rtol=1e-5, atol=1e-6)
    tol = rtol * max(_scale(a), _scale(b))
    for name, v in a.items():
        if not isinstance(v, np.ndarray):
            continue
        w = b[name].copy()
        if flip and w.shape == (2,):
            w[0] = -w[0]
        np.testing.assert_allclose(w, v, rtol=0, atol=tol, err_msg=name)


@pytest.mark.parametrize("name", list(SCENES))
def test_mirrored_scene_gives_the_mirrored_answer(name):
    d = SCENES[name]
    _compare(answers(d), answers(mirrored(d, x0=0.37)), flip=True)


@pytest.mark.parametrize("name", ["key block on two bolts", "sliding block",
                                  "jointed tunnel 1, bolted"])
def test_translated_scene_gives_the_same_answer(name):
    d = SCENES[name]
    _compare(answers(d), answers(translated(d, 1234.5, -321.0)), flip=False)


def test_symmetric_scene_gives_a_symmetric_answer():
    # A symmetric tunnel: vertical and horizontal joints through the axis, symmetric
    # bolts; the crown moves straight down and the two walls converge equally.
    d = jointed_tunnel(spacing=2.5, water=False, bolts=False)
    d["joints"]["set1"].update(dip_deg=0.0, origin=[0.0, 0.0])
    d["joints"]["set2"].update(dip_deg=90.0, origin=[0.0, 0.0])
    d["bolts"] = [{"from": [x, 1.9], "to": [x, 5.5], "stiffness": 5e4, "yield_force": 200.0,
                   "anchor_capacity": 300.0} for x in (-1.25, 1.25)]
    d["monitors"] += [{"name": "left", "point": [-2.05, -2.0]},
                      {"name": "right", "point": [2.05, -2.0]}]
    r = jaxdem.solve(parse_scene(d))
    assert r.converged
    scale = _scale(answers(d))
    ux, uy = r.monitors["crown"]["displacement"]
    assert abs(ux) <= 1e-6 * scale and uy < 0
    lx, ly = r.monitors["left"]["displacement"]
    rx, ry = r.monitors["right"]["displacement"]
    assert abs(lx + rx) <= 1e-6 * scale and abs(ly - ry) <= 1e-6 * scale
    f = [b["force"] for b in r.bolts]
    assert abs(f[0] - f[1]) <= 1e-6 * max(abs(f[0]), 1.0)
