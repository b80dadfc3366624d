"""Monitors as differentiable functions of scene parameters (SPEC section 4).

``f, theta0 = differentiable(scene, params)`` gives f(theta) -> {monitor: value},
a JAX function that jits, vmaps and differentiates in forward and reverse mode.

How it works:

- A forward solve is the ordinary incremental solve (:func:`jaxdem.solver.run`),
  on the host, reached from JAX through ``jax.pure_callback``.
- Derivatives are forward-mode sensitivities carried alongside that solve:
  each parameter seeds the derivatives of the model and loads it changes
  (:class:`ParameterMap`), and every geometry sub-step that ends in
  equilibrium is differentiated implicitly, with its contact states held
  (:func:`jaxdem.core.increment.increment_tangent`): one linear solve with the exact
  tangent per sub-step, for all parameters at once, never a derivative
  through the Newton iterations. The excavation release, the in-situ state
  and the stage ends are chained through exactly.
- ``f`` is a ``jax.custom_jvp`` whose tangent is J @ t, with the Jacobian J
  (monitors x parameters) from that one solve. J @ t is linear in t, so
  reverse mode (``jax.grad``) transposes it: a gradient costs one solve with
  sensitivities, whatever the number of monitors.

State changes. The solution is piecewise smooth in theta: between thresholds
(a slot that would start or stop slipping, open or close, a bolt that
yields) the derivative is exact. At a threshold it is one of the one-sided
derivatives (that of the states the solve found), and across it the
derivative jumps. A sub-step cut by the step length (a block moving a long
way before it finds equilibrium) is held fixed in the derivative; the
sensitivities are then approximate, which the solve records.

A solve that does not find equilibrium (a mechanism, the iteration limit)
gives NaN values and NaN derivatives: there is no displacement to fit.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.config import float64
from jaxdem.core import model as model_mod
from jaxdem.core.laws import intact_stiffness, plane_strain_elasticity
from jaxdem.core.sensitivities import SMOOTH_MODEL
from jaxdem.core.status import Status
from jaxdem.results import monitor_positions
from jaxdem.scene import SceneError, apply_overrides
from jaxdem.solver import Data, gravity_material, run, scene_data, stage_plan

#: Parameter paths that f can be differentiated with respect to (NAME, I, K are
#: a name, a list index and a table row).
DIFFERENTIABLE = (
    "joints.NAME.{kn, ks, friction_deg, cohesion, tensile_strength}",
    "materials.NAME.{E, nu, unit_weight, cohesion, friction_deg, tensile_strength}",
    "in_situ.{k0, sigma_xx, sigma_yy, sigma_xy, surface_y}",
    "bolts.I.{stiffness, yield_force, anchor_capacity, compression}",
    "supports.I.pressure",
    "water.unit_weight",
    "water.table.K.1 (water level at a table point)",
    "stages.I.water_table.K.1",
)

_JOINT_FIELD = dict(kn="joint_kn", ks="joint_ks", cohesion="joint_c",
                    tensile_strength="joint_t", friction_deg="joint_tanphi")


@float64
def differentiable(scene, params: Sequence[str], stages: Sequence[str] | None = None):
    """Monitors at the end of the solve as a differentiable function of scene parameters.

    Args:
      scene: a validated :class:`jaxdem.Scene`.
      params: dotted paths of numeric scene entries (see :data:`DIFFERENTIABLE`).
      stages: optional stage names; then f returns {stage: {monitor: value}} at
        the end of each (``"initial"`` is the state before the first stage).
    Returns:
      (f, theta0): theta0 is the (p,) float64 array of the parameters' values
      in the scene (file units); f(theta) returns {monitor: value}, [ux, uy]
      (m) for a point monitor and the convergence (m) for a section, at the end
      of the last stage. f is a JAX function: jit, grad, jacfwd, jacrev and
      vmap compose with it (vmap solves the batch one member after another).
    Raises:
      SceneError: a path that does not exist, is not numeric, or is not a
        parameter the solution depends on smoothly (geometry, solver settings).

    Example::

        f, theta0 = jaxdem.differentiable(scene, ["joints.set1.kn", "joints.set1.ks"])
        loss = lambda th: (f(th)["section 1-1"] - 0.012) ** 2
        g = jax.grad(loss)(theta0)
    """
    problem = Problem(scene, params, stages)
    return problem.function(), jnp.asarray(problem.theta0)


class Problem:
    """A scene built once, solved at any theta with the Jacobian of its monitors (host side).

    ``evaluate(theta, jacobian)`` returns the flat vector of monitor values
    (and, if asked, its (n, p) Jacobian); ``keys`` names the entries
    (stage, monitor, component). Solves are cached by theta, so that a value
    asked for after its derivative costs nothing.
    """

    @float64
    def __init__(self, scene, params: Sequence[str], stages: Sequence[str] | None = None,
                 cache: int = 8):
        if isinstance(params, str) or not params:
            raise SceneError("params", "give a non-empty list of parameter paths")
        self.scene = scene
        self.paths = list(params)
        if len(set(self.paths)) != len(self.paths):
            raise SceneError("params", "a parameter is named twice")
        for path in self.paths:
            try:
                apply_overrides(scene.data, {path: 0.0})  # refuses a path that does not exist
            except SceneError as err:
                raise SceneError(path, err.problem) from None
        self.model, self.state, self.layout = model_mod.build(scene)
        self.data = scene_data(scene, self.layout)
        self.map = ParameterMap(scene, self.model, self.layout, self.data, self.paths)
        self.theta0 = self.map.theta0
        self.stages = None if stages is None else list(stages)
        known = ["initial"] + [s["name"] for s in stage_plan(scene)]
        for name in self.stages or []:
            if name not in known:
                raise SceneError("stages", f"no stage named {name!r} (stages: {known})")
        self.keys = [(stage, name, comp) for stage in (self.stages or [None])
                     for name, m in self.layout.monitors.items()
                     for comp in (("ux", "uy") if m["kind"] == "point" else (None,))]
        if not self.keys:
            raise SceneError("monitors", "the scene has no monitors to differentiate")
        self._cache: collections.OrderedDict = collections.OrderedDict()
        self._size = cache
        self.solves = collections.Counter()

    # -- host evaluation ---------------------------------------------------

    @float64
    def evaluate(self, theta, jacobian: bool = False):
        """Monitor vector (n,) at theta and, with ``jacobian``, d vector / d theta (n, p)."""
        theta = np.asarray(theta, float).reshape(len(self.paths))
        key = theta.tobytes()
        hit = self._cache.get(key)
        if hit is not None and (hit[1] is not None or not jacobian):
            self._cache.move_to_end(key)
            return hit if jacobian else (hit[0], None)
        y, J, info = self._solve(theta, jacobian)
        self.solves["jacobian" if jacobian else "value"] += 1
        self.last = info
        self._cache[key] = (y, J)
        while len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return y, J

    def _solve(self, theta, jacobian):
        mf, data = self.map.apply(theta, jacobian)
        model = dataclasses.replace(self.model, **mf)
        n, p = len(self.keys), len(self.paths)
        want = set(self.stages) if self.stages else None
        found = {}

        def stage_end(d, name):
            if want is not None and name in want:
                found[name] = self._monitors(d)

        # One solve of many: its programs are not compiled quick (level 0).
        d = run(self.scene, model, self.state, self.layout, data, stage_end=stage_end, quick=False)
        info = dict(status=d.status, approximate=d.approximate)
        if d.status != Status.CONVERGED:
            return np.full(n, np.nan), (np.full((n, p), np.nan) if jacobian else None), info
        if want is None:
            found = {None: self._monitors(d)}
        y = np.full(n, np.nan)
        J = np.full((n, p), np.nan) if jacobian else None
        for i, (stage, name, comp) in enumerate(self.keys):
            if stage not in found:
                continue
            values, tangents = found[stage]
            k = dict(ux=0, uy=1).get(comp, 0)
            y[i] = values[name][k]
            if jacobian:
                J[i] = tangents[name][:, k]
        return y, J, info

    def _monitors(self, d):
        """{monitor: (2,) or (1,)} readings and {monitor: (p, 2) or (p, 1)} derivatives."""
        now = {k: getattr(d.state, k) for k in ("centroid", "rot", "strain")}
        ref = None if d.ref is None else {k: getattr(d.ref, k) for k in now}
        if d.dstate is None:
            values = self._readings(now, ref)
            return {k: np.asarray(v) for k, v in values.items()}, None
        dnow = {k: d.dstate[k] for k in now}
        dref = None if d.dref is None else {k: d.dref[k] for k in now}
        values, tangents = self._readings_and_tangents(now, ref, dnow, dref)
        return ({k: np.asarray(v) for k, v in values.items()},
                {k: np.asarray(v) for k, v in tangents.items()})

    @functools.cached_property
    def _readings(self):
        return jax.jit(functools.partial(monitor_readings, self.layout))

    @functools.cached_property
    def _readings_and_tangents(self):
        read = functools.partial(monitor_readings, self.layout)

        def both(now, ref, dnow, dref):
            tangent = lambda dn, dr: jax.jvp(read, (now, ref), (dn, dr))[1]  # noqa: E731
            return read(now, ref), jax.vmap(tangent)(dnow, dref)

        return jax.jit(both)

    # -- the JAX function --------------------------------------------------

    def function(self, jacobian=None):
        """f(theta) -> {monitor: value} (or {stage: {monitor: value}}), a jax.custom_jvp.

        ``jacobian``: optional host function theta -> (values, Jacobian) that replaces
        the solve with sensitivities (the benchmarks use finite differences).
        """
        n, p = len(self.keys), len(self.paths)

        def flat_of(dtype):
            """theta -> flat monitor vector in ``dtype``, a jax.custom_jvp over the host solve."""
            out, jac = jax.ShapeDtypeStruct((n,), dtype), jax.ShapeDtypeStruct((n, p), dtype)

            def values(theta):
                return self.evaluate(theta, False)[0].astype(dtype)

            def values_and_jacobian(theta):
                if jacobian is not None:
                    y, J = jacobian(np.asarray(theta, float))
                else:
                    y, J = self.evaluate(theta, True)
                return np.asarray(y, dtype), np.asarray(J, dtype)

            @jax.custom_jvp
            def flat(theta):
                return jax.pure_callback(values, out, theta, vmap_method="sequential")

            @flat.defjvp
            def flat_jvp(primals, tangents):
                (theta,), (t,) = primals, tangents
                y, J = jax.pure_callback(values_and_jacobian, (out, jac), theta,
                                         vmap_method="sequential")
                return y, J @ t

            return flat

        flats: dict = {}

        def f(theta):
            # The solve runs in float64 (Problem.evaluate); f answers in the caller's
            # precision: float64 where JAX has x64 on, else float32.
            theta = jnp.asarray(theta, float)
            if theta.dtype not in flats:
                flats[theta.dtype] = flat_of(theta.dtype)
            return self.unflatten(flats[theta.dtype](theta))

        f.problem = self
        return f

    def unflatten(self, y):
        """The flat monitor vector as {monitor: value} (or {stage: {monitor: value}})."""
        groups: dict = {}
        for i, (stage, name, _) in enumerate(self.keys):
            groups.setdefault(stage, {}).setdefault(name, []).append(i)
        out = {stage: {name: (y[idx[0]] if len(idx) == 1 else y[jnp.asarray(idx)])
                       for name, idx in mons.items()} for stage, mons in groups.items()}
        return out[None] if self.stages is None else out


def monitor_readings(layout, now: dict, ref: dict | None) -> dict:
    """{monitor: (2,) displacement [ux, uy] or (1,) convergence} (m), in jax.numpy.

    The same readings as :func:`jaxdem.results.monitor_values`, written so that
    they differentiate: a point follows its block, c + (I + E) R(rot) offset.
    """
    def positions(m, s):
        return monitor_positions(m, s["centroid"], s["rot"], s["strain"])

    out = {}
    for name, m in layout.monitors.items():
        now_p = positions(m, now)
        start = jnp.asarray(m["points"]) if ref is None else positions(m, ref)
        if m["kind"] == "point":
            out[name] = now_p[0] - start[0]
        else:
            out[name] = (jnp.linalg.norm(start[1] - start[0])
                         - jnp.linalg.norm(now_p[1] - now_p[0]))[None]
    return out


class NotSmooth(SceneError):
    """A parameter that changes the blocks, the array shapes or the solver settings: it has
    no derivative, and samples that differ in it cannot share one batch."""


class ParameterMap:
    """Scene parameters -> the model fields and driver loads they set, as a JAX function.

    ``apply(theta, derivatives)`` returns the :data:`SMOOTH_MODEL` fields and a
    :class:`Data` whose stacks hold the values at theta and, with
    ``derivatives``, their derivatives with respect to each parameter (by
    forward-mode differentiation of this map: tan(phi), 1/E, ... exactly).
    Everything else (geometry, scales, tolerances) is that of the scene as
    built, so f(theta) matches ``solve(scene, set=...)`` to the solver tolerance.
    """

    def __init__(self, scene, model, layout, data: Data, paths):
        self.scene, self.model, self.layout, self.data = scene, model, layout, data
        self.kinds = []
        for path in paths:
            try:
                self.kinds.append(self._kind(path))
            except SceneError:
                raise
            except (KeyError, IndexError, ValueError, AttributeError, TypeError):
                raise SceneError(path, "no such parameter") from None
        self.theta0 = np.array([k["value"] for k in self.kinds], float)
        self.dtype = model.radius.dtype
        self.blocks = {name: np.array([i for i in range(layout.n_rock)
                                       if layout.materials[i] == name], int)
                       for name in scene.materials}

    def _kind(self, path):
        scene = self.scene
        keys = path.split(".")
        unsupported = NotSmooth(path, "is not a parameter the solution depends on smoothly; "
                                 "differentiable parameters: " + "; ".join(DIFFERENTIABLE))
        sec = keys[0]
        if sec == "joints" and len(keys) == 3 and keys[2] in _JOINT_FIELD:
            return dict(kind="joint", name=keys[1], field=keys[2],
                        value=getattr(scene.joints[keys[1]], keys[2]))
        if sec == "materials" and len(keys) == 3:
            m = scene.materials[keys[1]]
            if keys[2] in ("E", "nu", "unit_weight", "cohesion", "friction_deg",
                           "tensile_strength"):
                return dict(kind="material", name=keys[1], field=keys[2],
                            value=getattr(m, keys[2]))
        if sec == "in_situ" and len(keys) == 2 and scene.in_situ is not None:
            if keys[1] in ("k0", "sigma_xx", "sigma_yy", "sigma_xy") or (
                    keys[1] == "surface_y" and scene.in_situ.mode == "gravity"):
                return dict(kind="in_situ", field=keys[1], value=getattr(scene.in_situ, keys[1]))
        if sec == "bolts" and len(keys) == 3 and keys[2] in (
                "stiffness", "yield_force", "anchor_capacity", "compression"):
            i = int(keys[1])
            return dict(kind="bolt", index=i, field=keys[2],
                        value=getattr(scene.bolts[i], keys[2]))
        if sec == "supports" and len(keys) == 3 and keys[2] == "pressure":
            i = int(keys[1])
            return dict(kind="support", index=i, value=scene.supports[i].pressure)
        if sec == "water" and keys[1:] == ["unit_weight"]:
            return dict(kind="gamma_w", value=scene.water.unit_weight)
        table = None
        if sec == "water" and len(keys) == 4 and keys[1] == "table" and keys[3] == "1":
            table, stage = scene.water.table, None
        if (sec == "stages" and len(keys) == 5 and keys[2] == "water_table"
                and keys[4] == "1"):
            st = scene.stages[int(keys[1])]
            table, stage = st.water_table, st.name
        if table is not None:
            k = int(keys[2] if sec == "water" else keys[3])
            return dict(kind="water", stage=stage, row=k, value=float(table[k][1]))
        raise unsupported

    def apply(self, theta, derivatives: bool):
        """(model fields, Data) at theta, with derivatives when asked (see the class)."""
        theta = jnp.asarray(theta, jnp.float64)
        p = theta.shape[0]
        fields, arrays = self._jit_values(theta)
        tangents = self._jit_tangents(theta) if derivatives else None
        cast = lambda x: jnp.asarray(x, self.dtype)  # noqa: E731
        model_fields = {k: cast(v) for k, v in fields.items()}

        def stack(name):
            v = np.asarray(arrays[name])[None]
            if tangents is None:
                return v
            return np.concatenate([v, np.asarray(tangents[1][name])])


        data = dataclasses.replace(
            self.data, weight=stack("weight"), traction=self.data.traction
            if tangents is None else _pad(self.data.traction, p),
            supports=[stack(f"support{i}") for i in range(len(self.data.supports))],
            sigma=stack("sigma"), k0=stack("k0"), gamma=stack("gamma"),
            surface=stack("surface"), water_y=stack("water_y"),
            stage_water={k: stack(f"water:{k}") for k in self.data.stage_water},
            dmodel=None if tangents is None else {k: cast(v) for k, v in tangents[0].items()})
        return model_fields, data

    @functools.cached_property
    def _jit_values(self):
        return jax.jit(self._values)

    @functools.cached_property
    def _jit_tangents(self):
        """The derivatives of :meth:`_values` with respect to each parameter, stacked first."""
        def tangents(theta):
            eye = jnp.eye(theta.shape[0], dtype=theta.dtype)
            return jax.vmap(lambda e: jax.jvp(self._values, (theta,), (e,))[1])(eye)

        return jax.jit(tangents)

    def _values(self, theta):
        """({model field: value}, {driver array: value}) at theta, in jax.numpy."""
        model, layout, data, scene = self.model, self.layout, self.data, self.scene
        mf = {k: jnp.asarray(getattr(model, k), jnp.float64) for k in SMOOTH_MODEL}
        arr = dict(weight=jnp.asarray(data.weight[0]), sigma=jnp.asarray(data.sigma[0]),
                   k0=jnp.asarray(data.k0[0]), gamma=jnp.asarray(data.gamma[0]),
                   surface=jnp.asarray(data.surface[0]), water_y=jnp.asarray(data.water_y[0]))
        for i, f in enumerate(data.supports):
            arr[f"support{i}"] = jnp.asarray(f[0])
        for k, v in data.stage_water.items():
            arr[f"water:{k}"] = jnp.asarray(v[0])
        names = list(scene.joints)
        mats = list(scene.materials)
        elastic: dict = {}
        tables: dict = {}
        for x, kd in zip(theta, self.kinds, strict=True):
            kind = kd["kind"]
            if kind == "joint":
                rows = [names.index(kd["name"])]
                if scene.default_joint == kd["name"]:
                    rows.append(mf["joint_kn"].shape[0] - 1)  # the default joint's row
                value = jnp.tan(jnp.radians(x)) if kd["field"] == "friction_deg" else x
                field = _JOINT_FIELD[kd["field"]]
                mf[field] = mf[field].at[jnp.asarray(rows)].set(value)
            elif kind == "material":
                blocks = self.blocks[kd["name"]]
                if kd["field"] in ("E", "nu"):
                    elastic.setdefault(kd["name"], {})[kd["field"]] = x
                elif kd["field"] == "unit_weight":
                    area = jnp.asarray(model.area)[blocks]
                    arr["weight"] = arr["weight"].at[blocks, 1].set(-x * area)
                    if scene.in_situ is not None and scene.in_situ.mode == "gravity" and \
                            gravity_material(scene, layout) == kd["name"]:
                        arr["gamma"] = x
                else:
                    row = len(names) + mats.index(kd["name"])
                    value = jnp.tan(jnp.radians(x)) if kd["field"] == "friction_deg" else x
                    field = _JOINT_FIELD[kd["field"]]
                    mf[field] = mf[field].at[row].set(value)
            elif kind == "in_situ":
                f = kd["field"]
                if f.startswith("sigma_"):
                    arr["sigma"] = arr["sigma"].at[("xx", "yy", "xy").index(f[6:])].set(x)
                else:
                    arr[{"k0": "k0", "surface_y": "surface"}[f]] = x
            elif kind == "bolt":
                # The scene bolt's sub-bolts (model._bolts), each with its share.
                b = scene.bolts[kd["index"]]
                i = np.nonzero(np.asarray(layout.bolt_of) == kd["index"])[0]
                w = jnp.asarray(np.asarray(layout.bolt_share)[i]) / b.spacing
                if kd["field"] == "stiffness":
                    mf["bolt_k"] = mf["bolt_k"].at[i].set(w * x)
                elif kd["field"] == "compression":
                    mf["bolt_comp"] = mf["bolt_comp"].at[i].set(w * x)
                else:
                    other = b.anchor_capacity if kd["field"] == "yield_force" else b.yield_force
                    mf["bolt_cap"] = mf["bolt_cap"].at[i].set(w * jnp.minimum(x, other))
            elif kind == "support":
                i = kd["index"]
                arr[f"support{i}"] = x * jnp.asarray(layout.supports[i]["unit"])
            elif kind == "gamma_w":
                mf["gamma_w"] = x
            elif kind == "water":
                tables.setdefault(kd["stage"], {})[kd["row"]] = x
        for name, ev in elastic.items():
            m = scene.materials[name]
            E, nu = ev.get("E", m.E), ev.get("nu", m.nu)
            blocks = self.blocks[name]
            kn_i, ks_i = intact_stiffness(E, nu)
            mf["kn_inv"] = mf["kn_inv"].at[blocks].set(1.0 / kn_i)
            mf["ks_inv"] = mf["ks_inv"].at[blocks].set(1.0 / ks_i)
            if model.ndof == 6:
                mf["cell_D"] = mf["cell_D"].at[blocks].set(plane_strain_elasticity(E, nu))
        for stage, rows in tables.items():
            table = (scene.water.table if stage is None else
                     next(s.water_table for s in scene.stages if s.name == stage))
            ys = jnp.asarray(np.asarray(table, float)[:, 1])
            for k, x in rows.items():
                ys = ys.at[k].set(x)
            y = jnp.interp(jnp.asarray(data.water_x), jnp.asarray(table, float)[:, 0], ys)
            arr["water_y" if stage is None else f"water:{stage}"] = y
        return mf, arr


def _pad(x, p):
    return np.concatenate([x, np.zeros((p,) + x.shape[1:])])


__all__ = ["DIFFERENTIABLE", "Problem", "differentiable"]
