"""jaxdem: 2D block-spring discrete element analysis of tunnels in jointed rock, in JAX.

Rigid convex blocks, normal and shear springs at contacts (Hataf & Baharloo,
after Wang & Garga), Mohr-Coulomb joints, static equilibrium solved
incrementally with large displacements. Units: m, kN, kPa, kN/m3; degrees in
files. Compression positive.

    import jaxdem
    scene = jaxdem.load_scene("scene.toml")
    result = jaxdem.solve(scene)
    result.to_dict()
"""

from jaxdem import config

# float64 by default, one OpenBLAS thread, the persistent compilation cache:
# see jaxdem.config.
config.configure()

from jaxdem.batch import BatchResult, solve_batch  # noqa: E402
from jaxdem.differentiable import differentiable  # noqa: E402
from jaxdem.fos import FactorOfSafety, factor_of_safety  # noqa: E402
from jaxdem.results import Result  # noqa: E402
from jaxdem.scene import Scene, SceneError, load_scene  # noqa: E402
from jaxdem.solver import solve  # noqa: E402
from jaxdem.status import Status  # noqa: E402
from jaxdem.sweep import SweepResult, sweep  # noqa: E402

__all__ = ["BatchResult", "FactorOfSafety", "Result", "Scene", "SceneError", "Status",
           "SweepResult", "differentiable", "factor_of_safety", "load_scene", "solve",
           "solve_batch", "sweep"]
__version__ = "0.1.0"
