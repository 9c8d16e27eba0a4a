"""`simulate`: one compiled composition of a formulation, a diffrax solver, a step-size
controller, what to save, an event and an adjoint.

Everything value-dependent happens inside the compiled program: the checks of
the initial state (their outcome is a `STATUS`, no host callback), the choice
of independent velocities for Appell's equations (per batch member under
`vmap`, re-chosen during the run), the solve and the recorded quantities.
Python only resolves the static options, so a repeat call costs little more
than the compiled solve.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from typing import Any, Callable, Iterable, Optional, TypeGuard

import diffrax
import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxnh._base.compat import status_code
from jaxnh._base.compile import lean_jit, SOLVE
from jaxnh._base.host import as_data, as_float
from jaxnh._base.linalg import pick
from jaxnh._base.status import error_for, is_traced, raise_in_graph, STATUS
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._equations import Appell, as_formulation, Formulation, Lagrange
from jaxnh._equations.scalarize import scalarized
from jaxnh._equations.step_maps import normalize_quaternions
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.profiles import declared_breakpoints, Profile
from jaxnh._solve.diagnose import (
    diagnose_stall,
    initial_checks,
    on_branch,
    root_finder_fails,
    spectral_radius,
    step_bound_count,
    STIFF_ABOVE,
)
from jaxnh._solve.friction import MAX_TRANSITIONS, simulate_friction
from jaxnh._solve.outputs import all_finite, bcast, input_sum, nan_link, no_grad, run_checked
from jaxnh._solve.rk import UnrolledTsit5
from jaxnh._solve.sensitivity import choose_adjoint, diffrax_solve, forward_mode_outputs, ForwardSensitivity
from jaxnh._solve.solution import DenseMotion, Expansion, Solution
from jaxnh._solve.stepping import coarse_interpolant


__all__ = [
    "Solution",
    "simulate",
    "RECORDABLE",
    "STABILIZATIONS",
    "STATUS",
    "default_solver",
    "DOP853_BELOW_RTOL",
    "DOPRI8_BELOW_RTOL_LOOPED",
    "UNROLL_MAX_OPERATIONS",
    "vector_field_operations",
    "field",
]

RECORDABLE = ("multipliers", "energy", "residual")
STABILIZATIONS = (None, "baumgarte", "projection")

DOP853_BELOW_RTOL = 1e-9
"""`default_solver` switches from a 5th- to an 8th-order method below this rtol
(the name is historical: the 8th-order default is `diffrax.Dopri8`)."""

DOPRI8_BELOW_RTOL_LOOPED = 1e-5
"""For large vector fields (where jaxnh's unrolled Tsit5 is not used), `default_solver`
switches to `diffrax.Dopri8` already below this rtol: both diffrax solvers loop over
their stages, and on the work-precision benchmarks Dopri8 was the faster of the two at
every error below ≈ 1e-5 (10-coordinate mechanism and rolling ball, both forms:
benchmarks/RESULTS.md, "Work–precision")."""

UNROLL_MAX_OPERATIONS = 300
"""Vector fields of at most this many JAX operations get jaxnh's unrolled Tsit5.

An unrolled step holds one copy of the vector field per stage, which XLA
compiles and schedules separately: for a small mechanism (the variator, in
either form) that removes diffrax's per-stage loop overhead; for a large one
(a 10-coordinate mechanism, the Whipple bicycle) it multiplied the compile
time and ran up to 2× slower than diffrax's Tsit5, which loops over its
stages (benchmarks/RESULTS.md).
"""


def default_solver(
    rtol: float, operations: Optional[int] = None, method: str = "lagrange"
) -> diffrax.AbstractSolver[Any]:
    """The explicit solver used when `simulate(solver=None)`.

    Arguments:
        rtol: the relative tolerance of the solve.
        operations: size of the vector field in JAX operations
            (`vector_field_operations`); None means small.
        method: the formulation's name ("lagrange", "appell", "substituted");
            the choice does not depend on it (kept for callers that pass it).

    Returns the fastest choice at matched error on the work-precision
    benchmarks (benchmarks/RESULTS.md, "Work–precision"):
    * small vector fields (at most `UNROLL_MAX_OPERATIONS`), in every form:
      jaxnh's unrolled 5th-order `jaxnh.solvers.UnrolledTsit5`, and
      `diffrax.Dopri8` (8th order) for rtol < `DOP853_BELOW_RTOL`. (On the
      variator at rtol 1e-8, Lagrange's form: 0.38 ms per solve and an error of
      1.5e-6, against 0.75 ms and 9.5e-7 for Dopri8 and 0.52 ms and 1.5e-6 for
      diffrax's looped Tsit5.)
    * large vector fields: `diffrax.Tsit5`, and `diffrax.Dopri8` for rtol <
      `DOPRI8_BELOW_RTOL_LOOPED`.
    """
    del method
    small = operations is None or operations <= UNROLL_MAX_OPERATIONS
    if small:
        return diffrax.Dopri8() if rtol < DOP853_BELOW_RTOL else UnrolledTsit5()
    return diffrax.Dopri8() if rtol < DOPRI8_BELOW_RTOL_LOOPED else diffrax.Tsit5()


def _count_operations(jaxpr) -> int:
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    n += _count_operations(inner)
    return n


def vector_field_operations(form, t, y, params) -> int:
    """Number of JAX operations (jaxpr equations, nested ones included) in one
    evaluation of a bound formulation's vector field: a size that does not
    depend on values (call it while tracing: it only traces)."""
    return _count_operations(jax.make_jaxpr(lambda y_: form.vector_field(t, y_, params))(y).jaxpr)


def field(t, y, args):
    """The vector field of every jaxnh solve: args = (bound formulation, params, ok).

    `ok` (False when the initial state failed a check) is for the step maps; the field does
    not test it: a solve whose check failed has zero length (`_run_traced`). A select on a traced
    flag applied to the field's output kept XLA from fusing diffrax's Runge–Kutta stages
    (variator with diffrax's Tsit5: 13 more kernels launched per stage).
    """
    form, params, _ = args
    return _vector_field(t, y, form, params)


@eqx.filter_jit
def _vector_field(t, y, form, params):
    """The formulation's vector field, traced once per structure of its arguments.

    A solve evaluates the field in many places (the solver's stages, its first step, the step
    maps, forward sensitivities): as a jitted function its trace (and the derivatives JAX takes
    of it) is made once and reused at every place, instead of tracing the user's energies anew
    each time. Small fields are flattened to scalar operations (`jaxnh._equations.scalarize`).
    """
    return scalarized(form.vector_field)(t, y, params)


def _stages_per_step(solver) -> Optional[int]:
    tab = getattr(solver, "tableau", None)
    if tab is None:
        return getattr(solver, "stages_per_step", None)
    return tab.num_stages - (1 if tab.fsal else 0)


@functools.lru_cache(maxsize=256)
def _resolve(method, independent, stabilization, baumgarte_rate_given):
    """The unbound formulation for the string/option aliases (cached: Python-side cost per call)."""
    form = as_formulation(method, independent)
    if stabilization not in STABILIZATIONS:
        raise ValueError(f"stabilization must be one of {STABILIZATIONS}; got {stabilization!r}")
    if stabilization is not None and not isinstance(form, Lagrange):
        raise ValueError(
            f"stabilization={stabilization!r} applies to method='lagrange' only: method={method!r} "
            "integrates the independent velocities and cannot drift off the constraints."
        )
    if baumgarte_rate_given and stabilization != "baumgarte":
        raise ValueError("baumgarte_rate is given but stabilization is not 'baumgarte'")
    if stabilization == "baumgarte":
        form = Lagrange(baumgarte="auto")
    elif stabilization == "projection":
        form = Lagrange(projection=True)
    return form


def _record(record, form) -> tuple:
    record = (record,) if isinstance(record, str) else tuple(record)
    for r in record:
        if r not in RECORDABLE:
            raise ValueError(f"record entries must be among {RECORDABLE}; got {r!r}")
    if "multipliers" in record and not form.has_multipliers:
        raise ValueError(f"record='multipliers' is not available for method={form.name!r} (it has no multipliers)")
    return tuple(r for r in RECORDABLE if r in record)  # one order: the same program for any order given


def simulate(
    mech: Mechanism,
    params: PyTree,
    q0: ArrayInput,
    qd0: ArrayInput,
    ts: ArrayInput,
    method: str | Formulation = "lagrange",
    solver: Optional[diffrax.AbstractSolver[Any]] = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    record: str | Iterable[str] = (),
    *,
    independent: Optional[Iterable[int]] = None,
    saveat: Optional[diffrax.SaveAt] = None,
    stepsize_controller: Optional[diffrax.AbstractStepSizeController[Any, Any]] = None,
    event: Optional[diffrax.Event] = None,
    progress_meter: Optional[diffrax.AbstractProgressMeter[Any]] = None,
    adjoint: Optional[diffrax.AbstractAdjoint | ForwardSensitivity] = None,
    max_steps: int = 100_000,
    dt0: Optional[float | jax.Array] = None,
    throw: bool = True,
    stabilization: Optional[str] = None,
    baumgarte_rate: Optional[float | jax.Array] = None,
    dtmax: Optional[float | jax.Array] = None,
    step_ts: Optional[ArrayInput] = None,
    max_transitions: int = MAX_TRANSITIONS,
) -> Solution:
    """Integrate the equations of motion of `mech` from (q0, qd0) at ts[0].

    Works the same eagerly and under `jax.jit`, `jax.vmap` and `jax.grad`:
    nothing needs concrete values.

    Arguments:
        mech: the `Mechanism`.
        params: parameter pytree passed to every user function; its arrays
            are traced, so `jax.grad`/`jax.vmap` over it work.
        q0: initial coordinates (s,).
        qd0: initial velocities (s,); must satisfy the constraints to √eps
            relative to the velocity scale (else `STATUS.inconsistent_velocities`).
        ts: report times (n,), strictly increasing, s; ts[0] is the start and
            ts[-1] the end.
        method: a formulation object — `jaxnh.Lagrange(baumgarte=...,
            projection=...)` (the default `Lagrange()`; multipliers, state
            (q, qd)), `jaxnh.Appell()` (state (q, independent velocities),
            the constraints hold exactly), `jaxnh.Substituted()` (the paper's
            wrong method, for comparison) — or its name "lagrange", "appell",
            "substituted". Lagrange's is the default: at the same error it
            took 0.78–0.96× Appell's time on a rolling ball, 0.78–0.87× on a
            car with four trailers and 0.71–0.83× on the variator (`python -m
            benchmarks.precision`), and its first call is the shorter one on
            large mechanisms (a car with 16 trailers: 6.4 s of CPU after the
            import against 12.8 s; `python -m benchmarks.size`).
        solver: a diffrax solver; default `default_solver(rtol, size of the
            vector field, method)`.
        rtol, atol: relative and absolute tolerances of the default PID step
            control (ignored when `stepsize_controller` is given).
        record: any of "multipliers", "energy", "residual" — computed at the
            saved times only when asked.
        independent: fixed indices of independent velocities ("appell",
            "substituted"), the same as `method=jaxnh.Appell(independent=...)`;
            default None: chosen and re-chosen inside the program (refused with
            Lagrange's equations, which integrate all velocities).
        saveat: a `diffrax.SaveAt` (default `SaveAt(ts=ts)`); with
            `dense=True` the solution's `evaluate(t)` gives the motion at any t.
        stepsize_controller: a diffrax step-size controller (default a
            `PIDController(rtol, atol, dtmax=dtmax, step_ts=step_ts)`).
        event: a `diffrax.Event` whose `cond_fn(t, y, args, **kwargs)` receives
            `y = (q, qd)` and `args = params`; a terminating event stops the run
            (the saved times after it are inf; `sol.event_mask` says which).
        progress_meter: a diffrax progress meter (e.g. `diffrax.TqdmProgressMeter()`).
        adjoint: how derivatives are computed. Default None: the one policy of
            simulate and fit (`choose_adjoint`): `jaxnh.ForwardSensitivity()`
            (sensitivities integrated with the state and included in the error
            control; one augmented solve for grad, jacfwd and jvp) for at most
            `jaxnh.FORWARD_MAX_PARAMETERS` float scalars in (params, q0, qd0)
            and no dense output or event, else
            `diffrax.RecursiveCheckpointAdjoint()`. Any diffrax adjoint may be passed.
        max_steps: step limit; reaching it is a failed solve.
        dt0: initial step, s (default: chosen automatically).
        throw: raise a `jaxnh.SimulationError` when the solve fails (default).
            With `throw=False` (recommended under `vmap`) check `sol.status`.
        stabilization: shortcut for Lagrange's drift control: "baumgarte"
            (`Lagrange(baumgarte=rate)`, rate `baumgarte_rate`, 1/s, default one
            over the median report interval) or "projection"
            (`Lagrange(projection=True)`).
        baumgarte_rate: α for "baumgarte", 1/s.
        dtmax: largest step, s (default: unlimited).
        step_ts: times at which a step must end, s. An adaptive solver only
            sees the right-hand side at its stages and can step over a change
            that is short compared with its step (a ratio step of 1 µs in a
            run of 0.1-s steps) with no sign in its error estimate: give the
            time of such a change here. Profiles in `params` declare their own
            (`jaxnh.profiles.SmoothStep`, the knots of `PiecewiseLinear`),
            which are added to these; with an own `stepsize_controller`,
            they are applied when it is a `diffrax.PIDController`.
        max_transitions: for a mechanism with friction contacts, the most
            changes between sticking and slipping (restarts of the solve);
            more stop it with `STATUS.friction_transitions_exceeded`.

    Returns:
        A `Solution`.
    """
    ind = None if independent is None else tuple(int(i) for i in independent)
    hashable = _hashable(method)
    cached_form = hashable and baumgarte_rate is None  # (no arrays: nothing in it can be traced)
    if hashable:  # names and array-free formulation objects: resolved once, cached
        form = _resolve(method, ind, stabilization, baumgarte_rate is not None)
    else:
        form = as_formulation(method, ind)
    if baumgarte_rate is not None:
        form = Lagrange(baumgarte=baumgarte_rate)
    if ind is not None and isinstance(form, Lagrange):  # (stabilization= and baumgarte_rate= make it Lagrange's)
        as_formulation(form, ind)  # refused there, naming method='appell'
    record = _record(record, form)
    if not _is_float_jax_array(q0) or not _is_jax_array(qd0, q0.dtype) or not _is_jax_array(ts, q0.dtype):
        for name, x in (("q0", q0), ("qd0", qd0), ("ts", ts)):
            _check_real_numbers(name, x)
    q0 = q0 if _is_float_jax_array(q0) else as_float(q0)
    qd0 = qd0 if _is_jax_array(qd0, q0.dtype) else jnp.asarray(qd0, dtype=q0.dtype)
    ts_given = ts
    ts = ts if _is_jax_array(ts, q0.dtype) else jnp.asarray(ts, dtype=q0.dtype)
    _check_cast_times(ts_given, ts)
    params = as_data(params, q0)  # one program per structure of params, not per value
    leaves, params_def = jax.tree_util.tree_flatten(params)
    if any(_is_complex(x) for x in leaves):
        _refuse_complex(params)
    _check_param_leaves(leaves)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(
            f"ts must be a 1-D array of at least 2 report times (ts[0] is the start); got shape {ts.shape}"
        )
    if q0.dtype not in (jnp.float32, jnp.float64):
        raise ValueError(
            f"q0 has dtype {q0.dtype}: jaxnh computes in float32 or float64; pass float32 or float64 arrays"
        )
    if solver is not None and not isinstance(solver, diffrax.AbstractSolver):
        raise TypeError(
            "solver must be a diffrax solver object, e.g. diffrax.Tsit5() or jaxnh.solvers.UnrolledTsit5(), or None "
            f"for the default; got {solver!r}"
        )
    if not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer; got {max_steps!r}")
    eps = float(np.finfo(q0.dtype).eps)
    for name, value in (("rtol", rtol), ("atol", atol)):
        number = isinstance(value, (int, float, np.number, np.ndarray, jax.Array)) and not isinstance(value, bool)
        if not number or np.ndim(value) != 0 or not (0 <= float(value) < np.inf):
            raise ValueError(
                f"{name}={value!r}: the tolerances must be finite real numbers ≥ 0 (rtol relative, atol in the "
                f"units of the state), e.g. rtol=1e-8, atol=1e-10"
            )
    if rtol < 10 * eps:
        raise ValueError(
            f"rtol={rtol:g} is below what {q0.dtype} can resolve (machine epsilon {eps:.2g}); "
            f"use rtol ≥ {10 * eps:.1g}" + (" or float64 inputs" if q0.dtype == jnp.float32 else "")
        )
    _check_dtmax(dtmax, stepsize_controller)
    given_step_ts = step_ts is not None
    declared = declared_breakpoints(params, q0.dtype) if _holds_profile(params_def) else None
    if declared is not None:
        step_ts = declared if step_ts is None else jnp.sort(jnp.concatenate([_as_times(step_ts, q0.dtype), declared]))
    if coarse_interpolant(solver) and (
        stepsize_controller is None or isinstance(stepsize_controller, diffrax.PIDController)
    ):
        # e.g. Kvaerno5: a fifth-order method whose dense output is a third-order Hermite
        # interpolant; between its long (implicit) steps a report would carry the interpolant's
        # error, far above the tolerance (4.5e-5 relative at rtol 1e-9): end a step at every report
        step_ts = ts if step_ts is None else jnp.sort(jnp.concatenate([_as_times(step_ts, q0.dtype), ts]))
    if step_ts is not None and stepsize_controller is not None:
        if isinstance(stepsize_controller, diffrax.PIDController):
            stepsize_controller = diffrax.ClipStepSizeController(
                stepsize_controller, step_ts=_as_times(step_ts, q0.dtype)
            )
        elif given_step_ts:
            raise ValueError(
                f"step_ts: applies to the default controller or a diffrax.PIDController; with "
                f"stepsize_controller={type(stepsize_controller).__name__}, put the step times in it"
            )
        # (an own controller of another kind chooses its steps itself: the profiles' breakpoints are left to it)
        step_ts = None
    if stepsize_controller is None:
        # the tolerances are data (a new rtol reuses the compiled program unless it
        # changes the default solver's order, see `_rtol_class`)
        if dtmax is None and step_ts is None and _hashable(rtol) and _hashable(atol):
            stepsize_controller = _pid(rtol, atol, q0.dtype)  # cached: no arrays made per call
        else:
            tol: dict[str, Any] = dict(rtol=jnp.asarray(rtol, dtype=q0.dtype), atol=jnp.asarray(atol, dtype=q0.dtype))
            stepsize_controller = diffrax.PIDController(**tol, dtmax=dtmax)
            if step_ts is not None:
                stepsize_controller = diffrax.ClipStepSizeController(
                    stepsize_controller, step_ts=_as_times(step_ts, q0.dtype)
                )
    if (
        dt0 is not None
        and not is_traced(dt0)
        and not (
            isinstance(dt0, (int, float, np.number, np.ndarray, jax.Array)) and np.ndim(dt0) == 0 and float(dt0) > 0
        )
    ):
        raise ValueError(f"dt0={dt0!r}: the initial step must be positive (s), or None for an automatic choice")
    if mech.contacts:  # friction-held rows: the segmented solve (jaxnh/_solve/friction.py)
        return simulate_friction(
            mech, form, params, q0, qd0, ts, stepsize_controller=stepsize_controller, record=record,
            solver=default_solver(float(rtol), None, form.name) if solver is None else solver,
            saveat=saveat, event=event, progress_meter=progress_meter, adjoint=adjoint, max_steps=max_steps, dt0=dt0,
            throw=throw, rtol=float(rtol), max_transitions=max_transitions,
        )  # fmt: skip
    traced = is_traced(leaves, q0, qd0, ts) or (not cached_form and is_traced(form))

    def solve(graph_throw: bool) -> Solution:
        try:
            return _run(
                mech, form, params, q0, qd0, ts, solver, stepsize_controller, saveat, event, progress_meter, adjoint,
                dt0, record=record, max_steps=int(max_steps), rtol=_rtol_class(float(rtol)), graph_throw=graph_throw,
            )  # fmt: skip
        except TypeError as e:  # JAX's words name no argument: say which one and the fix
            if "custom_vjp" not in str(e):
                raise
            raise TypeError(
                "simulate: forward-mode derivatives (jax.jvp, jax.jacfwd) cannot go through a reverse-mode adjoint "
                f"(adjoint={adjoint!r}; diffrax's RecursiveCheckpointAdjoint is the default with events, dense "
                "output and progress meters): pass adjoint=diffrax.ForwardMode(), or use jax.grad / jax.jacrev"
            ) from e

    sol, traced = run_checked(solve, traced, bool(throw))
    if throw and not traced and np.ndim(status_code(sol.status)) == 0 and int(np.asarray(status_code(sol.status))) != 0:
        err = error_for(sol.status)
        if isinstance(err, ValueError):  # name the argument and show the values, eagerly
            try:
                _check_ts(ts)
                mech.check_values(q0, qd0, ts[0], params)
            except ValueError as detail:
                err = type(err)(f"{err}\nDetails: {detail}", sol.status)
        stopped = sol.stats.get("stopped_at") if isinstance(sol.stats, dict) else None
        if not isinstance(err, ValueError) and stopped is not None and np.ndim(stopped) == 0:
            err = type(err)(f"{err} (The solve stopped at t = {float(stopped):.10g} s.)", sol.status)
        raise err
    return sol


def _check_dtmax(dtmax, controller) -> None:
    """Refuse, naming dtmax, a largest step that is not a positive finite number (given as
    `dtmax=` or in a `diffrax.PIDController`): the steps could never advance, and the solve would
    run out of max_steps at t0."""
    for where, value in (("dtmax", dtmax), ("stepsize_controller.dtmax", getattr(controller, "dtmax", None))):
        if value is None or is_traced(value):
            continue
        number = isinstance(value, (int, float, np.number, np.ndarray, jax.Array)) and not isinstance(value, bool)
        if not number or np.ndim(value) != 0 or not (0 < float(value) < np.inf):
            raise ValueError(
                f"{where}={value!r}: the largest step must be a positive finite time (s), or None for no bound"
            )


def _boolean_condition(conditions, t, y, args) -> bool:
    """Whether any of an Event's conditions (a pytree of them) returns a bool (an event without a root)."""
    conds = jax.tree_util.tree_leaves(conditions, is_leaf=callable)
    # (args closed over, not abstracted: the formulation in them has Python flags its methods branch on)
    return any(jnp.dtype(jax.eval_shape(lambda t_, y_, c=c: c(t_, y_, args), t, y).dtype) == jnp.bool_ for c in conds)


@jax.custom_jvp
def _refuse_derivative(x):
    return x


@_refuse_derivative.defjvp
def _refuse_derivative_jvp(primals, tangents):
    raise TypeError(
        "simulate: the solve ends at an event whose condition is boolean: it has no root to locate, so "
        "the event's time (and everything after it) has no derivative (it would come out 0). Write the "
        "condition as a real-valued function of (t, (q, qd), params) whose sign change marks the event "
        "(e.g. `q[0] - 1.0` rather than `q[0] > 1.0`): its time is then located by root finding and "
        "differentiable"
    )


def _refuse_derivatives(tree):
    return jax.tree_util.tree_map(lambda x: _refuse_derivative(x) if eqx.is_inexact_array(x) else x, tree)


def _check_cast_times(given, ts) -> None:
    """Refuse report times that were strictly increasing in their own dtype but are not once cast
    to q0's (e.g. float64 times a few µs apart with a float32 q0), naming the mixed dtypes."""
    if given is ts or is_traced(given):
        return
    a = np.asarray(given, dtype=float) if isinstance(given, (list, tuple)) else np.asarray(given)
    if a.ndim != 1 or a.shape[0] < 2 or not np.issubdtype(a.dtype, np.floating) or a.dtype == ts.dtype:
        return
    cast = np.asarray(ts, dtype=float)
    if bool(np.all(np.diff(a.astype(float)) > 0)) and not bool(np.all(np.diff(cast) > 0)):
        raise ValueError(
            f"ts: the report times are {a.dtype} and q0 is {ts.dtype}; jaxnh computes in q0's dtype, and cast to "
            f"{ts.dtype} the times are no longer strictly increasing (some are closer than its resolution). "
            f"Pass q0 and qd0 in {a.dtype}, or report times that {ts.dtype} can tell apart."
        )


@functools.lru_cache(maxsize=64)
def _pid(rtol, atol, dtype):
    # arrays: data to the compiled program (not a static constant). Made eagerly even when the
    # first call is traced (a jnp array made while tracing would be a tracer, unsafe to cache);
    # JAX arrays, not NumPy scalars, which a call would copy to the device every time
    with jax.ensure_compile_time_eval():
        rtol, atol = jnp.asarray(rtol, dtype=dtype), jnp.asarray(atol, dtype=dtype)
    return diffrax.PIDController(rtol=rtol, atol=atol)


def _rtol_class(rtol: float) -> float:
    """A stand-in for `rtol` that makes every rtol-dependent choice of the compiled
    program (`default_solver`'s order, the lean loop's tableau) the same way.

    The choices compare rtol with the thresholds `DOP853_BELOW_RTOL` and
    `DOPRI8_BELOW_RTOL_LOOPED` (a factor > 2 apart): half of the smallest
    threshold above rtol (1 above all) lies on the same side of each. The
    tolerance itself reaches the step control as an array, so tolerances
    within one class share one compiled program.
    """
    above = [th for th in (DOP853_BELOW_RTOL, DOPRI8_BELOW_RTOL_LOOPED) if rtol < th]
    return 0.5 * min(above) if above else 1.0


def _check_real_numbers(name, x):
    """Raise, naming the argument, for input that is not an array of real numbers (strings, complex)."""
    if is_traced(x):
        kind = x.dtype
    else:
        try:
            kind = np.asarray(x).dtype
        except Exception as err:  # ragged lists and the like
            raise ValueError(f"{name} must be an array of real numbers; got {x!r} ({err})") from None
    if not (np.issubdtype(kind, np.floating) or np.issubdtype(kind, np.integer) or np.issubdtype(kind, np.bool_)):
        raise ValueError(
            f"{name} must be an array of real numbers (float32 or float64); got dtype {kind} from {x!r:.80}"
            + (
                ": drop the imaginary part explicitly if it is meant to be zero"
                if np.issubdtype(kind, np.complexfloating)
                else ""
            )
        )


_PLAIN_LEAVES = (jax.Array, np.ndarray, np.generic, int, float, bool, str, bytes, type(None), enum.Enum)


def _check_param_leaves(leaves) -> None:
    """Refuse a params leaf that is an arbitrary object: JAX would treat it as one opaque constant
    (its numbers compiled in, never differentiated or batched), or fail inside equinox or JAX with
    a message that names nothing."""
    for x in leaves:
        if isinstance(x, _PLAIN_LEAVES) or callable(x):
            continue
        raise TypeError(
            f"params: found an object of type {type(x).__name__} that JAX cannot look into (it is not a "
            "pytree: not a dict, list, tuple, NamedTuple, equinox.Module or registered dataclass), so its "
            "numbers would be neither differentiated nor batched. Pass params as a dict (or another pytree) "
            f"of arrays and numbers; got {x!r:.200}"
        )


def _is_complex(x) -> bool:
    if isinstance(x, jax.Array):
        return x.dtype.kind == "c"
    return isinstance(x, complex) or (hasattr(x, "dtype") and np.iscomplexobj(x))


def _holds_profile(params_def) -> bool:
    """Whether a params structure holds a `Profile` (its breakpoints are looked for only then;
    one answer per structure, True when the structure cannot say)."""
    try:
        return _structure_holds_profile(params_def)
    except Exception:  # an unhashable structure, or a user node that refuses placeholder leaves
        return True


@functools.lru_cache(maxsize=256)
def _structure_holds_profile(params_def) -> bool:
    tree = jax.tree_util.tree_unflatten(params_def, [None] * params_def.num_leaves)
    found = jax.tree_util.tree_leaves(tree, is_leaf=lambda x: isinstance(x, Profile))
    return any(isinstance(x, Profile) for x in found)


def _as_times(step_ts, dtype):
    """step_ts as a sorted 1-D array of the state's dtype."""
    return jnp.sort(jnp.ravel(jnp.asarray(step_ts, dtype=dtype)))


def _refuse_complex(params):
    bad = [jax.tree_util.keystr(path) for path, x in jax.tree_util.tree_leaves_with_path(params) if _is_complex(x)]
    raise ValueError(
        f"params{', params'.join(bad)} {'is' if len(bad) == 1 else 'are'} complex: jaxnh's energies, forces and "
        "constraints take real parameters (SI units); pass the real part explicitly if the imaginary part is zero"
    )


def _is_jax_array(x: object, dtype: Any) -> TypeGuard[jax.Array]:
    return isinstance(x, jax.Array) and x.dtype == dtype


def _is_float_jax_array(x: object) -> TypeGuard[jax.Array]:
    return isinstance(x, jax.Array) and x.dtype in (jnp.float32, jnp.float64)


def _check_ts(ts):
    """Raise naming the entries of concrete report times that are not finite or not increasing."""
    a = np.asarray(ts)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"ts must be finite; got non-finite entries at {np.nonzero(~np.isfinite(a))[0].tolist()}")
    if not np.all(np.diff(a) > 0):
        bad = int(np.nonzero(np.diff(a) <= 0)[0][0])
        raise ValueError(f"ts must be strictly increasing; ts[{bad}]={a[bad]:g} ≥ ts[{bad + 1}]={a[bad + 1]:g}")


def _hashable(x) -> bool:
    try:
        hash(x)
        return True
    except TypeError:
        return False


def _clip_save_times(saveat, ok, t0):
    """`saveat` with every time it saves at moved to t0 where not `ok` (a zero-length solve)."""
    subs = jax.tree_util.tree_leaves(saveat.subs, is_leaf=lambda x: isinstance(x, diffrax.SubSaveAt))
    with_ts = [x for x in subs if x.ts is not None]
    if not with_ts:
        return saveat
    return eqx.tree_at(
        lambda s: [
            x.ts
            for x in jax.tree_util.tree_leaves(s.subs, is_leaf=lambda x: isinstance(x, diffrax.SubSaveAt))
            if x.ts is not None
        ],
        saveat,
        [jnp.where(ok, x.ts, t0).astype(x.ts.dtype) for x in with_ts],
    )


class _UserEvent(eqx.Module):
    """A user's event condition, called with (q, qd) in all coordinates and params."""

    cond_fn: Callable
    expand: Optional[Expansion] = None  # for a solve that eliminates dependent coordinates

    def __call__(self, t, y, args, **kwargs):
        form, params, _ = args
        q, qd = form.unpack(y, t, params)
        if self.expand is not None:
            q, qd, params = self.expand(q, qd, t, params)
        return self.cond_fn(t, (q, qd), params, **kwargs)


def reindexed(form, free: tuple):
    """`form` with its fixed independent velocities given among the free coordinates `free`."""
    ind = getattr(form, "independent", None)
    if ind is None:
        return form
    dependent = [i for i in ind if i not in free]
    if dependent:
        raise ValueError(
            f"independent={tuple(ind)}: coordinates {tuple(dependent)} are `dependent` (solved from the holonomic "
            f"constraints, their rates follow from ġ = 0); choose the independent velocities among {free}"
        )
    return dataclasses.replace(form, independent=tuple(free.index(i) for i in ind))


def eliminate(mech: Mechanism, form, params, q0, qd0):
    """The solve of a mechanism with `dependent` coordinates, set up in the s − h others.

    Returns (the reduced mechanism, `form` with its independent velocities among the free
    coordinates, the reduced mechanism's params `(params, start)` with Newton's start at q0's
    dependent coordinates (the branch q0 lies on), q0 and qd0 of the free coordinates, and the
    `Expansion` that maps the solve's states back to all coordinates).
    """
    free = mech.free_coordinates(q0.shape[0])
    start = jax.lax.stop_gradient(pick(q0, mech.dependent))
    run = (params, jnp.where(jnp.isfinite(start), start, 0.0))
    reduced = mech.reduced_from_start(q0.shape[0])
    return reduced, reindexed(form, free), run, pick(q0, free), pick(qd0, free), Expansion(mech)


def _run_traced(
    mech,
    form,
    params,
    q0,
    qd0,
    ts,
    solver,
    controller,
    saveat,
    event,
    progress_meter,
    adjoint,
    dt0,
    *,
    record,
    max_steps,
    rtol,
    graph_throw,
):
    """The compiled part of `simulate`."""
    t0 = ts[0]
    m = mech.check_shapes(q0, qd0, t0, params)
    s = qd0.shape[0]  # velocities (speeds, with `kinematics`)
    full = full_form = expand = None
    inputs = (q0, qd0)
    run = params  # the params of the formulation's functions
    if mech.dependent is not None:
        # holonomic constraints solved for the dependent coordinates: the solve integrates the
        # mechanism in the s − h others, with Newton's method started at q0's dependent
        # coordinates (the branch q0 is on), and the outputs are mapped back to all s
        full, full_form = mech, Lagrange().bind(mech, s, m)  # the full initial state is checked as given
        mech, form, run, q0, qd0, expand = eliminate(full, form, params, q0, qd0)
        m = mech.check_shapes(q0, qd0, t0, run)
        s = q0.shape[0]
    if isinstance(form, Lagrange) and isinstance(form.baumgarte, str):
        form = Lagrange(baumgarte=1.0 / jnp.median(jnp.diff(ts)), projection=form.projection)
    form = form.bind(mech, s, m, q0.shape[0])
    finite = all_finite((inputs, ts, params, form))
    increasing = jnp.all(jnp.diff(ts) > 0)
    q0r = jnp.where(finite, q0, 0.0)
    qd0r = jnp.where(finite, qd0, 0.0)
    tsr = jnp.where(finite & increasing, ts, jnp.arange(ts.shape[0], dtype=ts.dtype))
    t0r = tsr[0]
    # the checks and diagnoses below only decide a status: no derivative flows through them, and
    # cutting it at their inputs spares tracing their tangents under jvp/grad (a fit's Jacobian)
    checked, check_status, inertias = initial_checks(*no_grad((form, q0r, qd0r, t0r, run)))
    if full is not None:  # the full state first: g(q0) = 0, ġ = 0 and c = 0, on the branch `guess` picks
        qf, qdf = (jnp.where(finite, x, 0.0) for x in inputs)
        full_ok, full_status, _ = initial_checks(*no_grad((full_form, qf, qdf, t0r, params)))
        branch = on_branch(*no_grad((full, qf, t0r, params)))  # (with a `guess`: the one it reaches)
        full_status = STATUS.where(full_ok & ~branch, STATUS.holonomic_branch, full_status)  # pyright: ignore[reportArgumentType]
        check_status = STATUS.where(full_ok & branch, check_status, full_status)  # pyright: ignore[reportArgumentType]
        checked = full_ok & branch & checked
    ok = finite & increasing & checked
    if mech.quaternions:  # (unit to √eps, checked above: to rounding from here on)
        q0r = normalize_quaternions(q0r, mech.quaternions)
    y0 = form.state(q0r, qd0r, t0r, run)
    y0 = jax.tree_util.tree_map(lambda x: jnp.where(ok, x, jnp.zeros_like(x)), y0)
    if graph_throw:  # an invalid input raises before the solve: the solve depends on it, so it is never pruned
        # (equinox types Enumerations as enum.Enum: an item STATUS inherits from diffrax looks like diffrax's)
        pre = STATUS.where(checked, STATUS.successful, check_status)  # pyright: ignore[reportArgumentType]
        pre = STATUS.where(increasing, pre, STATUS.bad_report_times)
        pre = STATUS.where(finite, pre, STATUS.non_finite_input)
        y0 = jax.tree_util.tree_map(lambda x: raise_in_graph(x, pre), y0)
    if solver is None:
        solver = default_solver(rtol, vector_field_operations(form, t0, y0, run), form.name)
    dense = saveat is not None and bool(saveat.dense)
    # a progress meter, like dense output and events, needs a diffrax adjoint
    adjoint = choose_adjoint(adjoint, params, q0, qd0, dense=dense or event is not None or progress_meter is not None)
    # with the default saving, keep the last state reached for a failure's diagnosis: reports at ts,
    # and separately the state at the end (or where a failed solve stopped). BacksolveAdjoint
    # cannot save `subs`: it gets the reports alone, and a failure is diagnosed at the last one.
    diagnose = saveat is None and not isinstance(adjoint, diffrax.BacksolveAdjoint)
    own_saveat = saveat is None
    # a solve whose initial check failed has zero length: no step is taken, and every report is
    # the (zero) stand-in state at t0, which the outputs replace by NaN below
    t_end = jnp.where(ok, tsr[-1], t0r)
    ts_save = jnp.where(ok, tsr, t0r)
    if diagnose:
        saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(ts=ts_save), diffrax.SubSaveAt(t1=True)])
    elif saveat is None:
        saveat = diffrax.SaveAt(ts=ts_save)
    else:
        saveat = _clip_save_times(saveat, ok, t0r)
    args = (form, run, ok)
    boolean = False
    if event is not None:
        # diffrax 0.7.0 (the oldest supported) has no `direction` on its Event; 0.7.2 has
        direction = {"direction": event.direction} if hasattr(event, "direction") else {}
        conditions = jax.tree_util.tree_map(lambda f: _UserEvent(f, expand), event.cond_fn, is_leaf=callable)
        boolean = _boolean_condition(conditions, t0r, y0, args)
        # an event without a root finder would end at the end of the step that crossed it, with a
        # time whose derivative is 0: it gets Newton's method on the solver's interpolant, so its
        # time is located to the tolerance and differentiable (a boolean condition has no root to
        # find and keeps diffrax's behaviour: its derivatives are refused below)
        root_finder = event.root_finder
        if root_finder is None and not boolean:
            # Newton converges quadratically on the smooth interpolant: a tolerance of 1e-3 √eps
            # (1.5e-11 in float64) costs an iteration or two more than a loose one
            tol = float(np.sqrt(np.finfo(np.dtype(q0.dtype)).eps)) * 1e-3
            root_finder = optx.Newton(rtol=tol, atol=tol)
        event = diffrax.Event(conditions, root_finder=root_finder, **direction)
    maps = form.solve_maps()
    if dense and isinstance(adjoint, diffrax.BacksolveAdjoint):
        raise ValueError(
            "adjoint=diffrax.BacksolveAdjoint() cannot differentiate dense output (saveat=SaveAt(dense=True)): "
            "diffrax's backsolve adjoint saves at given times only; use the default adjoint or "
            "diffrax.RecursiveCheckpointAdjoint(), or save at report times"
        )
    if maps is not None and isinstance(adjoint, diffrax.BacksolveAdjoint):
        raise ValueError(
            f"adjoint=diffrax.BacksolveAdjoint() cannot differentiate through the maps method={form.name!r} applies "
            "around every step (Appell's choice of independent velocities, Lagrange's projection): use the "
            "default adjoint or diffrax.RecursiveCheckpointAdjoint(), or method='lagrange' without projection"
        )
    if isinstance(adjoint, diffrax.BacksolveAdjoint) and isinstance(form, Lagrange) and form.baumgarte is not None:
        # the backsolve adjoint rebuilds the state by integrating backward in time, where Baumgarte's
        # damping of the constraint drift (rate α) becomes growth by e^(α Δt) between saved states:
        # at α = 20/s over 2 s a gradient came out 4e9 instead of -82 (5 /s: 4e-6 off), with success
        raise ValueError(
            "adjoint=diffrax.BacksolveAdjoint() cannot differentiate stabilization='baumgarte' "
            "(Lagrange(baumgarte=α)): "
            "it rebuilds the state by integrating backward in time, where the stabilisation's damping of the "
            "constraint drift becomes growth by e^(α·Δt) between saved states, and the gradient loses every digit. "
            "Use the default adjoint or diffrax.RecursiveCheckpointAdjoint(), or stabilization=None"
        )
    kw = dict(t0=t0r, t1=t_end, max_steps=max_steps, dt0=dt0, error_mask=form.error_mask())
    event_mask = interpolation = None
    if isinstance(adjoint, ForwardSensitivity):
        if dense or event is not None or progress_meter is not None:
            raise ValueError(
                "adjoint=ForwardSensitivity() supports saving at report times only; dense output, events and "
                "progress meters need a diffrax adjoint, e.g. diffrax.RecursiveCheckpointAdjoint()"
            )
        out_ts, ys, result, stats = adjoint.solve(field, solver, maps, y0, args, saveat, controller, **kw)  # pyright: ignore[reportArgumentType]
    else:
        adaptive = not isinstance(controller, diffrax.ConstantStepSize)
        if event is not None and not boolean and coarse_interpolant(solver) and adaptive:
            # the event is located on the solver's interpolant and the state at it is read from it: for
            # Kvaerno4/5 a third-order Hermite between long implicit steps (qd at the event 50 rtol off
            # at rtol 1e-8, its derivative beyond the tolerance) while the steps themselves are accurate
            raise ValueError(
                f"event: with solver={type(solver).__name__}() and an adaptive step size the event's time and the "
                "state there are read from diffrax's third-order Hermite interpolant between the method's long "
                "implicit steps, far less accurate than the requested tolerance. Use diffrax.Kvaerno3() (an "
                "interpolant of its own order) or an explicit solver, or a constant step size (dt0=..., "
                "stepsize_controller=diffrax.ConstantStepSize())"
            )
        sol = diffrax_solve(
            field,
            solver,
            maps,
            y0,
            args,
            saveat,
            controller,
            adjoint=adjoint,
            event=event,
            progress_meter=progress_meter,
            **kw,
        )
        sol = forward_mode_outputs(sol, adjoint)
        out_ts, ys, result, stats = sol.ts, sol.ys, sol.result, sol.stats
        event_mask, interpolation = sol.event_mask, sol.interpolation
        if boolean:
            # no root to locate: the solve stops at the end of the step in which the condition
            # became True, a time whose derivative would come out 0 — refused, not returned
            out_ts, ys = _refuse_derivatives((out_ts, ys))
    if out_ts is None or ys is None:
        raise ValueError("saveat must save at some times (ts=..., t1=True or steps=True) for simulate to report them")
    if diagnose:
        t_end, y_end = out_ts[1][-1], jax.tree_util.tree_map(lambda x: x[-1], ys[1])
        out_ts, ys = out_ts[0], ys[0]
    if own_saveat:  # the reports' times, not t0
        out_ts = jnp.where(ok, out_ts, tsr)
    # rows the solve did not reach (diffrax fills them with inf: SaveAt(steps=True) beyond the last
    # step, reports after a terminating event) are evaluated at the initial state and then set to inf
    # (NaN for recorded quantities): evaluated at inf, their zero cotangents would meet infinite
    # derivatives and make every gradient NaN
    saved = jnp.isfinite(out_ts)
    ys_s = jax.tree_util.tree_map(lambda x, x0: jnp.where(bcast(saved, x), x, x0), ys, y0)
    ts_s = jnp.where(saved, out_ts, t0r)
    q, qd = jax.vmap(lambda y, t: form.unpack(y, t, run))(ys_s, ts_s)
    out = {}
    if "multipliers" in record:
        out["multipliers"] = jax.vmap(lambda a, b, t: form.accelerations(a, b, t, run, multipliers=True)[1])(
            q, qd, ts_s
        )
    if full is not None and expand is not None:  # all s coordinates out; energy and residual of the full mechanism
        q, qd = jax.vmap(lambda a, b, t: expand(a, b, t, run)[:2])(q, qd, ts_s)
        mech, s = full, q.shape[-1]
    if "energy" in record:
        out["energy"] = jax.vmap(lambda a, b, t: mech.energy(a, b, t, params))(q, qd, ts_s)
    if "residual" in record:
        out["residual"] = jax.vmap(lambda a, b, t: mech.constraint(a, b, t, params))(q, qd, ts_s)
    u = None
    if mech.has_speeds:  # the solve's velocities are the speeds; qd is dq/dt
        u, qd = qd, jax.vmap(lambda a, b, t: mech.rate(a, b, t, params))(q, qd, ts_s)
        u = jnp.where(bcast(saved, u), u, jnp.inf)
    q, qd = (jnp.where(bcast(saved, x), x, jnp.inf) for x in (q, qd))
    out = {k: jnp.where(bcast(saved, v), v, jnp.nan) for k, v in out.items()}
    stats = dict(stats)
    stages = _stages_per_step(solver)
    if stages is not None and "rhs_evaluations" not in stats:
        stats["rhs_evaluations"] = stats["num_steps"] * stages
    # the solve's own outcome; a terminating event is a success (event_mask says which)
    result = STATUS.promote(result)
    result = STATUS.where(result == STATUS.event_occurred, STATUS.successful, result)  # pyright: ignore[reportArgumentType]
    if isinstance(form, Appell):
        result = STATUS.where(result == STATUS.singular, STATUS.singular_split, result)
        if form.bound_mech.nonlinear_constraints:  # (`appell.LEFT_ROOT`, from its step maps)
            result = STATUS.where(result == STATUS.breakdown, STATUS.nonlinear_root_left, result)
    if diagnose:
        # the state to diagnose: where the solve stopped, or the first report whose motion is not
        # finite (a dependent velocity through a singular block is infinite at that report only)
        rows = jnp.isfinite(out_ts) & ~(
            jnp.all(jnp.isfinite(q.reshape(q.shape[0], -1)), axis=1) & jnp.all(jnp.isfinite(qd), axis=1)
        )
        first = jnp.argmax(rows)
        y_diag = jax.tree_util.tree_map(lambda x, e: jnp.where(rows.any(), x[first], e), ys, y_end)
        t_diag = jnp.where(rows.any(), out_ts[first], t_end)
        result = STATUS.where((result == STATUS.successful) & rows.any(), STATUS.non_finite_output, result)
        form_, y_, t_, params_ = no_grad((form, y_diag, t_diag, run))
        user: Optional[Callable] = None
        if expand is not None and full is not None:  # the user's functions, in all coordinates
            full_, expand_ = full, expand

            def user_(q_, qd_, t__):
                return (full_, *expand_(q_, qd_, t__, params_))

            user = user_

        steps_ran_out = (result == STATUS.max_steps_reached) | (result == STATUS.max_steps_rejected)
        result = diagnose_stall(
            form_, y_, t_, params_, result, start_inertias=inertias, span=tsr[-1] - t0r, t1=tsr[-1], user=user
        )
        stats["stopped_at"] = t_diag
        # steps that ran out for want of another cause: a step-size bound that forced most of them,
        # or (an implicit solver) a root finder that fails on a step of the length the solve took
        still = steps_ran_out & ((result == STATUS.max_steps_reached) | (result == STATUS.max_steps_rejected))
        num_steps = stats["num_steps"]
        t_stop = jax.lax.stop_gradient(t_end)
        bound = step_bound_count(controller, t0r, t_stop) >= 0.5 * num_steps
        result = STATUS.where(still & bound, STATUS.max_steps_step_bound, result)
        if isinstance(solver, diffrax.AbstractImplicitSolver) and hasattr(solver, "root_finder"):
            # trial steps from the mean accepted step up to 256 times it (the step-size control lets a
            # step grow until the root finder fails on it)
            mean = (t_stop - t0r) / jnp.maximum(stats["num_accepted_steps"], 1)
            hs = jnp.minimum(mean * 4.0 ** jnp.arange(5, dtype=t0r.dtype), tsr[-1] - t_stop)
            probe = still & ~bound & (mean > 0)
            fails = jax.lax.cond(
                probe,
                lambda: root_finder_fails(solver, controller, field, *no_grad((y_end, t_stop, args, hs))),
                lambda: jnp.asarray(False),
            )
            result = STATUS.where(probe & fails, STATUS.root_finder_failed, result)
    if not (isinstance(adjoint, ForwardSensitivity) and adjoint.error_control) and _explicit(solver):
        # derivatives through the steps of an explicit method held back by stability are wrong:
        # say so (forward sensitivities in the error control are right, and need no check). The
        # values are right either way, so the check is made by the derivative's own rule: a solve
        # that is not differentiated neither compiles nor runs it (NaN: not measured)
        ratio = _stiffness(
            ys, out_ts, **no_grad(dict(form=form, params=run, steps=stats["num_accepted_steps"], t0=t0r))
        )
        stats["stiffness"] = ratio
        result = STATUS.where((result == STATUS.successful) & (ratio > STIFF_ABOVE), STATUS.stiff, result)
    status = STATUS.where(checked, result, check_status)
    status = STATUS.where(increasing, status, STATUS.bad_report_times)
    status = STATUS.where(finite, status, STATUS.non_finite_input)
    reached = jnp.isfinite(out_ts)
    bad_output = (status == STATUS.successful) & ~all_finite(
        jax.tree_util.tree_map(lambda x: jnp.where(bcast(reached, x), x, 0.0), (q, qd, out))
    )
    status = STATUS.where(bad_output, STATUS.non_finite_output, status)
    failed = status != STATUS.successful
    nan_all = ~ok
    link = nan_link(failed, input_sum((params, inputs, form)))

    def finish(x):
        return jnp.where(nan_all, jnp.nan, x) + link.astype(x.dtype)

    q, qd = finish(q), finish(qd)
    u = None if u is None else finish(u)
    out = {k: finish(v) for k, v in out.items()}
    if graph_throw:  # on every output, so that whatever the caller keeps carries the check
        q, qd = raise_in_graph(q, status), raise_in_graph(qd, status)
        u = None if u is None else raise_in_graph(u, status)
        out = {k: raise_in_graph(v, status) for k, v in out.items()}
    return Solution(
        ts=out_ts,
        q=q,
        qd=qd,
        speeds=u if mech.has_speeds else None,
        multipliers=out.get("multipliers"),
        energy=out.get("energy"),
        residual=out.get("residual"),
        stats=stats,
        status=status,
        names=mech.coordinate_names(q.shape[-1]),
        dense=DenseMotion(interpolation, form, run, expand) if dense and interpolation is not None else None,
        event_mask=event_mask,
    )


_run = lean_jit(_run_traced, compiler_options=SOLVE)
"""`_run_traced` as its own compiled program (calls from outside any jit)."""


def _explicit(solver) -> bool:
    inner = getattr(solver, "solver", solver)
    return not isinstance(inner, diffrax.AbstractImplicitSolver)


@eqx.filter_custom_jvp
def _stiffness(ys, ts, *, form, params, steps, t0):
    """Mean accepted step (s) × median spectral radius of ∂f/∂y (1/s) over up to 8 saved states,
    or NaN (not measured) where no derivative of the solve is taken.

    A diagnostic that decides the `stiff` status (reported as `stats["stiffness"]`): derivatives
    through the steps of an explicit method held back by stability are wrong, the values are not.
    So it is measured only by the derivative rule below, which JAX applies under `grad`, `jacfwd`,
    `jvp` and `linearize` wherever the saved states `ys` carry a tangent (a `jit` traced before
    the derivative included), and which returns the measured ratio as its value. It has no
    derivative itself."""
    del form, params, steps, t0
    return jnp.full((), jnp.nan, ts.dtype)


@_stiffness.def_jvp
def _stiffness_jvp(primals, tangents, *, form, params, steps, t0):
    del tangents
    ys, ts = no_grad(primals)
    return _measure_stiffness(form, ys, ts, params, steps, t0), None


def _measure_stiffness(form, ys, ts, params, steps, t0, samples: int = 8):
    """`_stiffness` measured: step × spectral radius (dimensionless)."""
    n = ts.shape[0]
    idx = jnp.unique(jnp.linspace(0, n - 1, min(samples, n)).astype(jnp.int32), size=min(samples, n))
    sub = jax.tree_util.tree_map(lambda x: x[idx], ys)
    tsub = ts[idx]
    ok = jnp.isfinite(tsub)
    rho = jax.vmap(lambda y, t: spectral_radius(lambda t_, y_: _vector_field(t_, y_, form, params), y, t))(
        jax.tree_util.tree_map(lambda x: jnp.where(bcast(ok, x), x, 0.0), sub), jnp.where(ok, tsub, t0)
    )
    rho = jnp.where(ok & jnp.isfinite(rho), rho, jnp.nan)
    t_last = jnp.max(jnp.where(jnp.isfinite(ts), ts, t0))
    h = (t_last - t0) / jnp.maximum(steps, 1)
    return jnp.nan_to_num(h * jnp.nanmedian(rho))
