"""The package's architecture, checked: imports go one way, privacy lives on modules.

- Packages and entry-point modules import one way (:data:`ORDER`, bottom up): a unit
  may import itself and any unit before it, never one after it (issue 29).
- Inside the solver, modules import one way too (:data:`LAYERS`, issue 20).
- No private name (``_x``) is imported from another module, and no private module
  (``jaxdem.P._m``) is imported from outside its package P (issue 29).

Every import counts, at the top of the file or inside a function, so a late import
cannot hide a circle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxdem"

ORDER = ["geometry", "config", "scene", "rockmass", "core", "results", "solver",
         "differentiable", "batch", "sweep", "plots", "fos", "reliability", "grc", "vtk",
         "inverse", "cli"]
"""jaxdem's units (a subpackage or a top-level module) and ``inverse``, from the bottom up:
host input (scene, generated rock), the device side (core), the host results and driver,
the entry points built on them, figures, the back-analysis, the command line."""

LAYERS = ["core.state", "core.status", "core.compile_cache", "core.kinematics", "core.laws",
          "core._contact", "core._springs", "core._linsolve", "core.loads", "core._substep",
          "core.sensitivities", "core.increment", "core.model", "results", "solver",
          "differentiable", "batch", "sweep", "fos", "grc"]
"""The solver's modules (dotted under jaxdem), from the bottom up, as the README's layout
and each module's docstring describe them."""


def _sources() -> list[Path]:
    return sorted([*PACKAGE.rglob("*.py"), *(ROOT / "inverse").rglob("*.py")])


def _name(path: Path) -> str:
    """Dotted module name of a source file: ``jaxdem.core.state``, ``jaxdem.scene``."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, str | None]]:
    """(module, imported name or None) of every jaxdem or inverse import in the file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module.split(".")[0] in ("jaxdem", "inverse"):
                found += [(node.module, alias.name) for alias in node.names]
        elif isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names if a.name.split(".")[0] in
                      ("jaxdem", "inverse")]
    return found


def _unit(dotted: str) -> str | None:
    """The unit of ORDER that a dotted module belongs to (None: the package root)."""
    parts = dotted.split(".")
    if parts[0] == "inverse":
        return "inverse"
    return parts[1] if len(parts) > 1 and parts[1] != "__main__" else None


def _targets(module: str, name: str | None) -> list[str]:
    """The modules an import reaches: ``from jaxdem import core`` reaches jaxdem.core."""
    if name is not None and module in ("jaxdem", "jaxdem.core"):
        candidate = f"{module}.{name}"
        if (ROOT / Path(*candidate.split(".")).with_suffix(".py")).exists() or \
                (ROOT / Path(*candidate.split("."))).is_dir():
            return [candidate]
    return [module]


@pytest.mark.parametrize("path", _sources(), ids=lambda p: _name(p))
def test_units_import_one_way(path):
    me = _unit(_name(path))
    if me is None:  # jaxdem/__init__.py is the public face: it may import any unit
        return
    below = set(ORDER[: ORDER.index(me) + 1])
    for module, name in _imports(path):
        for target in _targets(module, name):
            unit = _unit(target)
            assert unit is None or unit in below, f"{_name(path)} imports {target} ({unit} " \
                f"comes after {me} in ORDER)"


@pytest.mark.parametrize("module", LAYERS)
def test_no_solver_module_imports_upward(module):
    path = PACKAGE / Path(*module.split(".")).with_suffix(".py")
    above = {f"jaxdem.{m}" for m in LAYERS[LAYERS.index(module) + 1:]}
    reached = {t for m, n in _imports(path) for t in _targets(m, n)}
    assert not reached & above, f"jaxdem.{module} imports {reached & above}"


def test_results_know_nothing_of_the_driver():
    reached = {t for m, n in _imports(PACKAGE / "results.py") for t in _targets(m, n)}
    assert not reached & {"jaxdem.solver", "jaxdem.core.increment", "jaxdem.core._substep",
                          "jaxdem.core.sensitivities"}


@pytest.mark.parametrize("path", _sources(), ids=lambda p: _name(p))
def test_no_private_name_is_imported_from_another_module(path):
    private = [(m, n) for m, n in _imports(path) if n and n.startswith("_")
               and not n.startswith("__")]
    assert not private, f"{_name(path)} imports private names {private}"


@pytest.mark.parametrize("path", _sources(), ids=lambda p: _name(p))
def test_private_modules_stay_in_their_package(path):
    me = _name(path)
    for module, name in _imports(path):
        for target in _targets(module, name):
            parts = target.split(".")
            for i, part in enumerate(parts):
                if part.startswith("_") and not part.startswith("__"):
                    package = ".".join(parts[:i])
                    assert me == package or me.startswith(package + "."), \
                        f"{me} imports {target}, private to {package}"


def test_the_layers_name_every_solver_module():
    # A new solver module must take its place in LAYERS (else nothing checks it).
    core = {f"core.{p.stem}" for p in (PACKAGE / "core").glob("*.py") if p.stem != "__init__"}
    assert core == {m for m in LAYERS if m.startswith("core.")}


def test_the_order_names_every_unit():
    units = {p.stem for p in PACKAGE.glob("*.py")} | {p.name for p in PACKAGE.iterdir()
                                                      if (p / "__init__.py").exists()}
    assert units - {"__init__", "__main__"} == set(ORDER) - {"inverse"}
