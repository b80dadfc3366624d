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

import jax

# float64 by default; a scene may ask for float32 (solver.dtype).
jax.config.update("jax_enable_x64", True)

from jaxdem.differentiable import differentiable  # noqa: E402
from jaxdem.results import Result  # noqa: E402
from jaxdem.scene import Scene, SceneError, load_scene  # noqa: E402
from jaxdem.solver import Status, solve  # noqa: E402

__all__ = ["Result", "Scene", "SceneError", "Status", "differentiable", "load_scene", "solve"]
__version__ = "0.1.0"
