"""The device side of the solver: everything that runs inside ``jax.jit``, and the host
driver's programs.

Modules, from the bottom up (each imports only those before it; ``tests/test_layers.py``
checks it):

- :mod:`~jaxdem.core.state`: the frozen pytrees ``Model``, ``State``, ``Loads``.
- :mod:`~jaxdem.core.status`: the ``Status`` enumeration and the admissibility tolerances.
- :mod:`~jaxdem.core.compile_cache`: compiled programs per shape, on disk too.
- :mod:`~jaxdem.core.kinematics`: rigid motion, constant strain, points and anchors.
- :mod:`~jaxdem.core.laws`: equivalent stiffness (paper eqs. 3-7) and Mohr-Coulomb.
- ``_contact``: broad and narrow phase (spring slots).
- ``_springs``: a sub-step's spring forces, states, residual and stiffness terms.
- ``_linsolve``: the Newton iteration's linear solves.
- :mod:`~jaxdem.core.loads`: water, in-situ preload, excavation release.
- ``_substep``: one geometry sub-step (detect, Newton, commit).
- :mod:`~jaxdem.core.sensitivities`: forward-mode sensitivities of a sub-step.
- :mod:`~jaxdem.core.increment`: the jitted increment (sub-steps to equilibrium).
- :mod:`~jaxdem.core.model`: Scene (host) -> device ``Model`` and initial ``State``.

Modules whose names start with ``_`` are private to this package; the others are used by
jaxdem's entry points (``jaxdem.solver``, ``jaxdem.batch``, ...). None of this is the
public API (README, "Python"): names here may change between versions.
"""
