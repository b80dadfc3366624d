"""The data that live inside jit are typed pytrees, not dicts with string keys (issue 30,
item 3; STYLE.md habit 3): a sub-step's data (jaxdem.core._springs.Sub), the springs'
evaluation (Springs), what a sub-step returns and the increment's report. The one dict
allowed is a map of a dataclass's fields to their derivatives (``dstate``: it is applied
with dataclasses.replace)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest
from scenes import jointed_tunnel

from jaxdem.core import model as model_mod
from jaxdem.core._springs import Springs, evaluate
from jaxdem.core._substep import force_scales, newton_and_commit, prepare_substep
from jaxdem.core.increment import Progress, increment
from jaxdem.core.loads import make_loads
from jaxdem.scene import parse_scene


def _dict_paths(tree) -> list[str]:
    """Where ``tree`` holds a dict (the paths of the leaves below one)."""
    leaves = jax.tree_util.tree_leaves_with_path(tree, is_leaf=lambda x: x is None)
    return [jax.tree_util.keystr(path) for path, _ in leaves
            if any(isinstance(k, jax.tree_util.DictKey) for k in path)]


@pytest.fixture(scope="module")
def tunnel():
    """A jointed tunnel with water and a bolt (every optional part of a sub-step's data)."""
    model, state, _ = model_mod.build(parse_scene(jointed_tunnel(water=True, bolts=True)))
    return model, state, make_loads(model, model.f_ext)


def test_a_substeps_data_and_outputs_hold_no_dict(tunnel):
    model, state, loads = tunnel
    mdl, sub, st0, pairs, found = prepare_substep(model, state, loads)
    assert sub.bolt is not None and model.has_water  # the bolts' and water's fields are there
    assert _dict_paths((sub, found)) == []
    S = st0.shape[0]
    ev = evaluate(mdl, sub, jnp.zeros((mdl.n_blocks, mdl.ndof)), jnp.zeros(S, bool), st0, st0,
                  force_scales(mdl, sub)[1])
    assert isinstance(ev, Springs) and ev.bolt_force is not None
    assert _dict_paths(ev) == []
    new, du, newton, need, balance, snapshot = newton_and_commit(mdl, state, sub, st0, pairs,
                                                                 found)
    assert _dict_paths((newton, need, balance, snapshot)) == []


def test_the_increments_report_holds_no_dict(tunnel):
    model, state, loads = tunnel
    new, report = increment(model, state, loads)
    assert isinstance(report, Progress) and report.dstate is None and report.joints is not None
    assert _dict_paths(report) == []
