"""What a solve checks and diagnoses about its own states, inside the compiled program.

* `state_checks`: the checks of an initial state every solve runs (the friction solve too), and
  `initial_checks`: those, the constraint rows (`jaxnh._model.checks`) and the formulation's own
  conditions, as one `STATUS`;
* `diagnose_stall`: what is wrong at the last state of a failed solve (a mass matrix gone
  singular, a dependent block gone singular);
* `spectral_radius`: the stiffness estimate that tells a derivative through the steps of an
  explicit method held back by stability.

Each gives a status instead of raising, so the outcome is the same eagerly and under `jit`,
`vmap` (per batch member) and `grad`. `simulate` includes the diagnosis and the stiffness
estimate only in scenes that need them.
"""

from __future__ import annotations

from typing import Callable, Optional

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import optimistix as optx

from jaxnh._base.linalg import pick, value_and_jacfwd
from jaxnh._base.status import STATUS
from jaxnh._equations.appell import Appell
from jaxnh._equations.split import best_block_margin, partition_quality
from jaxnh._equations.terms import mass_and_velocity_terms, speeds_span_velocities
from jaxnh._model.checks import constraint_row_checks, mass_matrix_check


__all__ = [
    "holonomic_consistent",
    "on_branch",
    "initial_checks",
    "state_checks",
    "first_failure",
    "speeds_checks",
    "diagnose_stall",
    "spectral_radius",
    "non_finite_function",
    "root_finder_fails",
    "step_bound_count",
    "STIFF_ABOVE",
    "STALLED_SPLIT_BELOW",
    "LOST_RANK_BELOW",
    "PROBE_STEPS",
]

LOST_RANK_BELOW = 1e-6
"""A stalled solve of Appell's equations whose constraint rows, at the last state reached, have
no dependent block with a smallest singular value above this (rows scaled to unit length,
columns by the inertias: `best_block_margin`) has lost the rank of its constraint set. (The
variator-like test mechanism whose two rows become parallel at t* stalled 1e-16 before t*,
a margin of 5e-17; a well-posed set starts above 1e3 eps, which the initial checks ensure.)"""

PROBE_STEPS = (0.0, 1e-12, 1e-9, 1e-6, 1e-3)
"""Steps, as fractions of the run's length, beyond the last state reached at which the user's
functions are evaluated when a solve stalls (`non_finite_function`): a solve that meets a NaN
creeps up to it with ever shorter steps, and stops a rounding error before it."""

USER_FUNCTIONS = ("forces", "potential", "kinetic", "constraints")
"""The user's functions `non_finite_function` reports, in its codes' order (1, 2, 3, 4)."""

STALLED_SPLIT_BELOW = 1e-4
"""A failed solve whose last state has a dependent block this much worse conditioned than
the best available one is reported as a singular split."""


def on_branch(mech, q, t, params):
    """Whether q's dependent coordinates are those Newton's method reaches from `mech.guess`
    (without one, from q's own dependent coordinates: a q0 on g = 0 passes, unless G_D is singular).

    A simulation that eliminates them solves them afresh at every evaluation, from the guess:
    a q0 on another solution of g = 0 (the pendulum bob above its pivot when the guess is
    below) would start a different motion. Passed: within eps^¼ (1.2e-4 in float64) of
    1 + |q_D|, far above the √eps to which g(q0) = 0 is checked and far below the distance
    between two branches.
    """
    q = jax.lax.stop_gradient(q)
    given = pick(q, mech.dependent)
    # Newton from the guess if there is one, else from q's own dependent coordinates (as simulate)
    solved = mech.coordinates(pick(q, mech.free_coordinates(q.shape[0])), t, params, mech.newton_start(given))
    reached = pick(solved, mech.dependent)
    tol = jnp.finfo(q.dtype).eps ** 0.25 * (1 + jnp.abs(given))
    return jnp.all(jnp.abs(reached - given) <= tol)


def holonomic_consistent(mech, q, t, params):
    """Whether q satisfies the holonomic constraints g(q, t) = 0 to √eps of their scale.

    The scale of row j is `|∂g_j/∂q| |q| + |∂g_j/∂t| + |g_j(0, t)|`, the size of the terms g is made
    of (a hoop of radius 1 m: g = x² + y² − 1 has the scale 2 r² + 1), so the test does not
    depend on the units of the coordinates; a q0 a rounding error off g passes, a bead 0.1 m
    off a 1 m hoop (g = 0.21 of a scale 3.4) does not.
    """
    q = jax.lax.stop_gradient(q)

    def g(x, t_):
        return mech.holonomic_residual(x, t_, params)

    value, (dq, dt) = g(q, t), jax.jacfwd(g, argnums=(0, 1))(q, jnp.asarray(t, q.dtype))
    scale = jnp.abs(dq) @ jnp.abs(q) + jnp.abs(dt) + jnp.abs(g(jnp.zeros_like(q), t))
    tol = jnp.sqrt(jnp.finfo(q.dtype).eps) * (scale + jnp.finfo(q.dtype).tiny)
    return jnp.all(jnp.isfinite(value)) & jnp.all(jnp.abs(value) <= tol)


def acceleration_energy_agrees(mech, q, qd, t, params):
    """Whether the user's acceleration energy S agrees with T at (q, qd, t) and at a second
    velocity (qd + (1 + |qd|) w, w a fixed pattern of entries in [0.5, 1]: velocity terms that
    vanish at a state at rest are checked too).

    The check at one state: Appell's theorem
    ∂S/∂qdd = M qdd + h (M the mass matrix, h the velocity terms of Lagrange's equations, both
    from T), checked through S's Hessian in qdd against M and its gradient at qdd = 0 against h.
    Both sides are exact derivatives, so they agree to rounding: the allowance is √eps of each
    side's scale (for h: |h| + |∂S/∂qdd(0)| + eps |M| (1 + |qd|²), a floor at rounding level)."""
    w = jnp.linspace(0.5, 1.0, qd.shape[0], dtype=qd.dtype) * (1 + jnp.max(jnp.abs(qd)))
    return _agrees_at(mech, q, qd, t, params) & _agrees_at(mech, q, qd + w, t, params)


def _agrees_at(mech, q, qd, t, params):
    S = mech.acceleration_energy
    assert S is not None

    def dS(a):
        return jax.grad(S, argnums=2)(q, qd, a, t, params)

    M, h = mass_and_velocity_terms(mech, q, qd, t, params)
    g0, H = value_and_jacfwd(dS, jnp.zeros_like(qd))
    eps = jnp.finfo(q.dtype).eps
    m_scale = jnp.max(jnp.abs(M))
    h_scale = jnp.max(jnp.abs(h)) + jnp.max(jnp.abs(g0)) + eps * m_scale * (1 + jnp.max(jnp.abs(qd)) ** 2)
    tol = jnp.sqrt(eps)
    mass_ok = jnp.max(jnp.abs(H - M)) <= tol * m_scale
    terms_ok = jnp.max(jnp.abs(g0 - h)) <= tol * h_scale
    return mass_ok & terms_ok & jnp.all(jnp.isfinite(H)) & jnp.all(jnp.isfinite(g0))


def speeds_checks(mech, q, qd, t, params) -> tuple:
    """The checks of an initial state that only a mechanism in speeds has, as (ok, STATUS item)
    pairs in the order they are reported (none without `kinematics`): each `quaternions` group a
    unit quaternion to √eps (the solve then keeps it at 1), and speeds that give every velocity
    (no constraint hidden in q̇ = K u, `speeds_span_velocities`), at q0 and at a second
    configuration (a commutator may vanish at one point by accident). Shared by `simulate`'s
    solve and the friction solve."""
    out = []
    if mech.quaternions:
        eps = jnp.finfo(q.dtype).eps
        unit = jnp.all(
            jnp.stack([jnp.abs(jnp.linalg.norm(q[jnp.asarray(g)]) - 1) <= jnp.sqrt(eps) for g in mech.quaternions])
        )
        out.append((unit, STATUS.quaternion_not_unit))
    if mech.kinematics is not None:
        shifted = q + 0.1 * (1 + jnp.abs(q)) * jnp.linspace(0.5, 1.0, q.shape[0], dtype=q.dtype)
        spans = speeds_span_velocities(mech, q, qd, t, params) & speeds_span_velocities(mech, shifted, qd, t, params)
        out.append((spans, STATUS.speeds_incomplete))
    return tuple(out)


def state_checks(mech, q, qd, t, params) -> tuple:
    """The checks of an initial state that do not depend on the formulation or the contacts, as
    ((ok, STATUS item) pairs in the order they are reported, inertias): a positive definite mass
    matrix, a user's S that agrees with T, the speeds' checks (`speeds_checks`) and a q0 on the
    holonomic constraints g = 0. Shared by `simulate`'s solve and the friction solve, so a check
    added here guards both; the inertias (the mass matrix's diagonal, kg·m² or kg) are the reference
    of `diagnose_stall`."""
    pd, inertias = mass_matrix_check(mech, q, qd, t, params)
    out = [(pd, STATUS.mass_matrix_not_positive_definite)]
    if mech.acceleration_energy is not None:  # a user's S must be T's: both are given, check one against the other
        out.append((acceleration_energy_agrees(mech, q, qd, t, params), STATUS.acceleration_energy_mismatch))
    out += speeds_checks(mech, q, qd, t, params)
    if mech.holonomic is not None:  # positions are checked like velocities: q0 must lie on g = 0
        out.append((holonomic_consistent(mech, q, t, params), STATUS.holonomic_violated))
    return tuple(out), inertias


def first_failure(checks) -> tuple:
    """(ok, STATUS) of (ok, STATUS item) pairs: the first pair that fails is reported."""
    ok = jnp.asarray(True)
    status = STATUS.successful
    for good, item in checks:
        # (equinox types Enumerations as enum.Enum: an item STATUS inherits from diffrax looks like diffrax's)
        status = STATUS.where(ok & ~good, item, status)  # pyright: ignore[reportArgumentType]
        ok = ok & good
    return ok, status


def initial_checks(form, q, qd, t, params):
    """(ok, STATUS, inertias) for the initial state (q, qd) at t of a bound formulation; the
    inertias (the mass matrix's diagonal, kg·m² or kg) are the reference of `diagnose_stall`."""
    mech = form.mech
    checks, inertias = state_checks(mech, q, qd, t, params)
    if form.m:
        rows = constraint_row_checks(mech, q, qd, t, params)
        form_ok, form_status = form.check_given(q, qd, t, params, rows.A, inertias)
        checks = (*checks, *rows.leading, (form_ok, form_status), *rows.trailing)
    ok, status = first_failure(checks)
    return ok, status, inertias


def diagnose_stall(
    form,
    y,
    t,
    params,
    status,
    start_inertias: Optional[jax.Array] = None,
    span=None,
    t1=None,
    user: Optional[Callable] = None,
):
    """The status of a failed solve, refined by what is wrong at the last state reached.

    A solve that stalls (step limit, step size collapse) where the equations
    themselves break down says so: a mass matrix that is no longer positive
    definite, or whose diagonal (an inertia) has fallen below √eps of its value
    at the start, `start_inertias` (from `initial_checks`: the step before the breakdown), or
    (Appell's equations with a fixed partition) a dependent block that has
    become singular; the constraint rows that have lost rank (Appell's equations: no dependent
    block can be solved any more); and a user function (forces, potential, kinetic energy,
    constraints) that returns NaN or inf at the last state or just beyond it (`span`, `t1`: the
    run's length and end, for the probes; `user(q, qd, t) -> (mech, q, qd, params)` maps the
    solve's coordinates to the user's mechanism, for a solve that eliminated coordinates).
    """
    stalled_steps = (status == STATUS.max_steps_reached) | (status == STATUS.max_steps_rejected)
    stalled = (status != STATUS.successful) & (status != STATUS.singular_split) & (status != STATUS.nonlinear_root_left)
    q, qd = form.unpack(y, t, params)
    # a configuration to judge: finite coordinates (a dependent velocity through a singular block
    # is infinite, and is replaced by 0: the blocks of linear constraints do not depend on it)
    finite = jnp.all(jnp.isfinite(q)) & jnp.isfinite(t)
    q = jnp.where(finite, q, 0.0)
    qd = jnp.where(finite & jnp.isfinite(qd), qd, 0.0)
    pd, d1 = mass_matrix_check(form.mech, q, qd, t, params)
    if start_inertias is not None:
        collapsed = jnp.any(d1 < jnp.sqrt(jnp.finfo(q.dtype).eps) * jnp.abs(start_inertias))
        pd = pd & ~collapsed
    status = STATUS.where(stalled & finite & ~pd, STATUS.mass_matrix_became_singular, status)
    if isinstance(form, Appell) and form.m and form.bound_mech.nonlinear_constraints:
        # the dependent velocities of constraints nonlinear in them could not be solved (NaN from
        # jaxnh._equations.split: Newton's method did not converge) where the solve stopped
        q_y, qd_y = form.unpack(y, t, params)
        unsolved = ~jnp.all(jnp.isfinite(qd_y)) & jnp.all(jnp.isfinite(q_y))
        status = STATUS.where(stalled & finite & unsolved, STATUS.nonlinear_constraints_unsolved, status)
        stalled = stalled & ~unsolved
    if isinstance(form, Appell) and form.m:
        ratio = partition_quality(form.bound_mech, q, qd, t, params, form.partition(y), form.s - form.m, inertias=d1)[0]
        status = STATUS.where(stalled & finite & pd & (ratio < STALLED_SPLIT_BELOW), STATUS.singular_split, status)
        if form.m >= 2:
            # every dependent block singular: the rows themselves have lost rank (a fixed partition's
            # singular block, which re-choosing would cure, is the singular split above)
            margin = best_block_margin(form.bound_mech, q, qd, t, params, form.m, inertias=d1)
            lost = (stalled | (status == STATUS.singular_split)) & finite & pd & (margin < LOST_RANK_BELOW)
            status = STATUS.where(lost, STATUS.constraints_lost_rank, status)
    if span is not None and t1 is not None:
        which = non_finite_function(form, y, t, params, span, t1, user)
        for code, name in enumerate(USER_FUNCTIONS, start=1):
            item = getattr(STATUS, f"{_ITEM_OF[name]}_became_non_finite")
            status = STATUS.where(stalled_steps & finite & (which == code), item, status)
    return status


_ITEM_OF = {"forces": "forces", "potential": "potential", "kinetic": "kinetic_energy", "constraints": "constraints"}


def non_finite_function(form, y, t, params, span, t1, user: Optional[Callable] = None):
    """Which user function is NaN or inf at the state y at t, or on its straight continuation
    (q + h qd, qd) at t + h for the steps h of `PROBE_STEPS` × `span` (none beyond t1): 0 for
    none, else the position + 1 in `USER_FUNCTIONS` of the first one found (the earliest probe
    first). The functions are checked with the derivatives the equations take of them: ∂V/∂q,
    T's mass matrix and velocity terms, c and ∂c/∂(q, qd). `user(q, qd, t)` gives (mechanism,
    q, qd, params) in the user's own coordinates (default: the formulation's mechanism)."""
    q, qd = form.unpack(y, t, params)
    dtype = q.dtype
    steps = jnp.minimum(jnp.asarray(PROBE_STEPS, dtype) * span, jnp.maximum(t1 - t, 0.0))

    def codes(h):
        qp, qdp, tp = q + h * form.rate(q, qd, t, params), qd, t + h
        if user is None:
            mech, qp_, qdp_, p = form.mech, qp, qdp, params
        else:
            mech, qp_, qdp_, p = user(qp, qdp, tp)
        state_ok = jnp.all(jnp.isfinite(qp_)) & jnp.all(jnp.isfinite(qdp_)) & jnp.isfinite(tp)
        qp_ = jnp.where(state_ok, qp_, 0.0)
        qdp_ = jnp.where(state_ok, qdp_, 0.0)
        bad = []
        if mech.forces is not None:
            bad.append(~_finite(jnp.asarray(mech.forces(qp_, qdp_, tp, p))))
        else:
            bad.append(jnp.asarray(False))
        if mech.potential is not None:
            potential = mech.potential

            def V(x):
                return potential(x, tp, p)

            bad.append(~(_finite(V(qp_)) & _finite(jax.grad(V)(qp_))))
        else:
            bad.append(jnp.asarray(False))
        M, hv = mass_and_velocity_terms(mech, qp_, qdp_, tp, p)
        bad.append(~(_finite(mech.kinetic(qp_, qdp_, tp, p)) & _finite(M) & _finite(hv)))
        if mech.constraints is not None or mech.holonomic is not None:

            def c(x, v):
                return mech.constraint(x, v, tp, p)

            dq, dv = jax.jacfwd(c, argnums=(0, 1))(qp_, qdp_)
            bad.append(~(_finite(c(qp_, qdp_)) & _finite(dq) & _finite(dv)))
        else:
            bad.append(jnp.asarray(False))
        bad = jnp.stack(bad) & state_ok
        return jnp.where(jnp.any(bad), jnp.argmax(bad) + 1, 0)

    found = jax.vmap(codes)(steps)
    first = jnp.argmax(found > 0)
    return jnp.where(jnp.any(found > 0), found[first], 0)


def _finite(x):
    return jnp.all(jnp.isfinite(x))


def root_finder_fails(solver, controller, vector_field, y, t, args, hs):
    """Whether an implicit `solver`'s own root finder is what holds its steps back at y at t: on
    one of the trial steps `hs` it fails, while a Newton root finder at the solve's tolerances
    (`optimistix.Newton(rtol, atol)`) converges on the same step and that step's error estimate
    is within the tolerances (the step-size control would accept it).

    diffrax turns a step whose root find failed into a rejected step (an infinite error
    estimate), so a solve held back by its root finder shrinks its steps until max_steps with no
    sign of the cause in its result. The steps are taken as diffrax takes them: a root finder whose
    tolerances are to be taken from the step-size controller gets the controller's."""
    inner = controller
    while isinstance(inner, diffrax.ClipStepSizeController):
        inner = inner.controller
    if not all(hasattr(inner, a) for a in ("rtol", "atol", "norm")):
        return jnp.asarray(False)
    finder = solver.root_finder
    names = [a for a in ("rtol", "atol", "norm") if _from_controller(getattr(finder, a, None))]
    if names:
        solver = eqx.tree_at(
            lambda s: tuple(getattr(s.root_finder, a) for a in names),
            solver,
            tuple(getattr(inner, a) for a in names),
        )
    rtol, atol = getattr(inner, "rtol"), getattr(inner, "atol")
    newton = eqx.tree_at(lambda s: s.root_finder, solver, optx.Newton(rtol=rtol, atol=atol))
    terms = diffrax.ODETerm(vector_field)

    def step(solver_, h):
        state = solver_.init(terms, t, t + h, y, args)
        y1, err, _, _, result = solver_.step(terms, t, t + h, y, args, state, False)
        return y1, err, result == diffrax.RESULTS.successful

    def trial(h):
        _, _, own_ok = step(solver, h)
        y1, err, newton_ok = step(newton, h)
        scale = jax.tree_util.tree_map(
            lambda a, b: inner.atol + inner.rtol * jnp.maximum(jnp.abs(a), jnp.abs(b)), y, y1
        )
        ratio = jax.tree_util.tree_map(lambda e, c: e / c, err, scale)
        accepted = inner.norm(ratio) <= 1.0
        return ~own_ok & newton_ok & accepted & (h > 0)

    return jnp.any(jax.vmap(trial)(hs))


def _from_controller(x) -> bool:
    """Whether a root finder's attribute is diffrax's placeholder 'take it from the controller'."""
    return x is not None and type(x).__name__ == "_UseStepSizeTol"


def step_bound_count(controller, t0, t):
    """How many steps between t0 and t the step-size bound forces, at least: (t − t0) / dtmax plus
    the step_ts inside (t0, t], from the controller (a PIDController, possibly wrapped in
    a ClipStepSizeController); 0 when it bounds nothing."""
    count = jnp.zeros((), jnp.asarray(t).dtype)
    inner = controller
    while isinstance(inner, diffrax.ClipStepSizeController):
        step_ts = inner.step_ts
        if step_ts is not None:
            step_ts = jnp.asarray(step_ts)
            count = count + jnp.sum((step_ts > t0) & (step_ts <= t))
        inner = inner.controller
    dtmax = getattr(inner, "dtmax", None)
    if dtmax is not None:
        dtmax = jnp.asarray(dtmax, count.dtype)
        count = count + jnp.where(dtmax > 0, (t - t0) / jnp.where(dtmax > 0, dtmax, 1.0), jnp.inf)
    return count


STIFF_ABOVE = 1.5
"""Step × spectral radius above which a solve by an explicit method counts as stiff.

An explicit Runge–Kutta method is stable for h·|λ| up to about 3.3 (Tsit5,
Dopri5) or 6 (8th-order pairs) along the negative real axis; steps chosen for
accuracy on a non-stiff problem give h·ρ well below 1 at the tolerances used
here. A solve whose typical step times the Jacobian's spectral radius is
above 1.5 has been held back by stability: its values are still accurate
(the error control sees to that) but its derivative through the steps, in
reverse mode, is not (measured: damping 300/s on the variator, −5.6e93
against −6.0e-6)."""


def spectral_radius(vector_field, y, t, iterations: int = 12):
    """An estimate of the spectral radius of ∂f/∂y (1/s) at a state y at time t, by power
    iteration (no matrix formed, runs on any device).

    `vector_field(t, y)` is the solve's own field: the products J v are forward differences
    (f(y + h v) − f(y)) / h with h = √eps (1 + max|y|), so the estimate costs field evaluations
    only, and the program holds no derivative of the field (for a car pulling 16 trailers, a
    linearised field made the first gradient 9 s longer). The difference's relative error,
    h |f''| / |J| plus eps |f| / h, is far below what the test it serves needs (a factor of
    two on `STIFF_ABOVE`)."""
    z, unravel = jax.flatten_util.ravel_pytree(y)

    def f(z_):
        return jax.flatten_util.ravel_pytree(vector_field(t, unravel(z_)))[0]

    f0 = f(z)
    h = jnp.sqrt(jnp.finfo(z.dtype).eps) * (1 + jnp.max(jnp.abs(z)))
    v = jnp.ones_like(z) / jnp.sqrt(z.size) + 0.01 * jnp.arange(z.size, dtype=z.dtype) / z.size

    # the estimate is the geometric mean of two successive growth factors |J v_k| |J v_k+1| = |J² v_k|
    # (v_k of unit length), so complex pairs (oscillations) converge in modulus too; one product
    # with J per pass keeps one copy of the field in the loop
    def body(i, carry):
        v, n_prev, _ = carry
        w = (f(z + h * v) - f0) / h
        n = jnp.linalg.norm(w)
        return w / jnp.where(n > 0, n, 1.0), n, jnp.sqrt(n * n_prev)

    zero = jnp.zeros((), z.dtype)
    _, _, rho = jax.lax.fori_loop(0, 2 * iterations, body, (v / jnp.linalg.norm(v), zero, zero))
    return rho
