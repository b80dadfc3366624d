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

from jaxdem import config
from jaxdem.batch import BatchResult, solve_batch
from jaxdem.core.status import Status
from jaxdem.differentiable import differentiable
from jaxdem.fos import FactorOfSafety, factor_of_safety
from jaxdem.grc import GroundReaction, ground_reaction
from jaxdem.reliability import Reliability, reliability
from jaxdem.results import Result
from jaxdem.scene import Scene, SceneError, load_scene
from jaxdem.solver import solve
from jaxdem.sweep import SweepResult, sweep

__all__ = ["BatchResult", "FactorOfSafety", "GroundReaction", "Reliability", "Result", "Scene",
           "SceneError", "Status", "SweepResult", "config", "differentiable", "factor_of_safety",
           "ground_reaction", "load_scene", "reliability", "solve", "solve_batch", "sweep"]
__version__ = "0.1.0"
