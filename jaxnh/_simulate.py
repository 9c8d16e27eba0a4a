"""Integration of the equations of motion with diffrax."""

from __future__ import annotations

from typing import Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .equations import METHODS, formulation
from .equations.base import as_float
from .equations.lagrange import Lagrange
from ._consistent import consistent_velocities
from ._mechanism import Mechanism
from ._sensitivity import ForwardSensitivity, auto_adjoint, solve_at, solve_forward_sensitivity
from .solvers import Tsit5
from ._stabilize import ParamsOf, ProjectedSolver, VelocityProjection, default_baumgarte_rate

__all__ = ["Solution", "simulate", "RECORDABLE", "STABILIZATIONS", "STATUS", "default_solver", "DOP853_BELOW_RTOL",
           "DOPRI8_BELOW_RTOL_LOOPED", "UNROLL_MAX_OPERATIONS", "vector_field_operations"]

RECORDABLE = ("multipliers", "energy", "residual")
STABILIZATIONS = (None, "baumgarte", "projection")


class STATUS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Why a simulation stopped: diffrax's results plus jaxnh's own."""

    non_finite_input = (
        "The initial state, the report times or the parameters contain NaN or inf; "
        "nothing was integrated."
    )
    non_finite_output = (
        "The solve finished but a reported value (coordinates, velocities, multipliers, "
        "energy or constraint residual) is NaN or inf: an overflow, or a singular "
        "dependent-velocity block at a report time."
    )
    singular_split = (
        "The dependent-velocity block of the constraint matrix (the columns not in "
        "`independent`) became singular during the run: its determinant vanished or "
        "changed sign between report times. The Appell split is invalid there and the "
        "motion reported after it is not trustworthy. Pass `independent=` so that the "
        "dependent block stays regular over the whole motion, or use method='lagrange'."
    )


class Solution(eqx.Module):
    """A simulated motion, reported at the requested times.

    Attributes:
        ts: report times (n,), s.
        q: coordinates (n, s) at `ts`.
        qd: velocities (n, s) at `ts` (dependent ones from the constraints for
            "appell"/"substituted").
        multipliers: constraint multipliers λ (n, m), when recorded: the
            constraint forces are `Aᵀ λ` with `A = ∂c/∂qd` (for the variator
            λ is the tangential contact force times the roller radius, N·m).
        energy: T + V (n,), J, when recorded.
        residual: constraint values c(q, qd, t) (n, m), when recorded; zero
            for an exact solution.
        stats: dict with `num_steps` (attempted), `num_accepted_steps`,
            `num_rejected_steps`, `rhs_evaluations` (vector-field calls:
            stages per step times attempted steps), `max_steps`.
        status: `jaxnh.STATUS` item (diffrax's `RESULTS` extended):
            `STATUS.successful`, or why the solve failed (step limit, step
            size collapse, non-finite input). After a failure the values past
            the failure time are NaN or inf, never a plausible-looking
            answer.
        names: coordinate names.
    """

    ts: Float[Array, " n"]
    q: Float[Array, "n s"]
    qd: Float[Array, "n s"]
    multipliers: Optional[Float[Array, "n m"]]
    energy: Optional[Float[Array, " n"]]
    residual: Optional[Float[Array, "n m"]]
    stats: dict
    status: STATUS
    names: tuple = eqx.field(static=True)

    @property
    def success(self):
        """Boolean (array under vmap): did the solve reach the last report time."""
        return self.status == STATUS.successful

    @property
    def message(self) -> str:
        """Why the solve failed, or "success" (concrete, un-batched solutions only)."""
        if bool(np.all(np.asarray(self.success))):
            return "success"
        msg = f"solve failed: {STATUS[self.status]}"
        if self.status == STATUS.max_steps_reached:
            msg += (
                " If the step count is large because the problem is stiff (strong damping, a large "
                "Baumgarte rate), use an implicit solver with a Newton root finder, e.g. "
                "solver=diffrax.Kvaerno5(root_finder=optimistix.Newton(rtol=rtol, atol=atol)) "
                "(diffrax's default chord iteration rejected most steps of the multiplier form); "
                "if the state became non-finite (a singular mass matrix or dependent-velocity "
                "block), check the parameters or use method='lagrange'."
            )
        return msg


DOP853_BELOW_RTOL = 1e-9
"""`default_solver` switches from a 5th- to an 8th-order method below this rtol
(the name is historical: the 8th-order default is now `diffrax.Dopri8`)."""

DOPRI8_BELOW_RTOL_LOOPED = 1e-5
"""Where jaxnh's unrolled Tsit5 is not used (large vector fields, "lagrange"),
`default_solver` switches to `diffrax.Dopri8` already below this rtol: both
diffrax solvers loop over their stages, and on the work-precision benchmarks
Dopri8 was the faster of the two at every error below ≈ 1e-5 (10-coordinate
mechanism, both forms; variator, Lagrange form: benchmarks/RESULTS.md,
"Default solver")."""

UNROLL_MAX_OPERATIONS = 300
"""Vector fields of at most this many JAX operations may get jaxnh's unrolled Tsit5.

An unrolled step holds one copy of the vector field per stage, which XLA
compiles and schedules separately: for a small mechanism (the variator's
Appell form, ≈ 250 operations) that removes diffrax's per-stage loop
overhead; for a large one (a 10-coordinate mechanism, Appell form: ≈ 1100;
the Whipple bicycle: ≈ 7000) it multiplied the compile time (bicycle: 45 s
against 7 s) and ran up to 2× slower than diffrax's Tsit5, which loops over
its stages (benchmarks/RESULTS.md).
"""


def default_solver(rtol: float, operations: Optional[int] = None, method: str = "appell"):
    """The explicit solver used when `simulate(solver=None)`.

    Arguments:
        rtol: the relative tolerance of the solve.
        operations: size of the vector field in JAX operations
            (`vector_field_operations`); None means small.
        method: the formulation ("lagrange", "appell", "substituted").

    Returns the fastest choice at matched error on the work-precision
    benchmarks (variator and a 10-coordinate mechanism, benchmarks/RESULTS.md,
    "Default solver"):
    * small vector fields (at most `UNROLL_MAX_OPERATIONS`) in the "appell"
      and "substituted" forms: jaxnh's unrolled 5th-order
      `jaxnh.solvers.Tsit5`, and `diffrax.Dopri8` (8th order) for rtol <
      `DOP853_BELOW_RTOL`;
    * large vector fields and "lagrange" (whose step gains nothing from
      unrolling: 4.2 µs either way on the variator, benchmarks/field_cost.py):
      `diffrax.Tsit5`, and `diffrax.Dopri8` for rtol < `DOPRI8_BELOW_RTOL_LOOPED`.
    """
    small = operations is None or operations <= UNROLL_MAX_OPERATIONS
    if small and method != "lagrange":
        return diffrax.Dopri8() if rtol < DOP853_BELOW_RTOL else Tsit5()
    return diffrax.Dopri8() if rtol < DOPRI8_BELOW_RTOL_LOOPED else diffrax.Tsit5()


def _count_operations(jaxpr) -> int:
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for v in eqn.params.values():
            for sub in (v if isinstance(v, (tuple, list)) else (v,)):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    n += _count_operations(inner)
    return n


def vector_field_operations(form, t, y, params) -> int:
    """Number of JAX operations (jaxpr equations, nested ones included) in one
    evaluation of the formulation's vector field: a size that does not depend
    on values, so it can be taken under `jit` and `vmap`."""
    def spec(x):
        return jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) if eqx.is_array(x) else x

    arrays, static = eqx.partition((form, t, y, params), eqx.is_array)
    arrays = jax.tree_util.tree_map(spec, arrays)
    # tracing a large vector field takes a while (the bicycle: ~0.1 s; the variator ~20 ms,
    # eight times simulate's other per-call work), so the count is remembered per structure
    try:
        key = (jax.tree_util.tree_structure((arrays, static)), tuple(jax.tree_util.tree_leaves(arrays)),
               tuple(type(x) if isinstance(x, (bool, int, float, complex)) else x
                     for x in jax.tree_util.tree_leaves(static)))
        hash(key)
    except TypeError:  # an unhashable static leaf: count every time
        key = None
    if key is not None and key in _OPERATIONS_CACHE:
        return _OPERATIONS_CACHE[key]

    def field(a):
        f, t_, y_, p = eqx.combine(a, static)
        return f.vector_field(t_, y_, p)

    n = _count_operations(jax.make_jaxpr(field)(arrays).jaxpr)
    if key is not None:
        if len(_OPERATIONS_CACHE) >= 256:
            _OPERATIONS_CACHE.pop(next(iter(_OPERATIONS_CACHE)))
        _OPERATIONS_CACHE[key] = n
    return n


_OPERATIONS_CACHE: dict = {}


def _stages_per_step(solver) -> Optional[int]:
    tab = getattr(solver, "tableau", None)
    if tab is None:
        return getattr(solver, "stages_per_step", None)
    return tab.num_stages - (1 if tab.fsal else 0)


def _check_ts(ts):
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"ts must be a 1-D array of at least 2 report times (ts[0] is the start); got shape {ts.shape}")
    if not isinstance(ts, jax.core.Tracer):
        a = np.asarray(ts)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"ts must be finite; got non-finite entries at {np.nonzero(~np.isfinite(a))[0]}")
        if not np.all(np.diff(a) > 0):
            bad = int(np.nonzero(np.diff(a) <= 0)[0][0])
            raise ValueError(f"ts must be strictly increasing; ts[{bad}]={a[bad]} ≥ ts[{bad + 1}]={a[bad + 1]}")


def simulate(
    mech: Mechanism,
    params,
    q0,
    qd0,
    ts,
    method: str = "appell",
    solver=None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    record=(),
    *,
    independent=None,
    max_steps: int = 100_000,
    dt0=None,
    adjoint: Optional[diffrax.AbstractAdjoint] = None,
    throw: bool = True,
    stabilization: Optional[str] = None,
    baumgarte_rate=None,
    dtmax=None,
    step_ts=None,
) -> Solution:
    """Integrate the equations of motion of `mech` from (q0, qd0) at ts[0].

    Arguments:
        mech: the `Mechanism`.
        params: parameter pytree passed to every user function; its arrays
            are traced, so `jax.grad`/`jax.vmap` over it work.
        q0: initial coordinates (s,).
        qd0: initial velocities (s,); must satisfy the constraints.
        ts: report times (n,), strictly increasing, s; ts[0] is the start.
        method: "appell" (default; state (q, independent velocities), the
            constraints hold exactly), "lagrange" (multipliers, state (q, qd))
            or "substituted" (the paper's wrong method, for comparison).
        solver: a diffrax solver; default `default_solver(rtol, size of the
            vector field, method)`: for small Appell vector fields jaxnh's
            unrolled Tsit5, Dopri8 below rtol 1e-9; otherwise diffrax's Tsit5,
            Dopri8 below rtol 1e-5.
        rtol, atol: relative and absolute tolerances of the PID step control.
        record: any of "multipliers", "energy", "residual" — computed at the
            report times only when asked.
        independent: indices of independent velocities ("appell",
            "substituted"); default from `mech.independent` or chosen from
            the constraint matrix at the initial state (needs concrete
            values: pass it under `jit`/`vmap`).
        max_steps: step limit; reaching it is a failed solve.
        dt0: initial step, s (default: chosen automatically).
        adjoint: how derivatives of the solve are computed. Default (None):
            `jaxnh.ForwardSensitivity()` — the sensitivities integrated with
            the state, one augmented solve whatever the mode (`jax.grad`,
            `jax.jacfwd`, `jax.jvp`) — when (params, q0, qd0) hold at most
            `jaxnh._sensitivity.FORWARD_MAX_PARAMETERS` float scalars, else
            `diffrax.RecursiveCheckpointAdjoint()` (reverse mode only: use
            `ForwardSensitivity()` explicitly with `jax.jacfwd` then). Any
            diffrax adjoint may be passed.
        throw: raise an error when the solve fails (default). With
            `throw=False` (recommended under `vmap`) check `sol.status`.
        stabilization: constraint drift control for "lagrange": None,
            "baumgarte" (rate `baumgarte_rate`, 1/s, default one over the
            median report interval) or "projection" (velocities projected
            onto the constraints after every step). See `jaxnh.stabilize`.
        baumgarte_rate: α for "baumgarte", 1/s.
        dtmax: largest step, s (default: unlimited). An adaptive solver only
            sees the right-hand side at its stages and can step over a change
            that is short compared with its step (a steep ratio law): keep
            dtmax below the width of such a change.
        step_ts: times at which a step must end, s (e.g. the centre of a
            known fast change, so that the solver cannot step over it).

    Returns:
        A `Solution`.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    record = (record,) if isinstance(record, str) else tuple(record)
    for r in record:
        if r not in RECORDABLE:
            raise ValueError(f"record entries must be among {RECORDABLE}; got {r!r}")
    if method == "substituted" and "multipliers" in record:
        raise ValueError("record='multipliers' is not available for method='substituted' (it has no multipliers)")
    if stabilization not in STABILIZATIONS:
        raise ValueError(f"stabilization must be one of {STABILIZATIONS}; got {stabilization!r}")
    if stabilization is not None and method != "lagrange":
        raise ValueError(
            f"stabilization={stabilization!r} applies to method='lagrange' only: method={method!r} "
            "integrates the independent velocities and cannot drift off the constraints."
        )
    if baumgarte_rate is not None and stabilization != "baumgarte":
        raise ValueError("baumgarte_rate is given but stabilization is not 'baumgarte'")
    q0 = as_float(q0)
    qd0 = jnp.asarray(qd0, dtype=q0.dtype)
    ts = jnp.asarray(ts, dtype=q0.dtype)
    _check_ts(ts)
    eps = float(jnp.finfo(q0.dtype).eps)
    if rtol < 10 * eps:
        raise ValueError(
            f"rtol={rtol:g} is below what {q0.dtype} can resolve (machine epsilon {eps:.2g}); "
            f"use rtol ≥ {10 * eps:.1g}" + (" or float64 inputs" if q0.dtype == jnp.float32 else "")
        )
    t0 = ts[0]
    mech.check_shapes(q0, qd0, t0, params)
    mech.check_values(q0, qd0, t0, params)
    form = formulation(mech, method, q0, qd0, t0, params, independent)
    if stabilization == "baumgarte":
        rate = default_baumgarte_rate(ts) if baumgarte_rate is None else jnp.asarray(baumgarte_rate, q0.dtype)
        form = Lagrange(mech, baumgarte=rate)
    y0 = form.state(q0, qd0, t0, params)

    if solver is None:
        solver = default_solver(rtol, vector_field_operations(form, t0, y0, params), method)
    adjoint = auto_adjoint(params, q0, qd0) if adjoint is None else adjoint
    if stabilization == "projection":
        project = VelocityProjection(mech)
        # the forward-sensitivity solve passes args = (formulation, params)
        solver = ProjectedSolver(solver, ParamsOf(project) if isinstance(adjoint, ForwardSensitivity) else project)
    controller = diffrax.PIDController(
        rtol=rtol, atol=atol, dtmax=dtmax,
        step_ts=None if step_ts is None else jnp.asarray(step_ts, dtype=q0.dtype),
    )
    ys, result, stats, out = _integrate(
        form, params, y0, ts, solver, controller, record, max_steps, dt0, adjoint, throw
    )
    q, qd = ys
    return Solution(
        ts=ts,
        q=q,
        qd=qd,
        multipliers=out.get("multipliers"),
        energy=out.get("energy"),
        residual=out.get("residual"),
        stats=stats,
        status=result,
        names=mech.coordinate_names(q0.shape[0]),
    )


@eqx.filter_jit
def _integrate(form, params, y0, ts, solver, controller, record, max_steps, dt0, adjoint, throw):
    """The compiled part of `simulate`: solve, unpack, and the recorded quantities."""
    mech = form.mech

    def vector_field(t, y, p):
        dy = form.vector_field(t, y, p)
        return jax.tree_util.tree_map(lambda d, x: d.astype(x.dtype), dy, y)

    def form_vector_field(t, y, fp):  # the formulation passed as data, so its arrays are differentiated
        form_, p = fp
        dy = form_.vector_field(t, y, p)
        return jax.tree_util.tree_map(lambda d, x: d.astype(x.dtype), dy, y)

    # Non-finite input would make the adaptive loop reject steps until
    # max_steps: detect it first, integrate a harmless stand-in, flag it.
    finite = _all_finite((y0, ts, params))
    y0_run = jax.tree_util.tree_map(lambda x: jnp.where(finite, x, jnp.zeros_like(x)), y0)
    params_run = jax.tree_util.tree_map(
        lambda x: jnp.where(finite, x, jnp.ones_like(x)) if _is_float_array(x) else x, params
    )
    ts_run = jnp.where(finite, ts, jnp.arange(ts.shape[0], dtype=ts.dtype))
    if throw:
        y0_run = eqx.error_if(y0_run, ~finite, STATUS[STATUS.non_finite_input])
    if isinstance(adjoint, ForwardSensitivity):
        sol_ys, sol_result, sol_stats = solve_forward_sensitivity(
            (form, params_run), y0_run, ts_run, controller,
            vector_field=form_vector_field, solver=solver, max_steps=max_steps, dt0=dt0, throw=throw,
        )
    else:
        sol_ys, sol_result, sol_stats = solve_at(
            vector_field, solver, y0_run, params_run, ts_run, controller, max_steps, dt0, throw, adjoint
        )
    ys = jax.tree_util.tree_map(lambda x: jnp.where(finite, x, jnp.nan), sol_ys)
    if isinstance(solver, ProjectedSolver):  # dense output between steps is unprojected
        args = (form, params) if isinstance(solver.project, ParamsOf) else params
        ys = jax.vmap(lambda t, y: solver.project(t, y, args))(ts, ys)
    q, qd = jax.vmap(lambda y, t: form.unpack(y, t, params))(ys, ts)
    out = {}
    if "multipliers" in record:
        out["multipliers"] = jax.vmap(lambda a, b, t: form.accelerations(a, b, t, params, multipliers=True)[1])(q, qd, ts)
    if "energy" in record:
        out["energy"] = jax.vmap(lambda a, b, t: mech.energy(a, b, t, params))(q, qd, ts)
    if "residual" in record:
        out["residual"] = jax.vmap(lambda a, b, t: mech.constraint(a, b, t, params))(q, qd, ts)
    stats = dict(sol_stats)
    stages = _stages_per_step(solver)
    if stages is not None:
        stats["rhs_evaluations"] = stats["num_steps"] * stages
    result = STATUS.where(finite, STATUS.promote(sol_result), STATUS.non_finite_input)
    # Never a success with NaN or inf in what is reported.
    bad_output = (result == STATUS.successful) & ~_all_finite((q, qd, out))
    result = STATUS.where(bad_output, STATUS.non_finite_output, result)
    if throw:
        q = eqx.error_if(q, bad_output, STATUS[STATUS.non_finite_output])
    split = getattr(form, "split", None)
    if split is not None and split.dependent:
        # A split that passes through a singular block gives a wrong motion with a
        # successful solve (benchmarks/STABILITY.md, C): check it at the report times.
        det = jax.vmap(lambda a, b, t: split.dependent_block_determinant(a, b, t, params))(q, qd, ts)
        tiny = jnp.sqrt(jnp.finfo(det.dtype).eps)
        singular = jnp.any((jnp.sign(det) != jnp.sign(det[0])) | (jnp.abs(det) < tiny))
        singular = (result == STATUS.successful) & singular
        result = STATUS.where(singular, STATUS.singular_split, result)
        if throw:
            q = eqx.error_if(q, singular, STATUS[STATUS.singular_split])
    return (q, qd), result, stats, out


def _is_float_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.inexact)


def _all_finite(tree):
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree) if _is_float_array(x)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)
