"""jaxdem: 2D block-spring discrete element analysis of tunnels in jointed rock, in JAX.

Rigid convex blocks, normal and shear springs at contacts (Hataf & Baharloo,
after Wang & Garga), Mohr-Coulomb joints, static equilibrium solved
incrementally with large displacements. Units: m, kN, kPa, kN/m3; degrees in
files. Compression positive.

    import jaxdem
    scene = jaxdem.load_scene("scene.toml")
    result = jaxdem.solve(scene)
    result.to_dict()

Importing jaxdem changes nothing in the caller's process: no JAX flag, no environment
variable, no cache. The solver runs in float64 around its own entry points;
:func:`jaxdem.config.configure` makes the process-wide settings (float64 everywhere, one
OpenBLAS thread, the persistent compilation cache) for a program that wants them, as the
command line does.

The package, by concept (README, "Layout"): :mod:`jaxdem.scene` (scene files),
:mod:`jaxdem.rockmass` (generated blocks), :mod:`jaxdem.core` (the device side),
:mod:`jaxdem.results`, :mod:`jaxdem.solver`, :mod:`jaxdem.differentiable`,
:mod:`jaxdem.batch`, :mod:`jaxdem.sweep`, :mod:`jaxdem.fos`, :mod:`jaxdem.grc` (ground
reaction curve), :mod:`jaxdem.reliability` (FORM), :mod:`jaxdem.vtk`,
:mod:`jaxdem.plots`, :mod:`jaxdem.cli`, :mod:`jaxdem.config`, :mod:`jaxdem.geometry`.
"""

import importlib
import sys
import types

_EXPORTS = {
    "BatchResult": "jaxdem.batch", "solve_batch": "jaxdem.batch",
    "Status": "jaxdem.core.status",
    "differentiable": "jaxdem.differentiable",
    "FactorOfSafety": "jaxdem.fos", "factor_of_safety": "jaxdem.fos",
    "GroundReaction": "jaxdem.grc", "ground_reaction": "jaxdem.grc",
    "Reliability": "jaxdem.reliability", "reliability": "jaxdem.reliability",
    "Result": "jaxdem.results",
    "Scene": "jaxdem.scene", "SceneError": "jaxdem.scene", "load_scene": "jaxdem.scene",
    "solve": "jaxdem.solver",
    "SweepResult": "jaxdem.sweep", "sweep": "jaxdem.sweep",
}
"""The public names and the modules they come from, imported at their first use: ``import
jaxdem`` itself imports neither JAX nor the solver (0.7 and 0.3 s), so that the command
line, whose own modules need neither, reads its scene file and starts loading the stored
programs of its last run while the solver's modules are imported
(:func:`jaxdem.core.compile_cache.warm_start`). A subpackage or module (``jaxdem.core``,
``jaxdem.solver``) is imported at its first use the same way."""


def __getattr__(name: str):
    if name.startswith("__"):  # probes of tools (``__wrapped__``): not a submodule
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module = _EXPORTS.get(name)
    try:
        value = (getattr(importlib.import_module(module), name) if module is not None
                 else importlib.import_module(f"{__name__}.{name}"))
    except ModuleNotFoundError as err:
        if err.name != f"{__name__}.{name}":
            raise
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


class _Package(types.ModuleType):
    """The package's module: the import system binds a submodule on its package once it is
    imported (``jaxdem.sweep`` the module); the functions ``sweep``, ``reliability`` and
    ``differentiable`` keep those names over the modules they live in, as they did when
    this file imported them."""

    def __setattr__(self, name, value):
        if name in _EXPORTS and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


__all__ = sorted([*_EXPORTS, "config"])
__version__ = "0.1.0"
