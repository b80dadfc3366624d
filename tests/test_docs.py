"""The user documentation: docs/scene-format.md documents every field the parser accepts,
and the README's code runs as written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from jaxdem.scene import OVERLAP_TOLERANCE
from jaxdem.scene import _schema as scene_schema

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "scene-format.md"

# Section -> the parser's tuple of accepted fields (read from jaxdem.scene._schema, so that a
# field added to the parser fails here until it is documented).
SECTIONS = {
    "scene": "SCENE_FIELDS",
    "solver": "SOLVER_FIELDS",
    "materials": "MATERIAL_FIELDS",
    "joints": "JOINT_FIELDS",
    "blocks": "BLOCK_FIELDS",
    "discontinuities": "DISCONTINUITY_FIELDS",
    "domain": "DOMAIN_FIELDS",
    "zones": "ZONE_FIELDS",
    "excavations": "EXCAVATION_FIELDS",
    "boundaries": "BOUNDARY_FIELDS",
    "in_situ": "IN_SITU_FIELDS",
    "bolts": "BOLT_FIELDS",
    "supports": "SUPPORT_FIELDS",
    "water": "WATER_FIELDS",
    "stages": "STAGE_FIELDS",
    "monitors": "MONITOR_FIELDS",
}


def documented_fields() -> dict[str, set[str]]:
    """{section: fields in the first column of its table} from the doc's "## `[...]`"
    headings."""
    out: dict[str, set[str]] = {}
    section = None
    for line in DOC.read_text().splitlines():
        heading = re.match(r"^## `\[\[?([a-z_]+)(?:\.NAME)?\]\]?`", line)
        if heading:
            section = heading.group(1)
            out[section] = set()
            continue
        if line.startswith("## "):
            section = None
            continue
        row = re.match(r"^\| `([a-zA-Z_0-9]+)` \|", line)
        if section is not None and row:
            out[section].add(row.group(1))
    return out


def test_every_section_is_documented():
    assert set(documented_fields()) == set(scene_schema.SUPPORTED_SECTIONS)
    assert set(SECTIONS) == set(scene_schema.SUPPORTED_SECTIONS)


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_every_accepted_field_is_documented(section):
    accepted = set(getattr(scene_schema, SECTIONS[section]))
    if section == "bolts":
        accepted.add("compression")  # documented ahead of the bolt change (issue 16)
    documented = documented_fields()[section]
    assert accepted - documented == set(), f"[{section}] fields missing from {DOC.name}"
    assert documented - accepted <= ({"compression"} if section == "bolts" else set()), (
        f"[{section}] documents fields the parser refuses")


def test_the_doc_states_the_conventions_and_tolerances():
    text = DOC.read_text()
    assert "trace angle" in text and "not* the geological dip" in text
    assert "compression positive" in text.lower()
    assert OVERLAP_TOLERANCE == 1e-5 and "1e-5 of the smaller block's size" in text
    assert "stage = 2" in text


def test_readme_links_the_scene_reference():
    readme = (ROOT / "README.md").read_text()
    assert "docs/scene-format.md" in readme
    assert "SPEC.md" not in readme  # users never get the shared folder


def _readme_block(marker: str) -> str:
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    return next(b for b in blocks if marker in b)


def test_readme_gradient_example_runs_as_written(monkeypatch):
    """The README's jax.grad / jacfwd / jit / vmap(grad) lines, on the scene they name."""
    monkeypatch.chdir(ROOT)
    code = _readme_block("jax.vmap(jax.grad")
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102
    g, gs = namespace["g"], namespace["gs"]
    assert np.shape(g) == (2,) and np.all(np.isfinite(g))
    # vmap(grad) over two copies of theta0 gives the same gradient twice.
    np.testing.assert_allclose(np.asarray(gs), np.stack([g, g]), rtol=1e-9)
