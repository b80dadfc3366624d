"""Back-analysis on top of :func:`jaxdem.differentiable` (SPEC section 5).

Fit scene parameters (joint stiffnesses, strengths, in-situ stress ratio, ...) to
measured monitor values, with Gauss-Newton standard deviations and a report of
which parameters the measurements determine.

    import jaxdem
    from inverse import back_analyse, read_observations

    scene = jaxdem.load_scene("tunnel.toml")
    fit = back_analyse(scene, read_observations("obs.csv"),
                       fit=["joints.set1.kn", "joints.set1.ks"])
    fit.params, fit.std, fit.identifiable, fit.warnings

Figures: :func:`inverse.plots.write_figures`. Command line: ``jaxdem back-analyse``.
"""

from inverse.backanalysis import BackAnalysis, Observation, back_analyse, read_observations

__all__ = ["BackAnalysis", "Observation", "back_analyse", "read_observations"]
