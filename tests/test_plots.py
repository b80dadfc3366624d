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
    assert xs.min() == 0.0 and xs.max() == 2.0
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
    assert "largest bar 8771 kPa" in note


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
