"""The solver's modules import one way: each only from the modules below it (issue 20).

The layers, from the bottom up, as the README's layout and each module's
docstring describe them. A module may import any module listed before it,
and the host modules outside the solver (scene, geometry, config); never one
listed after it. Every import counts, at the top of the file or inside a
function, so a late import cannot hide a circle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jaxdem"

LAYERS = ["state", "status", "compile_cache", "kinematics", "laws", "contact", "springs",
          "linsolve", "loads", "substep", "sensitivities", "increment", "results", "model",
          "solver", "differentiable", "batch", "sweep", "fos"]


def _imports(module: str) -> set[str]:
    """The jaxdem modules that ``jaxdem/<module>.py`` imports, anywhere in the file."""
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "jaxdem":
                found.update(alias.name for alias in node.names)
            elif node.module.startswith("jaxdem."):
                found.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            found.update(a.name.split(".")[1] for a in node.names if a.name.startswith("jaxdem."))
    return found


@pytest.mark.parametrize("module", LAYERS)
def test_no_module_imports_upward(module):
    above = set(LAYERS[LAYERS.index(module) + 1:])
    assert not _imports(module) & above, f"jaxdem.{module} imports {_imports(module) & above}"


def test_results_know_nothing_of_the_driver():
    assert not _imports("results") & {"solver", "increment", "substep", "sensitivities"}


def test_the_layers_name_every_solver_module():
    # A new solver module must take its place in LAYERS (else nothing checks it).
    host = {"__init__", "__main__", "config", "geometry", "plots", "cli", "vtk"}
    prefixes = ("scene", "rockmass", "plots_", "cli_")
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    unlisted = {m for m in modules - set(LAYERS) - host if not m.startswith(prefixes)}
    assert not unlisted, f"modules without a layer: {sorted(unlisted)}"
