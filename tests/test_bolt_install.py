"""Bolts of a stage that never ran: result.json says ``not installed`` (force 0), not
"elastic, 0 kN"; bolts whose stage ran keep their real state.

The scene is tests/verification/test_bolts.py's key block (Hoek & Brown, Underground
Excavations in Rock, ch. 9: the bolts carry the loosened wedge's weight W = 58.5 kN/m)
under a uniform in-situ stress of zero, so that the wedge's weight is a load of the
first stage. Two bolts of yield force 20 kN, installed in stage 1, cannot hold it (2 x 20
< 58.5): the wedge falls in stage 1, both bolts yield at exactly their yield force
(elasto-plastic tendon), and the analysis stops there. The third bolt belongs to stage
2, which never runs.
"""

from __future__ import annotations

from verification.test_bolts import key_block

import jaxdem
from jaxdem.cli._summaries import result_summary
from jaxdem.scene import parse_scene

YIELD = 20.0  # kN


def _scene() -> dict:
    stages = [{"name": "first"}, {"name": "second"}]
    bolts = [((-0.4, 0.15), (-0.4, 2.6)), ((0.4, 0.15), (0.4, 2.6)), ((0.0, 0.5), (0.0, 2.5))]
    d = key_block(bolts, yield_force=YIELD, in_situ=True, stages=stages)
    d["bolts"][0]["stage"] = "first"
    d["bolts"][1]["stage"] = 1  # by number, as the file may give it
    d["bolts"][2]["stage"] = "second"
    return d


def test_bolt_of_a_stage_that_never_ran_is_not_installed():
    r = jaxdem.solve(parse_scene(_scene()))
    assert r.status == "mechanism"
    assert [s["name"] for s in r.stages] == ["initial", "first"]  # "second" never ran
    first, second, later = r.to_dict()["bolts"]
    # The stage-1 bolts acted: both yielded at their yield force (2 x 20 kN < W).
    for bolt in (first, second):
        assert bolt["state"] == "yielded"
        assert abs(bolt["force"] - YIELD) < 1e-9 * YIELD
    assert later == {"id": 2, "force": 0.0, "force_per_m": 0.0, "state": "not installed",
                     "compression_capacity": 0.0}
    # The summary printed after a run does not call it an elastic bolt at 0 kN.
    text = result_summary(r)
    line = next(ln for ln in text.splitlines() if ln.startswith("bolts:"))
    assert line.startswith("bolts: 2 yielded, 1 not installed; largest force 20 kN")
    assert "elastic" not in line and "0 kN" not in line.replace("20 kN", "")


def test_every_bolt_is_installed_when_every_stage_ran():
    # The same bolts on an unloaded wedge (no self-weight): every stage runs, the
    # third bolt is installed in stage 2 and carries nothing (elastic, 0 kN is its
    # real state here).
    d = _scene()
    d["materials"]["rock"]["unit_weight"] = 0.0
    r = jaxdem.solve(parse_scene(d))
    assert r.converged and [s["name"] for s in r.stages] == ["initial", "first", "second"]
    assert [b["state"] for b in r.bolts] == ["elastic"] * 3
    assert all(abs(b["force"]) < 1e-9 for b in r.bolts)
