"""Back-analysis of the foliation joint stiffnesses of seed example 2 from its convergences.

Identical-twin test: the "measured" convergences of sections 1-1 to 4-4 are the
solver's own at the scene's kn and ks, with 5% Gaussian noise (seed 0) and a 5%
standard deviation (at least 0.1 mm). The fit starts from kn x 0.5 and ks x 2
and uses the Jacobians of ``jaxdem.differentiable`` with the default optimiser
(Gauss-Newton / Levenberg-Marquardt). By default the rock between the joints is
left unmeshed (rigid blocks cut by the foliation and the shear zone, 72 blocks):
a solve with sensitivities then takes well under a second and the whole example
well under 2 minutes on a 2-core CPU. ``--mesh-size 8`` meshes the intact rock
(615 deformable blocks, 20-50 s per solve: several minutes), ``--mesh-size 4``
as the scene file has it (1,193 blocks).

Where the time went before (2-core CPU, L-BFGS, mesh 8, 11 min): 13 solves with
sensitivities of 20-50 s each, a trial point of the line search where the
model is a mechanism (one such solve took 9 minutes), and a second compilation
for the measurements' own ``jaxdem.solve``. Now: Gauss-Newton (4-6 solves, with
a trust region that keeps trials away from mechanisms), the measurements taken
from the fit's own compiled solve, and rigid blocks by default.

    python examples/back_analysis_example2.py [--mesh-size 0|8|4] [--out DIR]

Writes back_analysis.json, misfit.png, fit.png and sensitivity.png to ``--out``
(default out/back_analysis_example2; never over the shipped figures in
examples/figures/back_analysis unless asked), and prints the estimates with
their Gauss-Newton standard deviations against the truth, and where the time went.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import jaxdem
from inverse import Observation, back_analyse
from inverse.plots import write_figures
from jaxdem.differentiable import Problem
from jaxdem.scene import apply_overrides, parse_scene

HERE = Path(__file__).resolve().parent
SCENE = HERE / "seed_example2_tunnel.toml"
FIT = ["joints.foliation.kn", "joints.foliation.ks"]
START_FACTORS = (0.5, 2.0)
SECTIONS = ("section 1-1", "section 2-2", "section 3-3", "section 4-4")


def main(argv=None):
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/back_analysis_example2",
                        help="output folder (default out/back_analysis_example2; the shipped "
                        "figures are in examples/figures/back_analysis)")
    parser.add_argument("--max-iterations", type=int, default=30)
    parser.add_argument("--mesh-size", type=float, default=0.0,
                        help="intact-rock cell size (m); 0 (default): rigid blocks, no mesh; "
                        "the scene file has 4")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    base = jaxdem.load_scene(SCENE)
    data = base.data
    if args.mesh_size > 0:
        data = apply_overrides(data, {"domain.mesh_size": args.mesh_size})
    else:
        data = dict(data, domain={k: v for k, v in data["domain"].items() if k != "mesh_size"})
    scene = parse_scene(data, source=base.source)
    joint = scene.joints["foliation"]
    truth = {FIT[0]: float(joint.kn), FIT[1]: float(joint.ks)}
    # The measurements from the fit's own problem (a solve with sensitivities): the
    # program compiled for them is the one every iteration reuses.
    t0 = time.perf_counter()
    problem = Problem(scene, FIT)
    y, _ = problem.evaluate(problem.theta0, jacobian=True)
    t_forward = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    observations = []
    for name in SECTIONS:
        value = float(y[problem.keys.index((None, name, None))])
        std = max(0.05 * abs(value), 1e-4)
        observations.append(Observation(name, value + std * rng.standard_normal(), std))
    print(f"synthetic measurements (compilation and one solve with sensitivities, "
          f"{t_forward:.0f} s):")
    for obs in observations:
        print(f"  {obs.monitor}: {1e3 * obs.value:.3f} +- {1e3 * obs.std:.3f} mm")

    start = {p: truth[p] * f for p, f in zip(FIT, START_FACTORS, strict=True)}
    t0 = time.perf_counter()

    def progress(event):
        est = ", ".join(f"{p.split('.')[-1]}={v:.4g}" for p, v in event["params"].items())
        print(f"  iteration {event['iteration']:2d}  misfit {event['misfit']:10.4g}  {est}  "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)

    theta0 = np.array([start[p] for p in FIT])
    fit = back_analyse(scene.with_overrides(start), observations, fit=FIT,
                       forward=(problem.function(), theta0),
                       max_iterations=args.max_iterations, progress=progress)
    wall = time.perf_counter() - t0
    figures = write_figures(fit, out)
    record = fit.to_dict()
    record.update(truth=truth, start=start, wall_s=wall, forward_s=t_forward)
    (out / "back_analysis.json").write_text(json.dumps(record, indent=2, allow_nan=False))
    print(f"\n{fit.status}: {fit.message}")
    print(f"{'parameter':<22} {'truth':>10} {'start':>10} {'estimate':>10} {'std':>10} "
          f"{'|err|/std':>9}")
    for p in FIT:
        err = abs(fit.params[p] - truth[p]) / fit.std[p]
        print(f"{p:<22} {truth[p]:>10.4g} {start[p]:>10.4g} {fit.params[p]:>10.4g} "
              f"{fit.std[p]:>10.3g} {err:>9.2f}")
    print(f"time: measurements {t_forward:.0f} s (of which compilation), fit {wall:.0f} s "
          f"({sum(problem.solves.values()) - 1} solves); total {t_forward + wall:.0f} s")
    print(f"evaluations: {fit.evaluations}; wall {wall:.0f} s; figures: "
          + ", ".join(str(f) for f in figures))
    for w in fit.warnings:
        print("warning:", w)


if __name__ == "__main__":
    main()
