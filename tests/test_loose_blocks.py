"""Loose blocks: small joint-bounded blocks bonded at generation (``domain.min_block_area``)
and small blocks that fall free in a stage removed, the stage solved again without them
(``solver.loose_blocks``, ``solver.max_loose_volume``); a mechanism of small blocks that
were not removed is said to be small (``jaxdem.results.small_mechanism``)."""

from __future__ import annotations

import copy
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxdem
from jaxdem import geometry
from jaxdem.rockmass import generate
from jaxdem.scene import SceneError

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11, as jaxdem.scene reads TOML
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
TUNNEL = ROOT / "tests" / "data" / "loose_roof_tunnel.toml"


def _bodies(pieces) -> dict[int, list[int]]:
    """Rock bodies: pieces joined by faces that are intact rock on both sides."""
    polys = [p.vertices for p in pieces]
    root = list(range(len(polys)))

    def find(i):
        while root[i] != i:
            i = root[i]
        return i

    q = 1e-7 * 20.0
    keys = [np.round(v / q).astype(int) for v in polys]
    ends = {(*k[e], *np.roll(k, -1, axis=0)[e]): (i, e) for i, k in enumerate(keys)
            for e in range(len(k))}
    for (x0, y0, x1, y1), (i, e) in ends.items():
        other = ends.get((x1, y1, x0, y0))
        if other is None:
            continue
        j, m = other
        if (pieces[i].excavation == pieces[j].excavation
                and pieces[i].edge_labels[e][0] == pieces[j].edge_labels[m][0] == "intact"):
            root[find(i)] = find(j)
    out: dict[int, list[int]] = {}
    for i in range(len(polys)):
        out.setdefault(find(i), []).append(i)
    return out


def _scene(data: dict, **sets):
    return jaxdem.load_scene(copy.deepcopy(data), set=sets or None)


def _tunnel() -> dict:
    return tomllib.loads(TUNNEL.read_text())


# --- generation -----------------------------------------------------------------------


def test_default_threshold_is_below_every_block_of_the_regular_pattern():
    """Two persistent sets at spacings s1, s2 and angle a make parallelograms of area
    s1 s2 / sin a >= s_min^2; the default min_block_area (0.1 s_min^2) bonds none of them:
    a 10 m square cut by two orthogonal 1 m sets keeps all its 100 blocks joint-bounded."""
    data = {
        "scene": {"name": "two orthogonal sets"},
        "materials": {"rock": {"E": 1e7, "nu": 0.2, "unit_weight": 26.0}},
        "joints": {"a": {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0, "dip_deg": 0.0,
                         "spacing": 1.0, "origin": [0.0, 0.0]},
                   "b": {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0, "dip_deg": 90.0,
                         "spacing": 1.0, "origin": [0.0, 0.0]}},
        "domain": {"outline": [[0, 0], [10, 0], [10, 10], [0, 10]], "material": "rock"},
    }
    rm = generate(_scene(data))
    assert len(rm.pieces) == 100
    assert all(kind != "intact" for p in rm.pieces for kind, _ in p.edge_labels)
    # The tunnel's sets (1.5 m at 80 degrees): the smallest regular block against the default.
    tunnel = _scene(_tunnel())
    s = [j.spacing for j in tunnel.joints.values() if j.is_set]
    regular = s[0] * s[1] / math.sin(math.radians(80.0))
    assert 0.1 * min(s) ** 2 < regular


def _on_opening(piece, scene) -> bool:
    """Whether an edge of the piece lies on an excavation's outline (its midpoint does)."""
    v = piece.vertices
    mids = 0.5 * (v + np.roll(v, -1, axis=0))
    return any(geometry.distance_to_boundary(m, np.asarray(e.vertices, float)) < 1e-6
               for e in scene.excavations for m in mids)


def test_slivers_that_the_opening_cuts_off_are_bonded_and_areas_kept():
    """Default min_block_area on the tunnel: no rock body (pieces joined by intact rock)
    on an opening's outline below 0.1 s^2 = 0.225 m2 is left; the pieces are the same
    convex polygons (areas sum to the domain's to 1e-9); bodies away from the openings
    (the domain's corners) are not touched; with min_block_area = 0 the roof wedge
    (0.14 m2) and smaller slivers are bodies of their own."""
    data = _tunnel()
    scene = _scene(data)
    merged = generate(scene).pieces
    plain = generate(_scene(data, **{"domain.min_block_area": 0.0})).pieces
    a_merged = geometry.signed_areas([p.vertices for p in merged])
    a_plain = geometry.signed_areas([p.vertices for p in plain])
    assert np.array_equal(a_merged, a_plain)  # geometry untouched
    assert abs(a_merged.sum() - 14.0 * 14.0) <= 1e-9 * 196.0
    for v in (p.vertices for p in merged):
        assert len(v) >= 3 and geometry.signed_area(v) > 0
        assert len(geometry.convex_hull(v)) == len(v)  # strictly convex
    threshold = 0.1 * 1.5**2

    def small(pieces, areas, at_opening):
        return sorted(round(sum(areas[i] for i in members), 4)
                      for members in _bodies(pieces).values()
                      if pieces[members[0]].excavation is None
                      and any(_on_opening(pieces[i], scene) for i in members) == at_opening
                      and sum(areas[i] for i in members) < threshold)

    before, after = small(plain, a_plain, True), small(merged, a_merged, True)
    assert before == [0.0044, 0.0225, 0.1411] and after == []  # each had a neighbour to join
    assert small(plain, a_plain, False) == small(merged, a_merged, False) != []
    wedge = _crown_wedge(plain)
    assert abs(sum(a_plain[wedge]) - 0.1411) < 1e-3


def test_min_block_area_out_of_range_is_refused_with_the_field_named():
    data = _tunnel()
    data["domain"]["min_block_area"] = -0.1
    with pytest.raises(SceneError, match=r"domain\.min_block_area"):
        jaxdem.load_scene(data)


# --- loose blocks in stages -------------------------------------------------------------


def _crown_wedge(pieces) -> list[int]:
    """The two pieces (an opening's ray cut splits it) of the wedge over the crown."""
    return [i for i, p in enumerate(pieces) if p.excavation is None
            and 1.9 < geometry.centroid(p.vertices)[1] < 2.4
            and abs(geometry.centroid(p.vertices)[0]) < 0.3]


def test_roof_sliver_is_bonded_by_default_and_both_stages_run():
    """The generator bonds the roof wedge (0.14 m2 < 0.225 m2) to its neighbour: it stays
    in the roof, and heading and bench are solved. (A 0.004 m2 piece at the corner of the
    horseshoe's wall, bonded too, breaks its bonds under the stress there, falls free and
    is removed: each removed block is far below the limit, none is the wedge.)"""
    scene = _scene(_tunnel())
    wedge = _crown_wedge(generate(scene).pieces)
    r = jaxdem.solve(scene)
    assert r.status == "converged" and r.stable
    assert [s["name"] for s in r.stages] == ["initial", "heading", "bench"]
    assert len(wedge) == 2 and not {b["id"] for b in r.loose_blocks} & set(wedge)
    assert all(b["volume"] < 0.01 for b in r.loose_blocks)


@pytest.fixture(scope="module")
def unmerged():
    """The tunnel with merging off: the roof wedge falls free in the heading."""
    return jaxdem.solve(_scene(_tunnel(), **{"domain.min_block_area": 0.0}))


def test_without_merging_the_wedge_falls_is_removed_and_the_bench_runs(unmerged):
    r = unmerged
    assert r.status == "converged" and r.stable
    assert [s["name"] for s in r.stages] == ["initial", "heading", "bench"]
    assert all(s["converged"] for s in r.stages)
    loose = r.loose_blocks
    assert loose and all(b["stage"] == "heading" for b in loose)
    areas = geometry.signed_areas(r.geometry["initial_vertices"])
    for b in loose:
        assert b["volume"] == pytest.approx(areas[b["id"]], rel=1e-12)  # m3 per m = area
        assert b["volume"] <= 0.1 * 1.5**2  # the default limit, 0.1 s^2
    crown = [b for b in loose if abs(b["centroid"][0]) < 0.3 and b["centroid"][1] > 1.9]
    assert sum(b["volume"] for b in crown) == pytest.approx(0.1411, abs=1e-3)  # the wedge
    d = r.to_dict()
    assert d["loose_blocks"] == loose and "Loose blocks removed" in d["message"]
    assert r.geometry["loose"][[b["id"] for b in loose]].all()


def test_the_figure_shows_the_loose_blocks(unmerged, tmp_path):
    """blocks.png draws each removed block where it was, hatched, with a legend entry."""
    from matplotlib.figure import Figure

    from jaxdem.plots import write_figures
    from jaxdem.plots._loose import draw_loose_blocks

    paths = write_figures(unmerged, tmp_path)
    assert (tmp_path / "blocks.png") in [Path(p) for p in paths]
    ax = Figure().add_subplot()
    handles = draw_loose_blocks(ax, unmerged.geometry["initial_vertices"],
                                unmerged.loose_blocks, 0.5)
    assert [h.get_label() for h in handles] == [f"loose, removed ({len(unmerged.loose_blocks)})"]
    assert len(ax.collections[0].get_paths()) == len(unmerged.loose_blocks)
    assert draw_loose_blocks(ax, unmerged.geometry["initial_vertices"], [], 0.5) == []


def test_the_bench_equals_a_solve_with_the_loose_blocks_excavated_by_hand(unmerged):
    """Removing a loose block is excavating it in the stage it fell in: the same scene with
    those blocks added to the heading by hand gives the same answer to 1e-6."""
    data = _tunnel()
    polys = unmerged.geometry["initial_vertices"]
    for b in unmerged.loose_blocks:
        data.setdefault("excavations", []).append(dict(
            name=f"loose{b['id']}", shape="polygon", stage="heading",
            vertices=np.asarray(polys[b["id"]]).tolist()))
    hand = jaxdem.solve(_scene(data, **{"domain.min_block_area": 0.0}))
    assert hand.status == "converged" and hand.loose_blocks == []
    u = np.array([b["u"] for b in unmerged.blocks])
    u_hand = np.array([b["u"] for b in hand.blocks])
    assert np.max(np.abs(u - u_hand)) <= 1e-6 * max(1e-3, np.max(np.abs(u_hand[:, :2])))
    assert unmerged.monitors["span"]["convergence"] == pytest.approx(
        hand.monitors["span"]["convergence"], rel=1e-6)


def _prop_scene(slope_deg: float) -> dict:
    """A 1 x 0.5 m block on a fixed base inclined at ``slope_deg``, held up by a fixed
    prop that stage "remove" excavates: on a flat base the prop is under the block (it
    then falls free), on a slope it is at the block's toe (it then slides along the base,
    frictional joint of 20 degrees)."""
    a = math.radians(slope_deg)
    t, n = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    base = [-3 * t - 2 * n, 3 * t - 2 * n, 3 * t, -3 * t]
    if slope_deg == 0.0:
        prop = [np.array(p) for p in ([-0.5, 0.0], [0.5, 0.0], [0.5, 1.0], [-0.5, 1.0])]
        block = [np.array(p) for p in ([-0.5, 1.0], [0.5, 1.0], [0.5, 1.5], [-0.5, 1.5])]
    else:
        prop = [-t, 0 * t, 0.5 * n, -t + 0.5 * n]
        block = [0 * t, t, t + 0.5 * n, 0.5 * n]
    other = [2 * t, 2.8 * t, 2.8 * t + 0.8 * n, 2 * t + 0.8 * n]  # rests on a flat base
    as_list = lambda vs: [list(map(float, v)) for v in vs]  # noqa: E731
    return {
        "scene": {"name": f"block and prop, base at {slope_deg:g} degrees"},
        "solver": {"load_steps": 1, "max_displacement": 0.4, "max_loose_volume": 1.0},
        "materials": {"rock": {"E": 1e7, "nu": 0.2, "unit_weight": 26.0}},
        "joints": {"j": {"kn": 1e6, "ks": 5e5, "friction_deg": 20.0}},
        "blocks": [{"vertices": as_list(base), "material": "rock", "fixed": True},
                   {"vertices": as_list(prop), "material": "rock", "fixed": True},
                   {"vertices": as_list(block), "material": "rock"}]
                  + ([{"vertices": as_list(other), "material": "rock"}] if a == 0 else []),
        "stages": [{"name": "remove"}],
        "excavations": [{"name": "prop", "shape": "polygon", "vertices": as_list(prop),
                         "stage": "remove"}],
    }


def test_a_block_that_falls_free_is_removed():
    """The prop under the block is excavated: the block falls (no contact in the way), is
    removed with its volume (0.5 m3/m) and the stage is solved without it."""
    r = jaxdem.solve(jaxdem.load_scene(_prop_scene(0.0)))
    assert r.status == "converged" and r.stable
    assert [(b["id"], b["stage"]) for b in r.loose_blocks] == [(2, "remove")]
    assert r.loose_blocks[0]["volume"] == pytest.approx(0.5, rel=1e-12)
    data = _prop_scene(0.0)
    data["solver"]["loose_blocks"] = "stop"
    stop = jaxdem.solve(jaxdem.load_scene(data))
    assert stop.status == "mechanism" and stop.moving_blocks == [2] and stop.loose_blocks == []
    # Not removed, and no larger than max_loose_volume (1.0): said to be small.
    assert [w for w in stop.warnings if "mechanism is small: blocks 2, 0.5 m3/m" in w]
    small = _prop_scene(0.0)
    small["solver"]["max_loose_volume"] = 0.4  # the block (0.5 m3/m) is too large
    big = jaxdem.solve(jaxdem.load_scene(small))
    assert big.status == "mechanism" and big.moving_blocks == [2] and big.loose_blocks == []
    assert not [w for w in big.warnings if "mechanism is small" in w]


def test_a_block_that_slides_along_a_joint_is_not_removed():
    """The prop at the toe is excavated: the block slides down the 30-degree base
    (tan 20 < tan 30), in contact all the way: a mechanism, reported as before."""
    r = jaxdem.solve(jaxdem.load_scene(_prop_scene(30.0)))
    assert r.status == "mechanism" and not r.stable
    assert r.moving_blocks == [2] and r.loose_blocks == []
    # A block of 0.5 m3/m (1 m x 0.5 m), max_loose_volume 1.0: a small mechanism, said so.
    small = [w for w in r.warnings if "mechanism is small" in w]
    assert len(small) == 1 and "blocks 2, 0.5 m3/m in all (solver.max_loose_volume: 1)" in small[0]


def test_a_mechanism_is_small_where_its_blocks_together_are_no_larger_than_the_limit():
    """:func:`jaxdem.results.small_mechanism` on hand-made blocks: the sum of the moving
    blocks' areas against the limit, the largest block's centroid named."""
    from jaxdem.results import small_mechanism

    area = np.array([0.035, 0.013, 2.0, 0.5])
    centroids = np.array([[-6.1, -1.0], [-6.0, -0.9], [0.0, 0.0], [3.0, 1.0]])
    said = small_mechanism([0, 1], area, 1.6, centroids)
    assert said and "blocks 0, 1, 0.048 m3/m in all" in said and "(-6.1, -1)" in said
    assert small_mechanism([0, 1], area, 0.04, centroids) is None  # 0.048 > 0.04
    assert small_mechanism([0, 1, 2], area, 1.6, centroids) is None  # with a 2 m2 block
    assert small_mechanism([0, 1], area, 0.0, centroids) is None  # no limit: no warning
    assert small_mechanism([], area, 1.6, centroids) is None


@pytest.mark.parametrize("field, value", [("loose_blocks", "drop"),
                                          ("max_loose_volume", -1.0)])
def test_bad_solver_values_are_refused_with_the_field_named(tmp_path, field, value):
    data = _prop_scene(0.0)
    data["solver"][field] = value
    with pytest.raises(SceneError, match=rf"solver\.{field}"):
        jaxdem.load_scene(data)
    text = TUNNEL.read_text().replace("[solver]\n", f"[solver]\n{field} = {value!r}\n"
                                      .replace("'", '"'))
    path = tmp_path / "bad.toml"
    path.write_text(text)
    proc = subprocess.run([sys.executable, "-m", "jaxdem", "check", str(path),
                           "--out", str(tmp_path / "out")],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and f"solver.{field}" in proc.stderr + proc.stdout


@pytest.mark.parametrize("limit, small", [(1.0, True), (0.4, False)])
def test_a_batch_says_which_of_its_mechanisms_are_small(limit, small):
    """The toe-prop block (1 m x 0.5 m: 0.5 m3/m) at joint friction 20 and 40 degrees on
    its 30-degree base, batched and one solve after another (a sweep's loop): at 20 it
    slides (tan 20 < tan 30), a mechanism of 0.5 m3/m, small where max_loose_volume is
    1.0, not at 0.4; at 40 it holds (no mechanism, volume 0). The sweep's probability
    counts the small one apart, and both paths flag it alike."""
    from jaxdem.batch import solve_batch
    from jaxdem.sweep import probability_of_instability, solve_each

    data = _prop_scene(30.0)
    data["solver"]["max_loose_volume"] = limit
    scene = jaxdem.load_scene(data)
    theta = np.array([[20.0], [40.0]])
    for b in (solve_batch(scene, ["joints.j.friction_deg"], theta),
              solve_each(scene, ["joints.j.friction_deg"], theta)):
        assert b.status == ["mechanism", "converged"]
        assert b.moving_blocks[0] == [2] and b.moving_blocks[1] == []
        assert b.moving_volume == pytest.approx([0.5, 0.0], rel=1e-12)
        assert list(b.small_mechanism) == [small, False]
        p = probability_of_instability(b)
        assert (p["unstable"], p["small"]) == (1, int(small))


@pytest.mark.parametrize("release", [None, [0.4, 0.6]])
def test_a_batch_removes_each_samples_loose_blocks_as_a_single_solve_does(release):
    """The tunnel with merging off, batched (one chunk of two samples): with no cohesion on
    the smooth discontinuities the roof wedge's three pieces fall free, with 500 kPa one
    piece; each sample removes its own, runs the stage again without them and converges,
    as its single solve: the same blocks removed, the same iterations, the span's
    convergence the same to 1e-9. With the heading's load released at once (they fall in
    the heading) and over two stages (``release``: in the bench)."""
    from jaxdem.batch import solve_batch

    data = _tunnel()
    if release is not None:
        data["excavations"][0]["release"] = release
    scene = _scene(data, **{"domain.min_block_area": 0.0})
    theta = np.array([[0.0], [500.0]])
    b = solve_batch(scene, ["joints.smooth.cohesion"], theta, chunk=2)
    assert b.status == ["converged", "converged"] and b.timing["chunk"] == 2
    for i, (c,) in enumerate(theta):
        r = jaxdem.solve(scene, set={"joints.smooth.cohesion": c})
        assert r.status == "converged" and r.loose_blocks
        assert b.loose_blocks[i] == [x["id"] for x in r.loose_blocks]
        assert b.iterations[i] == sum(sum(s["iterations"]) for s in r.stages)
        assert b.monitors["span"][i] == pytest.approx(r.monitors["span"]["convergence"],
                                                      rel=1e-9)
    assert b.loose_blocks[0] != b.loose_blocks[1]  # each sample its own


@pytest.mark.parametrize("release", [None, [0.4, 0.6]])
def test_a_batch_runs_a_stage_again_only_for_the_samples_that_lost_blocks(monkeypatch,
                                                                         release):
    """The tunnel with merging off and 500 kPa on the smooth discontinuities, batched (one
    chunk of two samples) over the joint sets' cohesion: at 0 the roof piece 150 falls, at
    500 kPa nothing falls (as their single solves). Only the first sample runs that stage
    again: the second sits the rerun out (skipped by every batched increment of it: it
    runs as many increments as its single solve), and each ends as its single solve
    (blocks removed, iterations, the span's convergence to 1e-9). With the heading's load
    released at once (the piece falls in the heading, and the second sample, held at the
    heading's end, goes on with the bench) and over two stages (``release``: in the
    bench)."""
    from jaxdem import batch

    ran = []  # each batched increment's lanes that ran (not skipped)
    compiled = batch.compiled_program

    def spy(fn_jit, *args, **kw):
        fn, dt = compiled(fn_jit, *args, **kw)
        if "mode" in kw:  # the in-situ preload
            return fn, dt

        def call(*a):
            ran.append(~np.asarray(a[-1]))
            return fn(*a)

        return call, dt

    monkeypatch.setattr(batch, "compiled_program", spy)
    data = _tunnel()
    if release is not None:
        data["excavations"][0]["release"] = release
    scene = _scene(data, **{"domain.min_block_area": 0.0, "joints.smooth.cohesion": 500.0})
    params = ["joints.set1.cohesion", "joints.set2.cohesion"]
    theta = np.array([[0.0, 0.0], [500.0, 500.0]])
    b = batch.solve_batch(scene, params, theta, chunk=2)
    assert b.status == ["converged", "converged"] and b.loose_blocks == [[150], []]
    increments = np.sum(ran, axis=0)
    for i, row in enumerate(theta):
        r = jaxdem.solve(scene, set=dict(zip(params, row, strict=True)))
        assert r.status == "converged"
        assert b.loose_blocks[i] == [x["id"] for x in r.loose_blocks]
        assert b.iterations[i] == sum(sum(s["iterations"]) for s in r.stages)
        assert b.monitors["span"][i] == pytest.approx(r.monitors["span"]["convergence"],
                                                      rel=1e-9)
        own = sum(len(s["iterations"]) for s in r.stages)
        assert increments[i] == own if i == 1 else increments[i] > own
