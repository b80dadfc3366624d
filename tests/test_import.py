"""Importing jaxdem changes nothing in the caller's process; the solver still runs in float64.

Each check runs in a fresh Python process (this test process has float64 on, from
conftest.py): there, ``import jaxdem`` must leave JAX's flags and the environment as
they were, and ``jaxdem.solve`` must still give the float64 answer, bit for bit the one
this process gets, and restore the caller's float32 setting on return (issue 29).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

import jaxdem
from jaxdem.core.status import Status

ROOT = Path(__file__).resolve().parents[1]
INCLINE = ROOT / "examples" / "block_on_incline.toml"


def _fresh(code: str) -> dict:
    """Run ``code`` in a new Python process (without this process's JAX settings) and
    return the JSON it prints last."""
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS",
                                                            "JAX_ENABLE_X64")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_import_changes_nothing():
    seen = _fresh("""
        import json, os
        env = dict(os.environ)
        import jax
        cache = jax.config.jax_compilation_cache_dir
        import jaxdem, jaxdem.cli, inverse
        print(json.dumps(dict(x64=bool(jax.config.jax_enable_x64),
                              cache=jax.config.jax_compilation_cache_dir == cache,
                              env=dict(os.environ) == env,
                              api=[callable(getattr(jaxdem, n)) for n in jaxdem.__all__
                                   if n != "config"])))
    """)
    assert seen["x64"] is False and seen["cache"] and seen["env"] and all(seen["api"])


def test_import_of_the_package_and_command_line_loads_no_jax_and_names_keep_their_objects():
    """``import jaxdem`` and ``jaxdem.cli`` import neither JAX nor the solver (the command
    line reads its scene and starts loading stored programs while they are imported:
    jaxdem.core.compile_cache.warm_start); a public name is imported at its first use,
    and ``sweep``, ``reliability`` and ``differentiable`` stay the functions once their
    modules of the same names are imported, as ``from jaxdem.sweep import ...`` does."""
    seen = _fresh("""
        import json, sys, types
        import jaxdem, jaxdem.cli
        light = not any(m == "jax" or m.startswith(("jax.", "jaxdem.core", "jaxdem.solver"))
                        for m in sys.modules)
        from jaxdem.sweep import SweepResult
        import jaxdem.reliability, jaxdem.differentiable
        names = {n: not isinstance(getattr(jaxdem, n), types.ModuleType)
                 for n in ("sweep", "reliability", "differentiable", "solve", "Status")}
        from jaxdem import *
        star = callable(sweep) and callable(reliability) and callable(differentiable)
        try:
            jaxdem.no_such_name
            missing = False
        except AttributeError:
            missing = True
        print(json.dumps(dict(light=light, names=names, star=star, missing=missing,
                              module=isinstance(jaxdem.solver, types.ModuleType))))
    """)
    assert seen["light"], "import jaxdem imported JAX or the solver"
    assert all(seen["names"].values()), seen["names"]
    assert seen["star"] and seen["missing"] and seen["module"]


def test_solve_runs_in_float64_and_restores_the_callers_setting():
    seen = _fresh(f"""
        import json, os
        import jax
        import jaxdem
        scene = jaxdem.load_scene({str(INCLINE)!r})
        result = jaxdem.solve(scene)
        f, theta0 = jaxdem.differentiable(scene, ["joints.base.kn"])
        y = f(theta0)["block"]
        print(json.dumps(dict(
            x64_after=bool(jax.config.jax_enable_x64),
            openblas=os.environ.get("OPENBLAS_NUM_THREADS"),
            status=result.status, u=result.monitors["block"]["displacement"],
            f_dtype=str(y.dtype), f=[float(v) for v in y])))
    """)
    here = jaxdem.solve(jaxdem.load_scene(INCLINE))
    assert seen["x64_after"] is False and seen["openblas"] is None
    assert seen["status"] == here.status == "converged"
    # Bit for bit the float64 answer of this (float64) process: a float32 solve would
    # differ from the seventh digit on.
    assert seen["u"] == here.monitors["block"]["displacement"]
    # f answers in the caller's precision (float32 there), from the float64 solve.
    assert seen["f_dtype"] == "float32"
    np.testing.assert_allclose(seen["f"], here.monitors["block"]["displacement"], rtol=1e-6)


def test_result_status_is_the_status_enumeration():
    result = jaxdem.solve(jaxdem.load_scene(INCLINE))
    assert isinstance(result.status, Status) and result.status is Status.CONVERGED
    assert result.status == "converged" and f"{result.status}" == "converged"
    assert json.loads(json.dumps(result.to_dict()))["status"] == "converged"
    assert [Status.of(s.code) for s in Status] == list(Status)
