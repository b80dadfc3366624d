"""Figures: blocks.png, monitors.png and check.png from hand-built Results and scenes."""

from __future__ import annotations

import matplotlib
import matplotlib.collections
import numpy as np
import pytest

from jaxdem import plots
from jaxdem.core.state import OPEN, SLIP, STICK
from jaxdem.plots import _canvas as plots_canvas
from jaxdem.plots import _model as plots_model
from jaxdem.plots import _monitors as plots_monitors
from jaxdem.results import Result

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _square(x0: float, y0: float, side: float) -> np.ndarray:
    return np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]])


def make_result(moving: bool = False) -> Result:
    """Three squares (0 fixed, 1 and 2 resting on it), contacts in every state,
    a point and a section monitor, four increments over two stages."""
    initial = [_square(0.0, 0.0, 2.0), _square(0.0, 2.0, 1.0), _square(1.0, 2.0, 1.0)]
    u = np.array([[0.0, 0.0, 0.0], [1e-3, -2e-3, 1e-4], [3e-4, -1e-3, 0.0]])
    if moving:
        u[2] = [0.5, -0.1, 0.2]
    final = [v + ui[:2] for v, ui in zip(initial, u, strict=True)]
    points = np.array([[0.0, 2.0], [1.0, 2.0], [1.0, 2.0], [2.0, 2.0], [1.0, 2.5]])
    state = np.array([STICK, SLIP, STICK, OPEN, SLIP])
    history = [
        {
            "stage": stage,
            "step": step,
            "load_factor": step / 2,
            "monitors": {"crown": 1e-3 * (2 * k + step), "s1": 4e-4 * (2 * k + step)},
        }
        for k, stage in enumerate(["gravity", "excavate"])
        for step in (1, 2)
    ]
    return Result(
        scene="three squares",
        converged=True,
        stable=not moving,
        status="mechanism" if moving else "converged",
        message="synthetic",
        monitors={
            "crown": {"displacement": [1e-3, -2e-3]},
            "s1": {"convergence": 1.6e-3, "along": [8e-4, -8e-4]},
        },
        blocks=[
            {
                "id": i,
                "centroid": v.mean(axis=0).tolist(),
                "u": u[i].tolist(),
                "stress": [0.0, 0.0, 0.0],
                "fixed": i == 0,
            }
            for i, v in enumerate(initial)
        ],
        contacts={"total": 5, "open": 1, "slipping": 2},
        bolts=[],
        stages=[],
        moving_blocks=[2] if moving else [],
        equilibrium={},
        timing={"build_s": 0.0, "compile_s": 0.0, "solve_s": 0.0},
        geometry={
            "initial_vertices": initial,
            "final_vertices": final,
            "fixed": [True, False, False],
            "walls": [np.array([[-0.5, 0.0], [2.5, 0.0]])],
            "contacts": {
                "points": points,
                "normals": np.tile([0.0, 1.0], (5, 1)),
                "state": state,
                "fn": np.ones(5),
                "fs": np.zeros(5),
            },
            "monitors": {"crown": np.array([0.5, 2.5]), "s1": np.array([[0.0, 2.5], [2.0, 2.5]])},
        },
        history=history,
    )


def _assert_png(path) -> None:
    assert path.is_file()
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > 5000  # a drawn figure, not an empty canvas


@pytest.mark.parametrize("moving", [False, True], ids=["stable", "mechanism"])
def test_write_figures_writes_blocks_and_monitors(tmp_path, moving):
    paths = plots.write_figures(make_result(moving), tmp_path / "figs")
    assert [p.name for p in paths] == ["blocks.png", "monitors.png"]
    for p in paths:
        _assert_png(p)


def test_no_monitors_gives_no_history_figure(tmp_path):
    result = make_result()
    result.monitors = {}
    result.history = [dict(h, monitors={}) for h in result.history]
    result.geometry["monitors"] = {}
    assert plots.plot_monitor_history(result, tmp_path / "m.png") is None
    assert not (tmp_path / "m.png").exists()
    paths = plots.write_figures(result, tmp_path)
    assert [p.name for p in paths] == ["blocks.png"]


def test_plot_blocks_without_contacts_or_motion(tmp_path):
    result = make_result()
    result.geometry["contacts"] = {}
    result.geometry["walls"] = []
    for b in result.blocks:
        b["u"] = [0.0, 0.0, 0.0]
    _assert_png(plots.plot_blocks(result, tmp_path / "b.png", magnification=10.0))


def test_status_text():
    assert plots_model._status_text(make_result()) == "stable"
    assert plots_model._status_text(make_result(moving=True)) == "UNSTABLE: block 2 moving"
    result = make_result(moving=True)
    result.moving_blocks = [3, 7]
    assert plots_model._status_text(result) == "UNSTABLE: blocks 3, 7 moving"
    result.status = "iteration_limit"
    assert "iteration_limit" in plots_model._status_text(result)


@pytest.mark.parametrize(
    ("size", "u_max", "expected"),
    [
        (4.0, 2e-3, 100.0),
        (10.0, 1e-3, 500.0),
        (10.0, 3e-3, 200.0),
        (10.0, 2.0, 1.0),
        (10.0, 0.0, 1.0),
    ],
)
def test_nice_magnification(size, u_max, expected):
    assert plots.nice_magnification(size, u_max) == pytest.approx(expected)


def test_largest_per_cell_keeps_one_per_cell():
    pts = np.array([[0.1, 0.1], [0.2, 0.2], [0.9, 0.9], [0.95, 0.95]])
    keep = plots_canvas.largest_per_cell(pts, np.array([1.0, 3.0, 2.0, 0.5]), 2)
    assert keep.tolist() == [False, True, True, False]


def test_many_blocks(tmp_path):
    n = 60  # 3,600 blocks: collections, thinned arrows
    initial = [_square(i, j, 1.0) for i in range(n) for j in range(n)]
    c = np.array([v.mean(axis=0) for v in initial])
    u = np.zeros((len(initial), 3))
    u[:, 1] = -1e-3 * np.exp(-((c[:, 0] - n / 2) ** 2) / n)
    result = make_result()
    result.blocks = [
        {"id": k, "centroid": c[k].tolist(), "u": u[k].tolist()} for k in range(len(initial))
    ]
    result.moving_blocks = []
    result.geometry.update(
        initial_vertices=initial,
        final_vertices=[v + d[:2] for v, d in zip(initial, u, strict=True)],
        fixed=[j == 0 for i in range(n) for j in range(n)],
        contacts={"points": c, "state": np.arange(len(c)) % 3},
    )
    _assert_png(plots.plot_blocks(result, tmp_path / "many.png"))


def _scene():
    from jaxdem.scene import parse_scene

    return parse_scene(
        {
            "scene": {"name": "check me"},
            "materials": {
                "rock": {"E": 1e7, "nu": 0.25, "unit_weight": 25.0},
                "soft": {"E": 1e6, "nu": 0.3, "unit_weight": 20.0},
            },
            "joints": {"j": {"kn": 1e7, "ks": 1e7, "friction_deg": 30.0}},
            "blocks": [
                {"vertices": [[0, 0], [4, 0], [4, 1], [0, 1]], "material": "rock", "fixed": True},
                {"vertices": [[1, 1], [2, 1], [2, 2], [1, 2]], "material": "rock"},
                {"vertices": [[2, 1], [3, 1], [3, 2], [2, 2]], "material": "soft"},
            ],
            "discontinuities": [{"from": [2, 1], "to": [2, 2], "joint": "j"}],
            "boundaries": [{"side": "bottom", "condition": "fixed"}],
            "monitors": [
                {"name": "top", "point": [1.5, 1.5]},
                {"name": "across", "from": [1.2, 1.5], "to": [2.8, 1.5]},
            ],
        }
    )


def test_plot_scene_check(tmp_path):
    path = plots.plot_scene_check(_scene(), tmp_path / "check.png")
    _assert_png(path)


# ---------------------------------------------------------------------------
# Principal stresses, bolts, excavated blocks, stage sections


def make_tunnel_result() -> Result:
    """A 4 x 3 grid of unit squares with the middle of the bottom-but-one row
    excavated, block stresses (one in tension), two bolts (elastic, yielded),
    a section and a point monitor over two stages."""
    initial = [_square(i, j, 1.0) for j in range(3) for i in range(4)]
    n = len(initial)
    excavated = np.zeros(n, dtype=bool)
    excavated[[5, 6]] = True
    fixed = np.array([j == 0 for j in range(3) for _ in range(4)])
    u = np.zeros((n, 3))
    u[8:, 1] = -2e-3
    final = [v + d[:2] for v, d in zip(initial, u, strict=True)]
    centroids = np.array([v.mean(axis=0) for v in final])
    stress = np.tile([300.0, 120.0, 40.0], (n, 1))
    stress[9] = [-50.0, 80.0, 0.0]  # tension along x
    stress[excavated] = 0.0
    result = make_result()
    result.scene = "tunnel grid"
    result.blocks = [
        {
            "id": k,
            "centroid": initial[k].mean(axis=0).tolist(),
            "u": u[k].tolist(),
            "stress": stress[k].tolist(),
            "fixed": bool(fixed[k]),
            **({"excavated": True} if excavated[k] else {}),
        }
        for k in range(n)
    ]
    result.bolts = [
        {"id": 0, "force": 42.0, "force_per_m": 42.0, "state": "elastic"},
        {"id": 1, "force": 150.0, "force_per_m": 150.0, "state": "yielded"},
    ]
    result.stages = [
        {"name": "in situ", "monitors": {"s1": [0.0, 0.0], "crown": [0.0, 1e-4]}},
        {"name": "excavate", "monitors": {"s1": [1e-3, 2.5e-3], "crown": [1e-3, 3e-3]}},
    ]
    result.geometry.update(
        initial_vertices=initial,
        final_vertices=final,
        fixed=fixed,
        excavated=excavated,
        stress=stress,
        centroids=centroids,
        bolts=[np.array([[1.5, 2.5], [1.5, 2.95]]), np.array([[2.5, 2.5], [2.6, 2.95]])],
        monitors={"crown": np.array([1.5, 2.0]), "s1": np.array([[1.0, 1.5], [3.0, 1.5]])},
    )
    return result


def test_principal_stresses_hand_cases():
    sigma, directions = plots.principal_stresses([[3.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    assert sigma[0] == pytest.approx([3.0, 1.0])
    assert np.abs(directions[0, 0]) == pytest.approx([1.0, 0.0])
    assert np.abs(directions[0, 1]) == pytest.approx([0.0, 1.0])
    assert sigma[1] == pytest.approx([1.0, -1.0])
    r = np.sqrt(0.5)
    d1 = directions[1, 0] * np.sign(directions[1, 0, 0])
    d2 = directions[1, 1] * np.sign(directions[1, 1, 0])
    assert d1 == pytest.approx([r, r])  # +1 at 45 degrees
    assert d2 == pytest.approx([r, -r])  # -1 at -45 degrees
    # A single (3,) stress, and unit, orthogonal directions for a general one.
    sigma, directions = plots.principal_stresses([300.0, 120.0, 40.0])
    assert sigma.shape == (1, 2) and sigma[0, 0] > sigma[0, 1]
    assert directions[0] @ directions[0].T == pytest.approx(np.eye(2))


def test_stress_crosses_lengths_and_colours():
    sigma = np.array([[4000.0, -1000.0]])
    directions = np.array([[[1.0, 0.0], [0.0, 1.0]]])
    segments, colours = plots.stress_crosses(np.array([[1.0, 2.0]]), sigma, directions, 2000.0)
    assert segments.shape == (2, 2, 2)
    assert segments[0] == pytest.approx(
        np.array([[0.0, 2.0], [2.0, 2.0]])
    )  # 4000 kPa -> 2 m along x
    assert segments[1] == pytest.approx(np.array([[1.0, 1.75], [1.0, 2.25]]))  # 1000 kPa -> 0.5 m
    assert colours == [plots_model._COMPRESSION, plots_model._TENSION]


@pytest.mark.parametrize(
    ("x", "expected"), [(1.0, 1.0), (1.3, 1.5), (2.2, 2.5), (3.5, 4.0), (6.1e3, 8e3), (9e3, 1e4)]
)
def test_nice_ceil(x, expected):
    assert plots.nice_ceil(x) == pytest.approx(expected)


def test_write_figures_with_stresses_bolts_and_stages(tmp_path):
    paths = plots.write_figures(make_tunnel_result(), tmp_path / "figs")
    names = [p.name for p in paths]
    assert names == ["blocks.png", "monitors.png", "stresses.png", "sections.png"]
    for p in paths:
        _assert_png(p)


def test_excavated_blocks_and_bolts_on_plot_blocks(tmp_path):
    result = make_tunnel_result()
    path = plots.plot_blocks(result, tmp_path / "b.png")
    _assert_png(path)
    # The excavated blocks get no displacement arrow even when they moved.
    result.blocks[5]["u"] = [1.0, 1.0, 0.0]
    _assert_png(plots.plot_blocks(result, tmp_path / "b2.png"))


def test_no_stress_or_stage_figures_without_data(tmp_path):
    result = make_result()  # zero stresses, no stages
    assert plots.plot_principal_stresses(result, tmp_path / "s.png") is None
    assert plots.plot_sections(result, tmp_path / "c.png") is None
    assert not any(tmp_path.iterdir())


def test_sections_points_only(tmp_path):
    result = make_tunnel_result()
    result.stages = [{"name": "only", "monitors": {"crown": [2e-3]}}]
    _assert_png(plots.plot_sections(result, tmp_path / "sections.png"))


def test_many_block_stresses_are_thinned(tmp_path):
    n = 100  # 10,000 blocks: crosses on a 50 x 50 grid
    initial = [_square(i, j, 1.0) for i in range(n) for j in range(n)]
    c = np.array([v.mean(axis=0) for v in initial])
    stress = np.stack([1000.0 + 10 * c[:, 1], 500.0 + 0 * c[:, 0], 50 * np.sin(c[:, 0])], axis=1)
    result = make_result()
    result.blocks = [
        {"id": k, "centroid": c[k].tolist(), "u": [0.0, 0.0, 0.0]} for k in range(n * n)
    ]
    result.geometry.update(
        initial_vertices=initial,
        final_vertices=initial,
        fixed=np.zeros(n * n, dtype=bool),
        stress=stress,
        centroids=c,
    )
    keep = plots_canvas.nearest_centre_per_cell(c, np.ones(len(c), dtype=bool),
                                                plots_model._CROSS_GRID)
    assert keep.sum() == plots_model._CROSS_GRID**2
    _assert_png(plots.plot_principal_stresses(result, tmp_path / "stresses.png"))


# --------------------------------------------------------------------------- issue 19: drawn data


@pytest.fixture
def drawn(monkeypatch):
    """The figures as drawn: {file name: Figure}, kept through ``plots_canvas.inspect``."""
    figures: dict = {}

    def keep(fig, path):
        figures[path.name] = {
            "texts": [(t.get_gid(), t.get_text(), t.get_window_extent())
                      for ax in fig.axes for t in ax.texts],
            "lines": [(line.get_gid(), np.asarray(line.get_xdata(), float),
                       np.asarray(line.get_ydata(), float), line.get_label())
                      for ax in fig.axes for line in ax.lines],
            "collections": [c for ax in fig.axes for c in ax.collections],
            "legend": [t.get_text() for ax in fig.axes if ax.get_legend()
                       for t in ax.get_legend().get_texts()],
            "axes": list(fig.axes),
        }

    monkeypatch.setattr(plots_canvas, "inspect", keep)
    return figures


def test_monitor_labels_do_not_overlap(tmp_path, drawn):
    # The demo's case: a point monitor "crown" at the end of the section "height".
    result = make_result()
    result.monitors["height"] = {"convergence": 1e-3, "along": [0.0, 0.0]}
    result.monitors["span"] = {"convergence": 1e-3, "along": [0.0, 0.0]}
    result.geometry["monitors"] = {
        "crown": np.array([0.5, 2.5]),
        "height": np.array([[0.5, 0.5], [0.5, 2.5]]),
        "span": np.array([[0.0, 2.5], [0.5, 2.5]]),
    }
    plots.plot_blocks(result, tmp_path / "blocks.png")
    boxes = [box for gid, _, box in drawn["blocks.png"]["texts"] if gid == "monitor label"]
    assert len(boxes) == 3
    for i in range(3):
        for j in range(i + 1, 3):
            assert not boxes[i].overlaps(boxes[j]), (i, j)


def test_monitor_marker_follows_the_rock_point(tmp_path, drawn):
    result = make_result(moving=True)
    result.monitors["crown"]["displacement"] = [0.9, -0.3]  # a block that slid
    plots.plot_blocks(result, tmp_path / "blocks.png")
    marker = [(x, y) for gid, x, y, _ in drawn["blocks.png"]["lines"]
              if gid == "monitor point crown"]
    assert len(marker) == 1
    assert marker[0][0] == pytest.approx([0.5 + 0.9])
    assert marker[0][1] == pytest.approx([2.5 - 0.3])


def test_displacement_legend_has_no_exponent(tmp_path, drawn):
    result = make_result(moving=True)
    result.blocks[2]["u"] = [1.0, 0.0, 0.0]  # 1 m: used to read "max 1e+03 mm"
    plots.plot_blocks(result, tmp_path / "blocks.png")
    legend = " ".join(drawn["blocks.png"]["legend"])
    assert "max 1.000 m" in legend
    assert "e+" not in legend
    assert plots.format_length(4.05e-3) == "4.05 mm"
    assert plots.format_length(0.25) == "250 mm"
    assert plots.format_length(2.5e-5) == "25 um"


def test_water_table_is_drawn(tmp_path, drawn):
    result = make_result()
    table = np.array([[-0.5, 2.5], [2.5, 1.5]])
    result.geometry["water_table"] = table
    plots.plot_blocks(result, tmp_path / "blocks.png")
    lines = [(x, y) for gid, x, y, _ in drawn["blocks.png"]["lines"] if gid == "water table"]
    assert len(lines) == 1
    np.testing.assert_allclose(np.column_stack(lines[0]), table)
    assert "water table" in drawn["blocks.png"]["legend"]


def test_open_contacts_that_never_carried_force_are_not_drawn(tmp_path, drawn):
    result = make_result()
    c = result.geometry["contacts"]
    # Three open contacts: one that carried 50 kN/m before the first stage (opened by
    # the analysis), two far-field corners that carried nothing.
    c["points"] = np.vstack([c["points"], [[0.0, 0.5], [2.0, 0.5]]])
    c["normals"] = np.tile([0.0, 1.0], (7, 1))
    c["state"] = np.concatenate([c["state"], [OPEN, OPEN]])
    c["fn"], c["fs"] = np.zeros(7), np.zeros(7)
    c["initial_fn"] = np.array([10.0, 10.0, 10.0, 50.0, 10.0, 0.0, 1e-13])
    plots.plot_blocks(result, tmp_path / "blocks.png")
    red = [col for col in drawn["blocks.png"]["collections"]
           if len(col.get_facecolors()) and np.allclose(
               col.get_facecolors()[0][:3], matplotlib.colors.to_rgb("tab:red"))]
    assert len(red) == 1
    np.testing.assert_allclose(red[0].get_offsets(), [[2.0, 2.0]])
    assert any("opened (1; 2 open" in t for t in drawn["blocks.png"]["legend"])


def test_monitor_history_axis_only_grows(tmp_path, drawn):
    # Two stages of two steps: the load factor goes 0.5, 1, 0.5, 1, which used to be drawn
    # as a line dropping back between stages; the x axis is now stage + load factor.
    result = make_result()
    plots.plot_monitor_history(result, tmp_path / "monitors.png")
    fig = drawn["monitors.png"]
    assert not any("load factor" == label for *_, label in fig["lines"])
    assert len(fig["axes"]) == 1  # no twin load-factor axis
    series = [(x, y) for gid, x, y, label in fig["lines"] if len(x) > 1]
    assert series
    xs = np.concatenate([x for x, _ in series])
    # The reference record before the first stage is squeezed to a narrow span.
    assert xs.min() == 0.0 and xs.max() == pytest.approx(1.0 + plots_monitors._REFERENCE_WIDTH)
    for x, _ in series:
        assert np.all(np.diff(x) >= 0)
    x, stages = plots.stage_axis(result.history)
    assert stages == ["gravity", "excavate"]
    np.testing.assert_allclose(x, [0.5, 1.0, 1.5, 2.0])


def test_stress_bar_scale_covers_the_peak(tmp_path, drawn):
    result = make_tunnel_result()
    result.geometry["stress"][4] = [8771.0, 100.0, 0.0]  # a peak 30 times the field
    plots.plot_principal_stresses(result, tmp_path / "stresses.png")
    fig = drawn["stresses.png"]
    note = next(t for t in fig["legend"] if t.startswith("scale: 1 m = "))
    kpa_per_m = float(note.split("= ")[1].split(" kPa")[0])
    bars = [c for c in fig["collections"] if isinstance(c, matplotlib.collections.LineCollection)
            and len(c.get_segments()) == 2 * 10]
    assert len(bars) == 1
    lengths = [np.hypot(*(s[1] - s[0])) for s in bars[0].get_segments()]
    assert max(lengths) * kpa_per_m == pytest.approx(8771.0, rel=1e-9)
    assert "largest stress 8771 kPa" in note


def test_sections_use_one_reference_state(tmp_path, drawn):
    result = make_tunnel_result()
    result.stages = [
        {"name": "loading", "monitors": {"s1": [5e-3, 9e-3], "crown": [4e-3, 8e-3]}},
        {"name": "excavate", "monitors": {"s1": [1e-3, 2.5e-3], "crown": [1e-3, 3e-3]}},
        {"name": "bench", "monitors": {"s1": [3e-3], "crown": [4e-3]}},
    ]
    plots.plot_sections(result, tmp_path / "sections.png")
    fig = drawn["sections.png"]
    assert fig["legend"] == ["excavate", "bench"]  # "loading" counts from another state
    labels = [t for gid, t, _ in fig["texts"]]
    assert "9" not in labels and "2.5" in labels and "3" in labels


# ----------------------------------------------- "No picture the rock cannot take": figures


def make_big_tunnel_result(n: int = 20, side: float = 3.0) -> Result:
    """A 60 m x 60 m model of 3 m squares with a 6 m x 6 m opening in the middle (the
    excavation "tunnel", 50 kPa of support), a fan of eight roof bolts (one not
    installed) and block stresses: a tunnel at the scale of its model."""
    initial = [_square(side * i - 30.0, side * j - 30.0, side) for j in range(n) for i in range(n)]
    centres = np.array([v.mean(axis=0) for v in initial])
    excavated = (np.abs(centres) < side).all(axis=1)
    outline = np.array([[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]])
    angles = np.radians(np.linspace(60.0, 120.0, 8))
    bolts = [np.array([[2.9 * np.cos(a) / max(abs(np.sin(a)), 0.5), 3.0],
                       [7.0 * np.cos(a), 3.0 + 4.0 * np.sin(a)]]) for a in angles]
    stress = np.tile([1500.0, 800.0, 100.0], (len(initial), 1))
    stress[excavated] = 0.0
    result = make_result()
    result.scene = "big tunnel"
    result.monitors = {}
    result.blocks = [{"id": k, "centroid": centres[k].tolist(), "u": [0.0, -1e-3, 0.0],
                      "stress": stress[k].tolist(), "fixed": False,
                      **({"excavated": True} if excavated[k] else {})}
                     for k in range(len(initial))]
    result.bolts = [{"id": k, "force": 80.0 + k, "state": "elastic"} for k in range(8)]
    result.bolts[3]["state"] = "not installed"
    result.moving_blocks = []
    result.geometry = {
        "initial_vertices": initial, "final_vertices": initial,
        "fixed": np.zeros(len(initial), dtype=bool), "excavated": excavated,
        "walls": [], "contacts": {}, "monitors": {}, "bolts": bolts,
        "stress": stress, "centroids": centres,
        "excavations": {"tunnel": outline},
        "supports": [{"excavation": "tunnel", "pressure": 50.0, "stage": None}],
    }
    return result


@pytest.fixture
def drawn_axes(monkeypatch):
    """{file name: [(axes, its texts' boxes by gid, its bolt segments in pixels)]}, taken
    when each figure is saved."""
    figures: dict = {}

    def keep(fig, path):
        renderer = fig.canvas.get_renderer()
        panels = []
        for ax in fig.axes:
            texts = [(str(t.get_gid()), t.get_text(), t.get_window_extent(renderer))
                     for t in ax.texts if t.get_visible()]
            bolts = [ax.transData.transform(seg) for c in ax.collections
                     if str(c.get_gid()).startswith("bolts ") for seg in c.get_segments()]
            panels.append(dict(ax=ax, texts=texts, bolts=bolts, xlim=ax.get_xlim(),
                               ylim=ax.get_ylim(), title=ax.get_title(),
                               xlabel=ax.get_xlabel(),
                               collections={str(c.get_gid()): c for c in ax.collections},
                               patches=list(ax.patches)))
        figures[path.name] = dict(panels=panels, size=tuple(fig.get_size_inches()))

    monkeypatch.setattr(plots_canvas, "inspect", keep)
    return figures


def test_zoom_panel_around_the_excavations(tmp_path, drawn_axes):
    plots.plot_blocks(make_big_tunnel_result(), tmp_path / "blocks.png")
    panels = drawn_axes["blocks.png"]["panels"]
    assert len(panels) == 2
    whole, zoom = panels
    (x0, x1), (y0, y1) = zoom["xlim"], zoom["ylim"]
    assert x0 <= -3.0 and x1 >= 3.0 and y0 <= -3.0 and y1 >= 3.0  # the opening is in view
    assert y1 >= 7.0  # and the bolts' far ends
    width = whole["xlim"][1] - whole["xlim"][0]
    assert (x1 - x0) < 0.4 * width and (y1 - y0) < 0.4 * width
    assert "around the excavations" in zoom["title"]
    # A frame on the whole model says where the zoom is.
    frames = [p for p in whole["patches"] if p.get_gid() == "zoom frame"]
    assert len(frames) == 1
    # A window given by the caller (jaxdem run --view) replaces the automatic one.
    plots.plot_blocks(make_big_tunnel_result(), tmp_path / "blocks.png", view=(-10, 10, -5, 12))
    zoom = drawn_axes["blocks.png"]["panels"][1]
    assert zoom["xlim"] == pytest.approx((-10, 10)) and zoom["ylim"] == pytest.approx((-5, 12))
    with pytest.raises(ValueError, match="view"):
        plots.plot_blocks(make_big_tunnel_result(), tmp_path / "b.png", view=(1, 0, 0, 1))


def test_no_zoom_panel_without_excavations(tmp_path, drawn_axes):
    plots.plot_blocks(make_result(), tmp_path / "blocks.png")
    assert len(drawn_axes["blocks.png"]["panels"]) == 1


def test_bolt_labels_neither_overlap_nor_sit_on_a_bolt(tmp_path, drawn_axes):
    from matplotlib.path import Path as MplPath

    result = make_big_tunnel_result()
    plots.plot_blocks(result, tmp_path / "blocks.png")
    zoom = drawn_axes["blocks.png"]["panels"][1]
    labels = [(text, box) for gid, text, box in zoom["texts"] if gid.startswith("bolt label")]
    written = {text for text, _ in labels}
    assert labels and "83 kN" not in written  # bolt 3 is not installed: no force
    for i, (_, a) in enumerate(labels):
        for _, b in labels[i + 1:]:
            assert not a.overlaps(b)
        for seg in zoom["bolts"]:
            assert not MplPath(seg).intersects_bbox(a, filled=False)
    # The whole-model panel leaves the forces to the zoom.
    whole = drawn_axes["blocks.png"]["panels"][0]
    assert not [gid for gid, *_ in whole["texts"] if gid.startswith("bolt label")]


def test_bolt_not_installed_is_light_and_dotted(tmp_path, drawn_axes):
    plots.plot_blocks(make_big_tunnel_result(), tmp_path / "blocks.png")
    quiet = drawn_axes["blocks.png"]["panels"][1]["collections"]["bolts not installed"]
    assert len(quiet.get_segments()) == 1
    assert quiet.get_color()[0][:3] == pytest.approx(matplotlib.colors.to_rgb("0.7"))
    assert quiet.get_linestyle()[0][1] is not None  # dashed pattern, not solid


def test_support_pressure_is_drawn_on_the_opening(tmp_path, drawn_axes):
    plots.plot_blocks(make_big_tunnel_result(), tmp_path / "blocks.png")
    zoom = drawn_axes["blocks.png"]["panels"][1]
    band = zoom["collections"]["support tunnel"]
    points = np.concatenate(band.get_segments())
    # On the outline of the 6 m square opening: |x| = 3 or |y| = 3.
    assert np.all(np.isclose(np.abs(points), 3.0).any(axis=1))
    assert "support arrows tunnel" in zoom["collections"]
    assert any(gid == "support label" and text == "50 kPa" for gid, text, _ in zoom["texts"])


def test_support_band_only_where_rock_is_left_behind(tmp_path, drawn_axes):
    result = make_big_tunnel_result()
    # The blocks under the opening's floor are excavated too (a bench): no rock to push on.
    centres = np.array(result.geometry["centroids"])
    floor = (np.abs(centres[:, 0]) < 3.0) & (centres[:, 1] > -6.0) & (centres[:, 1] < -3.0)
    result.geometry["excavated"] = result.geometry["excavated"] | floor
    plots.plot_blocks(result, tmp_path / "blocks.png")
    band = drawn_axes["blocks.png"]["panels"][1]["collections"]["support tunnel"]
    points = np.concatenate(band.get_segments())
    assert not np.any(np.isclose(points[:, 1], -3.0) & (np.abs(points[:, 0]) < 2.9))


def test_a_single_small_moving_block_is_seen(tmp_path, drawn_axes):
    result = make_big_tunnel_result()
    small = _square(-0.2, 3.0, 0.3)  # a 0.3 m block in the crown of a 60 m model
    result.geometry["initial_vertices"] = result.geometry["initial_vertices"] + [small]
    result.geometry["final_vertices"] = result.geometry["initial_vertices"]
    result.geometry["excavated"] = np.append(result.geometry["excavated"], False)
    result.geometry["fixed"] = np.append(result.geometry["fixed"], False)
    k = len(result.geometry["initial_vertices"]) - 1
    result.moving_blocks = [k]
    plots.plot_blocks(result, tmp_path / "blocks.png")
    whole, zoom = drawn_axes["blocks.png"]["panels"]
    # Filled and outlined in both panels, and ringed where it is small for the panel.
    for panel in (whole, zoom):
        fill = panel["collections"]["moving blocks"]
        assert fill.get_facecolor()[0][3] > 0  # filled, not only outlined
        np.testing.assert_allclose(fill.get_paths()[0].vertices[:4], small)
    ring = whole["collections"]["moving ring"]
    np.testing.assert_allclose(ring.get_offsets(), [small.mean(axis=0)])
    assert ring.get_sizes()[0] >= 100  # points^2: about 20 points across
    (x0, x1), (y0, y1) = zoom["xlim"], zoom["ylim"]
    assert x0 < -0.2 and x1 > 0.1 and y0 < 3.0 and y1 > 3.3


def test_largest_stress_bar_fits_its_block(tmp_path, drawn):
    result = make_big_tunnel_result()
    result.geometry["stress"][0] = [8000.0, 100.0, 0.0]  # a peak five times the field
    plots.plot_principal_stresses(result, tmp_path / "stresses.png")
    fig = drawn["stresses.png"]
    bars = [c for c in fig["collections"] if c.get_gid() == "stress bars"]
    assert len(bars) == 2  # the whole model and the panel around the opening
    assert len(bars[0].get_segments()) == 2 * int((~result.geometry["excavated"]).sum())
    lengths = np.array([np.hypot(*(s[1] - s[0])) for s in bars[0].get_segments()])
    assert lengths.argmax() // 2 == 0  # the peak's bar is the longest
    assert lengths.max() <= 3.0  # and no longer than its 3 m block
    assert lengths.max() >= 1.0  # yet drawn large enough to read
    room = plots_model.block_room(result.geometry["initial_vertices"][:1],
                                  np.array([[-28.5, -28.5]]))
    assert room == pytest.approx([3.0])
    diagonal = np.array([[[np.sqrt(0.5), np.sqrt(0.5)], [1.0, 0.0]]])
    along = plots_model.bar_room(result.geometry["initial_vertices"][:1],
                                 np.array([[-28.5, -28.5]]), diagonal)
    np.testing.assert_allclose(along, [[3.0 * np.sqrt(2.0), 3.0]])
    # A key bar of a round stress.
    texts = [t for _, t, _ in fig["texts"]] + fig["legend"]
    assert any("scale: 1 m = " in t for t in texts)


def test_tornado_names_the_monitor_and_stays_readable(tmp_path, drawn_axes):
    def bars(quantity):
        return [dict(path=f"joints.j{k}.kn", low=1e6, base=2e6, high=4e6, at_base=2e-3,
                     at_low=3e-3 - 2e-4 * k, at_high=1e-3 + 2e-4 * k, swing=-2e-3 + 4e-4 * k,
                     quantity=quantity) for k in range(3)]

    tornado = {"crown": bars("|u|"), "span": bars("convergence"), "height": bars("convergence"),
               "wall": bars("|u|")}
    plots.plot_tornado(tornado, tmp_path / "tornado.png")
    fig = drawn_axes["tornado.png"]
    labels = [p["xlabel"] for p in fig["panels"] if p["xlabel"]]
    assert "crown |u| (mm)" in labels and "span convergence (mm)" in labels
    width, height = fig["size"]
    assert width / height < 3.0  # four monitors in one row made it 26 x 3 inches


def test_reference_state_takes_a_small_part_of_the_stage_axis(tmp_path, drawn_axes):
    result = make_result()  # two stages: "gravity" (the reference) and "excavate"
    plots.plot_monitor_history(result, tmp_path / "monitors.png")
    panel = drawn_axes["monitors.png"]["panels"][0]
    shade = [p for p in panel["patches"] if p.get_gid() == "reference state"]
    assert len(shade) == 1
    x = shade[0].get_patch_transform().transform(shade[0].get_path().vertices)[:, 0]
    span = panel["xlim"][1] - panel["xlim"][0]
    assert (x.max() - x.min()) / span <= 0.15


def test_a_bar_in_a_sliver_is_cut_at_its_edge(tmp_path, drawn):
    # A 0.1 m x 3 m sliver carrying 20 times the field stress across its width: the
    # scale is set by the ordinary 3 m blocks, and the sliver's bar ends at its faces.
    result = make_big_tunnel_result()
    sliver = np.array([[27.0, -30.0], [27.1, -30.0], [27.1, -27.0], [27.0, -27.0]])
    g = result.geometry
    g["initial_vertices"] = g["initial_vertices"] + [sliver]
    g["final_vertices"] = g["initial_vertices"]
    g["excavated"] = np.append(g["excavated"], False)
    g["fixed"] = np.append(g["fixed"], False)
    g["stress"] = np.vstack([g["stress"], [30000.0, 100.0, 0.0]])
    g["centroids"] = np.vstack([g["centroids"], [27.05, -28.5]])
    plots.plot_principal_stresses(result, tmp_path / "stresses.png")
    fig = drawn["stresses.png"]
    bars = [c for c in fig["collections"] if c.get_gid() == "stress bars"][0]
    segments = bars.get_segments()
    sliver_bars = segments[-2:]
    lengths = [np.hypot(*(s[1] - s[0])) for s in sliver_bars]
    assert max(lengths) == pytest.approx(0.1)  # across the sliver: cut at its faces
    note = next(t for t in fig["legend"] if t.startswith("scale: 1 m = "))
    assert "1 bars in blocks smaller than" in note
    kpa_per_m = float(note.split("= ")[1].split(" kPa")[0])
    assert 1500.0 / kpa_per_m > 0.1  # the ordinary blocks' bars stay readable
    others = np.array([np.hypot(*(s[1] - s[0])) for s in segments[:-2]])
    assert others.max() <= 3.0


def test_blocks_out_of_balance_are_drawn_and_named(tmp_path, drawn_axes):
    # An analysis stopped at the iteration limit: its blocks out of balance are filled
    # and outlined in goldenrod in both panels, and the title's status names them.
    result = make_big_tunnel_result()
    result.status, result.converged = "iteration_limit", False
    ids = [0, 3]
    result.unbalanced_blocks = [dict(id=i, centroid=[0.0, 0.0], force=10.0, relative=0.5)
                                for i in ids]
    plots.plot_blocks(result, tmp_path / "blocks.png")
    for panel in drawn_axes["blocks.png"]["panels"]:
        fill = panel["collections"]["out of balance blocks"]
        assert len(fill.get_paths()) == len(ids)
        assert fill.get_edgecolor()[0][:3] == pytest.approx(matplotlib.colors.to_rgb("goldenrod"))
        for path, i in zip(fill.get_paths(), ids, strict=True):
            block = np.asarray(result.geometry["final_vertices"][i])
            np.testing.assert_allclose(path.vertices[:len(block)], block)
    assert (plots_model._status_text(result)
            == "NOT CONVERGED (iteration_limit): blocks 0, 3 out of balance")
