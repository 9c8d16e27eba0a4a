"""The least-squares problem of identification, as pure JAX (jit, vmap).

Unknowns θ = [free parameters | initial state | segment states]:

* free parameters, as set up by `Parametrisation` (logarithms for positive ones);
* the initial positions of the observed coordinates (encoder zero offsets
  and quantisation bias are absorbed here), the initial orientation of every
  unit-quaternion group (`Mechanism(quaternions=...)`) with an observed
  component, as a rotation vector δθ (3, rad, in the body axes of the nominal
  orientation e_nom: e(t0) = e_nom ⊗ exp(δθ/2), so it stays a unit
  quaternion), and the independent velocities — the speeds u of a mechanism
  with `kinematics`, q̇ otherwise — at the first sample (the dependent ones
  follow from the constraints);
* with multiple shooting, the full state (q, independent v) at the start of
  every further segment (a quaternion group there is divided by its norm for
  the solve, and its continuity defect holds the raw entries at unit norm).

Channels are the coordinates q (n_q) followed by the velocities u (n_u: the
speeds with `kinematics`, else q̇); an observed channel is either. Residuals
are `(channel_sim − y) / sigma` for every observed channel and sample,
plus, with multiple shooting, the continuity defects between segments.
A mechanism without `kinematics` is the special case u = q̇ of the same code.
Their Jacobian comes from forward sensitivities integrated with the state
(`jaxnh._solve.sensitivity.ForwardSensitivity`: one solve of the state and one
sensitivity column per unknown), in one `jax.jacfwd` pass: with tens of
unknowns and thousands of residuals this costs about 1.3–2 plain solves
(benchmarks/FIT_COST.md), far less than reverse mode (one adjoint pass per
residual) or `jax.jacfwd` through `diffrax.ForwardMode` (≈ 6× slower here).
`solve_least_squares` evaluates (r, J) explicitly once per iteration, so its
compiled loop holds one copy of that pass; `Problem.residuals` wraps it in a
`jax.custom_jvp` for consumers that differentiate the residuals themselves
(`jax.grad` for optax).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._base.compile import one_shot_jit, solve_jit
from jaxnh._base.types import ArrayInput
from jaxnh._equations import as_formulation, Lagrange
from jaxnh._equations.split import VelocitySplit
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.rigid import quat_multiply
from jaxnh._solve.sensitivity import ForwardSensitivity
from jaxnh._solve.simulate import simulate
from jaxnh.identify.parameters import Parametrisation


__all__ = [
    "Observations",
    "Problem",
    "LM_RESULTS",
    "lm_message",
    "solve_least_squares",
    "solve_least_squares_host",
    "value_and_jacobian",
    "statistics",
    "rotation_quaternion",
]

LM_TAU = 1e-3  # initial Levenberg–Marquardt damping relative to the scaled diag(JᵀJ) (Nielsen's τ)
FAILED_RESIDUAL = 1e6  # residual given to samples after a failed solve (in noise standard deviations)


class Observations(eqx.Module):
    """Measured channels as the problem sees them.

    Attributes:
        t: sample times (n,), s.
        y: measured observed coordinates (n, k), their units (rad).
        sigma: noise standard deviation per channel (k,), units of y.
    """

    t: jax.Array
    y: jax.Array
    sigma: jax.Array


class Problem(eqx.Module):
    """Residuals of a mechanism's simulated motion against observations.

    Attributes:
        mech: the `Mechanism`.
        par: the `Parametrisation` of the free parameters.
        q0_fixed: initial coordinates (n_q,) used for the ones not estimated,
            and the nominal orientation e_nom of every estimated quaternion group.
        observed: indices of the observed channels (static) in the channel
            vector `[q (n_q), u (n_u)]`: below n_q a coordinate, from n_q on a
            velocity (a speed with `kinematics`, else a q̇).
        independent: indices of the independent velocities (speeds) (static).
        starts: sample index where each shooting segment starts (static;
            `(0,)` for single shooting).
        length: samples per segment (static).
        method, solver, max_steps: passed to `simulate`.
        tol: (rtol, atol) of the step control, as data: a fit that tightens
            its tolerance (`fit(rtol="auto")`) reuses its compiled programs.
            `rtol`, `atol` read them as floats; `with_tolerances` replaces them.
        differentiation: "forward" (Jacobian by `jax.jacfwd` with
            `jaxnh._solve.sensitivity.ForwardSensitivity`) or "reverse"
            (`RecursiveCheckpointAdjoint`; for gradients of a scalar loss
            with many unknowns).
        positions: indices of the coordinates whose initial values are
            estimated (static; default None: the observed coordinates).
        rotations: the quaternion groups (4-tuples of coordinate indices)
            whose initial orientation is estimated as a rotation vector (static).
        n_speeds: number n_u of velocities (speeds) (static; default None: n_q).
    """

    mech: Mechanism
    par: Parametrisation
    q0_fixed: jax.Array
    observed: tuple = eqx.field(static=True)
    independent: tuple = eqx.field(static=True)
    starts: tuple = eqx.field(static=True)
    length: int = eqx.field(static=True)
    method: str = eqx.field(static=True)
    solver: Optional[diffrax.AbstractSolver[Any]] = eqx.field(static=True)
    tol: jax.Array
    max_steps: int = eqx.field(static=True)
    differentiation: str = eqx.field(static=True)
    defect_weight: float = eqx.field(static=True)
    positions: Optional[tuple] = eqx.field(static=True, default=None)
    rotations: tuple = eqx.field(static=True, default=())
    n_speeds: Optional[int] = eqx.field(static=True, default=None)

    @property
    def rtol(self) -> float:
        """Relative tolerance of the ODE solves (concrete problems only)."""
        return float(self.tol[0])

    @property
    def atol(self) -> float:
        """Absolute tolerance of the ODE solves, in the units of the state (concrete problems only)."""
        return float(self.tol[1])

    def with_tolerances(self, rtol: float, atol: float) -> "Problem":
        """The same problem solved at other tolerances (the same compiled programs)."""
        return dataclasses.replace(self, tol=jnp.asarray([rtol, atol], dtype=self.tol.dtype))

    def controller(self) -> diffrax.PIDController:
        """The step-size controller of the problem's solves (its tolerances traced)."""
        return diffrax.PIDController(rtol=self.tol[0], atol=self.tol[1])

    # --- layout of θ --------------------------------------------------------

    @property
    def n_params(self) -> int:
        """Number of free-parameter entries at the head of θ."""
        return self.par.size

    @property
    def n_coords(self) -> int:
        """Number n_q of coordinates of the mechanism."""
        return int(self.q0_fixed.shape[0])

    @property
    def n_velocities(self) -> int:
        """Number n_u of velocities: the speeds of a mechanism with `kinematics`, else n_q."""
        return self.n_coords if self.n_speeds is None else int(self.n_speeds)

    @property
    def estimated_positions(self) -> tuple:
        """Indices of the coordinates whose initial values are entries of θ."""
        if self.positions is None:
            return tuple(i for i in self.observed if i < self.n_coords)
        return self.positions

    @property
    def observed_coordinates(self) -> tuple:
        """The observed channels that are coordinates (indices into q)."""
        return tuple(i for i in self.observed if i < self.n_coords)

    @property
    def n_initial(self) -> int:
        """Entries of θ for the initial state: estimated positions, 3 per estimated orientation,
        independent velocities."""
        return len(self.estimated_positions) + 3 * len(self.rotations) + len(self.independent)

    @property
    def n_segment_state(self) -> int:
        """Entries of θ per further shooting segment: all positions, independent velocities."""
        return self.n_coords + len(self.independent)

    @property
    def size(self) -> int:
        """Length of θ."""
        return self.n_params + self.n_initial + (len(self.starts) - 1) * self.n_segment_state

    def channel_names(self, names: tuple[str, ...] | list[str]) -> tuple:
        """The n_q + n_u channel names from `names`: those names themselves when they are n_q + n_u
        long, or, given the n_q coordinate names of a mechanism without `kinematics`, those
        followed by the velocities' names "<coordinate>'"."""
        names = tuple(names)
        n_q, n_u = self.n_coords, self.n_velocities
        if len(names) == n_q + n_u:
            return names
        if len(names) == n_q and self.mech.kinematics is None:
            return names + tuple(f"{n}'" for n in names)
        raise ValueError(f"names: expected the {n_q} coordinate and {n_u} speed names; got {names}")

    def labels(self, names: tuple[str, ...] | list[str]) -> tuple:
        """Labels of θ's entries, given the channel names (`channel_names`): "x(t0)" for an initial
        coordinate, "rot_x[e0..e3](t0)" for a component of an initial rotation vector (rad, body axes
        of the nominal orientation), "<speed>(t0)" for an initial speed ("phi1'(t0)" for a q̇)."""
        ch = self.channel_names(names)
        n_q = self.n_coords
        coords, speeds = ch[:n_q], ch[n_q:]
        lab = list(self.par.labels)
        lab += [f"{coords[i]}(t0)" for i in self.estimated_positions]
        for g in self.rotations:
            lab += [f"rot_{c}[{coords[g[0]]}..{coords[g[3]]}](t0)" for c in "xyz"]
        lab += [f"{speeds[i]}(t0)" for i in self.independent]
        for k in range(1, len(self.starts)):
            lab += [f"{n}(seg{k})" for n in coords] + [f"{speeds[i]}(seg{k})" for i in self.independent]
        return tuple(lab)

    def split(self) -> VelocitySplit:
        """The map from independent to all velocities (paper eq. 17), in the speeds."""
        s = self.n_velocities
        m = s - len(self.independent)
        return VelocitySplit(self.mech, s, m)

    def channel_values(self, q: jax.Array, u: jax.Array) -> jax.Array:
        """The channel vector(s) `[q, u]` (..., n_q + n_u) from coordinates and velocities (speeds)."""
        return jnp.concatenate([q, u], axis=-1)

    def initial_state(self, theta: jax.Array, t0: jax.typing.ArrayLike, params: Any) -> tuple[jax.Array, jax.Array]:
        """(q0, u0) at the first sample from θ (dependent velocities from the constraints; u0 are the
        speeds of a mechanism with `kinematics`, else q̇0)."""
        P = self.n_params
        positions = self.estimated_positions
        k = len(positions)
        q0 = self.q0_fixed
        if k:
            q0 = q0.at[jnp.asarray(positions)].set(theta[P : P + k])
        j = P + k
        for g in self.rotations:
            e = quat_multiply(self.q0_fixed[jnp.asarray(g)], rotation_quaternion(theta[j : j + 3]))
            q0 = q0.at[jnp.asarray(g)].set(e.astype(q0.dtype))
            j += 3
        v0 = theta[j : P + self.n_initial]
        return q0, self.split().velocities(q0, v0, t0, params, self.independent)

    def _unit_groups(self, q: jax.Array) -> jax.Array:
        """q with each quaternion group divided by its norm."""
        for g in self.mech.quaternions:
            idx = jnp.asarray(g)
            q = q.at[idx].set(q[idx] / jnp.linalg.norm(q[idx]))
        return q

    def segment_states(self, theta: jax.Array, t_starts: jax.Array, params: Any) -> tuple[jax.Array, jax.Array]:
        """(q, u) at the start of segments 1.. (each (S−1, n_q), (S−1, n_u)), quaternion groups at unit norm."""
        base = self.n_params + self.n_initial
        X = theta[base:].reshape(len(self.starts) - 1, self.n_segment_state)
        q, v = jax.vmap(self._unit_groups)(X[:, : self.n_coords]), X[:, self.n_coords :]
        qd = jax.vmap(lambda q_, v_, t_: self.split().velocities(q_, v_, t_, params, self.independent))(q, v, t_starts)
        return q, qd

    # --- simulation and residuals ----------------------------------------------

    @property
    def solve_independent(self) -> Optional[tuple]:
        """`independent` for `simulate`: the split of the initial velocities, for the formulations
        that integrate independent velocities (Lagrange's integrates all of them: None)."""
        return None if isinstance(as_formulation(self.method), Lagrange) else self.independent

    def _simulate(self, params, q0, qd0, ts, adjoint):
        sol = simulate(
            self.mech,
            params,
            q0,
            qd0,
            ts,
            method=self.method,
            solver=self.solver,
            stepsize_controller=self.controller(),
            independent=self.solve_independent,
            max_steps=self.max_steps,
            adjoint=adjoint,
            throw=False,
        )
        return sol.q, sol.u

    def trajectory(
        self, theta: jax.Array, t: jax.Array, adjoint: Optional[diffrax.AbstractAdjoint | ForwardSensitivity] = None
    ) -> jax.Array:
        """Simulated coordinates (n, s) at the sample times t from θ (single shooting)."""
        params = self.par.unpack(theta[: self.n_params])
        q0, qd0 = self.initial_state(theta, t[0], params)
        return self._simulate(params, q0, qd0, t, adjoint)[0]

    def channels(
        self, theta: jax.Array, t: jax.Array, adjoint: Optional[diffrax.AbstractAdjoint | ForwardSensitivity] = None
    ) -> jax.Array:
        """Simulated channels `[q, u]` (n, n_q + n_u) at the sample times t from θ (single shooting)."""
        params = self.par.unpack(theta[: self.n_params])
        q0, u0 = self.initial_state(theta, t[0], params)
        return self.channel_values(*self._simulate(params, q0, u0, t, adjoint))

    def raw_residuals(self, theta: jax.Array, data: Observations) -> jax.Array:
        """Weighted residuals (vector) without the custom Jacobian rule."""
        # the Jacobian of the residuals the fit computes: the sensitivities take the primal solve's
        # steps (no sensitivity error control), so Gauss–Newton sees the derivative of its own residual
        adjoint = (
            ForwardSensitivity(error_control=False)
            if self.differentiation == "forward"
            else diffrax.RecursiveCheckpointAdjoint()
        )
        params = self.par.unpack(theta[: self.n_params])
        obs = jnp.asarray(self.observed)
        if len(self.starts) == 1:
            q0, qd0 = self.initial_state(theta, data.t[0], params)
            y = self.channel_values(*self._simulate(params, q0, qd0, data.t, adjoint))
            r = (y[:, obs] - data.y) / data.sigma
            return _finite(r.reshape(-1))
        # multiple shooting: equal-length segments, the last one flush with the end
        L = self.length
        idx_np = np.asarray(self.starts)[:, None] + np.arange(L)[None, :]  # (S, L) sample indices
        idx = jnp.asarray(idx_np)
        ts = data.t[idx]
        q0, qd0 = self.initial_state(theta, data.t[0], params)
        qs, qds = self.segment_states(theta, ts[1:, 0], params)
        Q0 = jnp.concatenate([q0[None], qs])
        QD0 = jnp.concatenate([qd0[None], qds])
        q, qd = jax.vmap(lambda a, b, c: self._simulate(params, a, b, c, adjoint))(Q0, QD0, ts)  # (S, L, n)
        owner = np.searchsorted(np.asarray(self.starts), idx_np, side="right") - 1
        own = jnp.asarray(owner == np.arange(len(self.starts))[:, None])  # each sample counted once
        y = self.channel_values(q, qd)
        r = jnp.where(own[..., None], (y[..., obs] - data.y[idx]) / data.sigma, 0.0)
        # continuity defects at the start of segments 1..: state reached by the previous segment
        local = np.asarray(self.starts[1:]) - np.asarray(self.starts[:-1])
        prev = np.arange(len(self.starts) - 1)
        coords = [j for j, i in enumerate(self.observed) if i < self.n_coords]
        scale_q = jnp.full((self.n_coords,), jnp.mean(data.sigma))
        if coords:
            scale_q = scale_q.at[jnp.asarray(self.observed_coordinates)].set(data.sigma[jnp.asarray(coords)])
        seg_T = (data.t[-1] - data.t[0]) / len(self.starts)
        ind = jnp.asarray(self.independent)
        raw = theta[self.n_params + self.n_initial :].reshape(len(self.starts) - 1, self.n_segment_state)
        dq = (q[prev, local] - raw[:, : self.n_coords]) / scale_q  # the raw entries: quaternions held at unit norm
        dv = (qd[prev, local][:, ind] - qds[:, ind]) * seg_T / jnp.mean(scale_q)
        defects = self.defect_weight * jnp.concatenate([dq.reshape(-1), dv.reshape(-1)])
        return _finite(jnp.concatenate([r.reshape(-1), defects]))

    def n_residuals(self, data: Observations) -> int:
        """Length of the residual vector for `data` (from the shapes alone): every observed
        channel at every sample of every segment, then the continuity defects between segments."""
        n_samples, k = data.y.shape
        S = len(self.starts)
        if S == 1:
            return n_samples * k
        return S * self.length * k + (S - 1) * self.n_segment_state

    def residuals(self, theta: jax.Array, data: Observations) -> jax.Array:
        """Weighted residuals; forward-mode problems carry a one-pass Jacobian rule."""
        if self.differentiation == "forward":
            return _residuals_fwd(self, theta, data)
        return self.raw_residuals(theta, data)


def _finite(r):
    return jnp.where(jnp.isfinite(r), r, FAILED_RESIDUAL)


SMALL_ROTATION2 = 1e-6
"""|δθ|² (rad²) below which `rotation_quaternion` uses its Taylor series (error below 1e-20)."""


def rotation_quaternion(rotation: jax.Array) -> jax.Array:
    """exp(δθ/2) = (cos(|δθ|/2), sin(|δθ|/2) δθ/|δθ|), the unit quaternion (4,) of a rotation by |δθ| rad
    about the axis δθ/|δθ| (δθ (3,), rad; `jaxnh.rigid.quaternion_from_axis_angle` of that axis and angle).

    Smooth at δθ = 0, where it is the identity (1, 0, 0, 0) and its derivative is ½ (0, I): the
    derivatives of every order are finite there (a Taylor series below |δθ|² = `SMALL_ROTATION2`).
    `e_nom ⊗ rotation_quaternion(δθ)` turns the orientation e_nom by δθ in its body axes.
    """
    a2 = jnp.sum(rotation * rotation)
    small = a2 < SMALL_ROTATION2
    a = jnp.sqrt(jnp.where(small, 1.0, a2))
    c = jnp.where(small, 1.0 - a2 / 8.0 + a2 * a2 / 384.0, jnp.cos(0.5 * a))
    s = jnp.where(small, 0.5 - a2 / 48.0 + a2 * a2 / 3840.0, jnp.sin(0.5 * a) / a)
    return jnp.concatenate([c[None], s * rotation])


@eqx.filter_custom_jvp
def _residuals_fwd(problem, theta, data):
    return problem.raw_residuals(theta, data)


@_residuals_fwd.def_jvp
def _residuals_fwd_jvp(primals, tangents):
    problem, theta, data = primals
    _, t_theta, _ = tangents
    r, J = _jacfwd(problem, theta, data)
    if t_theta is None:
        return r, jnp.zeros_like(r)
    return r, J @ t_theta


def _jacfwd(problem, theta, data):
    J, r = jax.jacfwd(lambda th: (problem.raw_residuals(th, data),) * 2, has_aux=True)(theta)
    return r, J


def value_and_jacobian(problem: Problem, theta: ArrayInput, data: Observations) -> tuple[jax.Array, jax.Array]:
    """Residuals r (N,) and their Jacobian J (N, size) at θ, by forward mode.

    Compiled once per problem structure, with XLA's cheapest settings when called with
    concrete values (`jaxnh._base.compile.one_shot_jit`)."""
    return _value_and_jacobian(problem, theta, data)


_value_and_jacobian = one_shot_jit(_jacfwd)


class _Progress(eqx.Module):
    """Prints one line per Levenberg–Marquardt iteration (via a host callback):
    the iteration, the loss at the point tried, the best loss so far, the
    damping and a few free parameters in natural units."""

    labels: tuple = eqx.field(static=True)
    index: tuple = eqx.field(static=True)  # entries of θ shown, with `labels`
    log: tuple = eqx.field(static=True)
    n_residuals: int = eqx.field(static=True)

    def show(self, k, loss, best, damping, theta):
        """Print the line now (host loop)."""
        _print_progress(
            k, loss, best, damping, np.asarray(theta)[list(self.index)], self.labels, self.log, self.n_residuals
        )

    def __call__(self, k, loss, best, damping, theta):
        jax.debug.callback(
            _print_progress,
            k,
            loss,
            best,
            damping,
            theta[jnp.asarray(self.index, dtype=int)],
            self.labels,
            self.log,
            self.n_residuals,
        )


def _print_progress(k, loss, best, damping, y, labels, log, n):
    vals = "  ".join(f"{lab}={(np.exp(v) if lg else v):.6g}" for lab, v, lg in zip(labels, np.asarray(y), log))
    rms = np.sqrt(2 * float(loss) / n)
    best = f"{float(best):12.6e}" if int(k) > 0 else f"{'-':>12}"
    print(
        f"  iter {int(k):3d}  loss {float(loss):12.6e}  rms {rms:9.4g}  best {best}  "
        f"damping {float(damping):8.2e}  {vals}",
        flush=True,
    )


GN_STOP_TOL = 0.05
"""Levenberg–Marquardt stops once the remaining Gauss–Newton step is below this
many standard errors: it then moves no estimate by more than 5 % of its
standard error. The ODE solver's own error sets a floor under that step (on the
embedded variator experiment at rtol 1e-8: 0.005–0.045 standard errors), and a
tolerance below the floor left the optimiser shrinking its trust region for
30–40 extra iterations with no change in the estimates beyond 0.01 standard
errors (measured over 5 noise realisations)."""

LM_ACCEPT = 1e-4
"""A trial step is taken when the actual decrease of the loss is at least this
fraction of the decrease the linear model predicted (Moré 1978)."""

LM_MAX_DAMPING = 1e16
"""Damping (relative to the scaled Gauss–Newton matrix, whose diagonal is ≤ 1)
beyond which the step is below rounding: no step lowers the loss, so the solve
stops as stalled."""

LM_RESULTS = {
    0: "stopped on its tolerances",
    1: "iteration limit reached",
    2: "stalled: no step lowers the loss (the damping grew past 1e16)",
    3: "the simulation failed at the starting point (non-finite residuals or Jacobian)",
}
"""The `result` codes of `solve_least_squares`, in words."""


class _LMState(eqx.Module):
    k: jax.Array  # residual-and-Jacobian evaluations so far
    theta: jax.Array  # accepted point
    r: jax.Array
    J: jax.Array
    loss: jax.Array
    D: jax.Array  # scaling of the unknowns: running maximum of J's column norms (Moré 1978)
    mu: jax.Array  # damping, relative to the scaled Gauss–Newton matrix
    nu: jax.Array  # growth factor of the damping after a rejected step (Nielsen 1999)
    trial: jax.Array  # the point evaluated next
    pred: jax.Array  # the decrease of the loss the linear model predicts at `trial`
    done: jax.Array
    code: jax.Array


def thin_svd(M, xp=np):
    """`U, s, Vt` of the thin SVD of M (n, p), NaN where M has a non-finite entry.

    That is what `jax.numpy` returns; NumPy's LAPACK call raises for NaN and may
    never return for inf, so NumPy input is checked first."""
    if xp is np and not np.all(np.isfinite(M)):
        n, p = M.shape
        k = min(n, p)
        return np.full((n, k), np.nan), np.full(k, np.nan), np.full((k, p), np.nan)
    return xp.linalg.svd(M, full_matrices=False)


def _lm_update(state: _LMState, r_c, J_c, limits, xp=jnp) -> _LMState:
    """One Levenberg–Marquardt iteration, given the residuals and Jacobian at `state.trial`.

    `xp` is the array module: `jax.numpy` in the compiled loop, `numpy` in the host loop
    (the same arithmetic, without compiling a program for a few small operations)."""
    tol, gn_tol, step_rtol, max_steps = limits
    loss_c = 0.5 * xp.dot(r_c, r_c)
    ok_c = xp.all(xp.isfinite(J_c)) & xp.all(r_c != FAILED_RESIDUAL) & xp.isfinite(loss_c)
    first = state.k == 0
    rho = (state.loss - loss_c) / xp.where(state.pred > 0, state.pred, xp.inf)
    take = first | (ok_c & (rho > LM_ACCEPT))
    failed_start = first & ~ok_c
    theta = xp.where(take, state.trial, state.theta)
    r = xp.where(take, r_c, state.r)
    J = xp.where(take, J_c, state.J)
    loss = xp.where(take, loss_c, state.loss)
    colnorm = xp.linalg.norm(J, axis=0)
    D = xp.where(first, xp.where(colnorm > 0, colnorm, 1.0), xp.maximum(state.D, colnorm))
    mu = xp.where(
        first,
        LM_TAU,
        xp.where(take, state.mu * xp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), state.mu * state.nu),
    )
    nu = xp.where(take, 2.0, 2.0 * state.nu)
    # the linear model at the accepted point, in scaled unknowns
    U, sv, Vt = thin_svd(J / D, xp)
    ur = U.T @ r
    keep = sv > 1e-12 * sv[0]
    n, p = J.shape
    s2 = xp.dot(r, r) / max(n - p, 1)
    pr = xp.where(keep, ur, 0.0)
    gn = -(Vt.T @ (pr / xp.where(keep, sv, 1.0))) / D
    small_in_std = xp.linalg.norm(pr) <= gn_tol * xp.sqrt(s2)
    small_change = xp.max(xp.abs(gn) / (1.0 + xp.abs(theta))) <= step_rtol
    cauchy = (
        take
        & ~first
        & (xp.abs(state.loss - loss_c) <= tol * loss_c)
        & (xp.max(xp.abs(state.trial - state.theta) / (1.0 + xp.abs(theta))) <= tol)
    )
    converged = take & ok_c & (small_in_std | small_change | cauchy)
    stalled = mu > LM_MAX_DAMPING
    k = state.k + 1
    code = xp.where(failed_start, 3, xp.where(converged, 0, xp.where(stalled, 2, xp.where(k >= max_steps, 1, 0))))
    done = failed_start | converged | stalled | (k >= max_steps)
    # the next trial: δ̃ = −V diag(s / (s² + μ)) Uᵀr, δ = δ̃ / D
    filt = sv / (sv**2 + mu)
    delta = -(Vt.T @ (filt * ur)) / D
    pred = 0.5 * xp.sum(ur**2 * (1.0 - (mu / (sv**2 + mu)) ** 2))
    new = _LMState(k, theta, r, J, loss, D, mu, nu, theta + delta, pred, done, code.astype(xp.int32))
    # under vmap the loop runs until every member is done: finished members keep their state
    return jax.tree_util.tree_map(lambda a, b: xp.where(state.done, a, b), state, new)


def _lm_start(theta0, n_residuals: int, xp=jnp) -> _LMState:
    dtype = theta0.dtype
    p, N = theta0.shape[0], n_residuals
    return _LMState(
        k=xp.asarray(0),
        theta=theta0,
        r=xp.zeros(N, dtype),
        J=xp.zeros((N, p), dtype),
        loss=xp.asarray(xp.inf, dtype),
        D=xp.ones(p, dtype),
        mu=xp.asarray(LM_TAU, dtype),
        nu=xp.asarray(2.0, dtype),
        trial=theta0,
        pred=xp.asarray(0.0, dtype),
        done=xp.asarray(False),
        code=xp.asarray(0, xp.int32),
    )


def _lm_limits(tol, gn_tol, step_rtol, max_steps, dtype, xp=jnp):
    # the tolerances and the limit as data: other values reuse the compiled programs
    return (
        xp.asarray(tol, dtype),
        xp.asarray(gn_tol, dtype),
        xp.asarray(step_rtol, dtype),
        xp.asarray(max_steps),
    )


def _lm_out(state: _LMState) -> dict:
    return {"theta": state.theta, "result": state.code, "steps": state.k, "r": state.r, "J": state.J}


def solve_least_squares(
    problem: Problem,
    theta0: ArrayInput,
    data: Observations,
    tol: float = 1e-8,
    max_steps: int = 100,
    progress: Optional[_Progress] = None,
    gn_tol: float = GN_STOP_TOL,
    step_rtol: float = 1e-10,
    *,
    host: bool = False,
) -> dict[str, Any]:
    """Levenberg–Marquardt from θ0; pure JAX, so it vmaps over data and θ0.

    Each iteration evaluates the residuals r and their Jacobian J at one trial
    point, in one forward-sensitivity solve (`value_and_jacobian`; one trace
    of it in the compiled loop). The step solves
    `min ‖r + J δ‖² + μ ‖D δ‖²` through the SVD of `J D⁻¹`, with D the running
    maximum of J's column norms (units of the unknowns do not matter) and the
    damping μ updated by the ratio ρ of actual to predicted decrease
    (Nielsen 1999: μ ← μ·max(1/3, 1 − (2ρ − 1)³) on success, μ ← μ·ν, ν ← 2ν
    on failure; μ starts at `LM_TAU`). A step is taken when ρ > `LM_ACCEPT`;
    a failed simulation at a trial point (residuals `FAILED_RESIDUAL` or a
    non-finite Jacobian) counts as no decrease.

    Stops (result 0) when the remaining Gauss–Newton step is below `gn_tol`
    standard errors (`s² = ‖r‖²/(N − p)`), or changes no unknown by more than
    `step_rtol·(1 + |θ|)` (data fitted to rounding level), or a taken step
    changed the loss by at most `tol`·loss and every unknown by at most
    `tol`·(1 + |θ|). Else result 1 (`max_steps` evaluations), 2 (stalled) or
    3 (failed at θ0); `LM_RESULTS` says them in words.

    With `host=True` (`solve_least_squares_host`, what `jaxnh.fit` uses) the
    same iteration runs from Python around a compiled `value_and_jacobian`,
    which compiles in about half the time; the default compiles the whole
    loop, for batches (`jax.vmap`). Both run `_levenberg_marquardt`.

    Returns a dict: `theta`, `result` (int, see above), `steps` (evaluations
    of r and J, the first at θ0 included), `r` and `J` at `theta`.
    """
    xp = np if host else jnp
    theta0 = xp.asarray(theta0)
    limits = _lm_limits(tol, gn_tol, step_rtol, max_steps, theta0.dtype, xp=xp)
    if not host:
        return _levenberg_marquardt_compiled(problem, theta0, data, limits, progress)

    def evaluate(theta):  # the compiled (r, J), as NumPy arrays
        r, J = value_and_jacobian(problem, jnp.asarray(theta), data)
        return np.asarray(r), np.asarray(J)

    return _levenberg_marquardt(evaluate, theta0, problem.n_residuals(data), limits, progress, np)


def solve_least_squares_host(
    problem: Problem, theta0: ArrayInput, data: Observations, **options: Any
) -> dict[str, Any]:
    """`solve_least_squares` for one record, iterated from Python (`host=True`; the same options).

    The same iteration and the same results; the loop runs on the host, so the
    only compiled program is `value_and_jacobian` (shared with every other
    caller) instead of a loop around it, which XLA took about twice as long
    to compile (benchmarks/FIT_COST.md); the iteration's own arithmetic runs
    in NumPy. Not for `jax.vmap`/`jax.jit`.
    """
    return solve_least_squares(problem, theta0, data, host=True, **options)


@solve_jit
def _levenberg_marquardt_compiled(problem: Problem, theta0, data: Observations, limits, progress):
    return _levenberg_marquardt(
        lambda theta: _jacfwd(problem, theta, data), theta0, problem.n_residuals(data), limits, progress, jnp
    )


def _levenberg_marquardt(evaluate, theta0, n_residuals: int, limits, progress, xp) -> dict:
    """The one Levenberg–Marquardt driver: evaluate (r, J) at the trial point, update, until done.

    `xp` is `jax.numpy` for the compiled loop (`jax.lax.while_loop`, traced once) or `numpy`
    for the host loop (a Python loop; `evaluate` returns NumPy arrays)."""
    show = None if progress is None else (progress.show if xp is np else progress)

    def step(state: _LMState) -> _LMState:
        r_c, J_c = evaluate(state.trial)
        if show is not None:
            show(state.k, 0.5 * xp.dot(r_c, r_c), state.loss, state.mu, state.trial)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # NumPy as jax.numpy: inf/nan, no warning
            return _lm_update(state, r_c, J_c, limits, xp=xp)

    state = _lm_start(theta0, n_residuals, xp=xp)
    if xp is np:
        while not bool(state.done):
            state = step(state)
    else:
        state = jax.lax.while_loop(lambda st: ~st.done, step, state)
    return _lm_out(state)


def lm_message(code: int, max_steps: int) -> str:
    """`solve_least_squares`'s result code in words."""
    if code == 1:
        return f"iteration limit ({max_steps}) reached"
    return LM_RESULTS.get(int(code), f"unknown result code {code}")


@jax.jit
def statistics(J: ArrayInput, r: ArrayInput, rank_tol: float = 1e-8, leak_tol: float = 1e-4) -> dict[str, Any]:
    """Gauss–Newton covariance of θ from the weighted Jacobian J (N, p) and residuals r (N,).

    Columns of J are scaled to unit length before the SVD, so the singular
    values compare parameters of any units. Directions with a relative
    singular value below `rank_tol` are not determined by the data: they are
    dropped from the covariance (pseudo-inverse) and every entry of θ with a
    component above `leak_tol` along them gets an infinite standard error.
    The covariance is scaled by the residual variance
    `s² = Σ r² / (N − rank)`. Pure JAX (vmaps); `statistics_host` is the
    same in NumPy, for one fit on the host.

    Returns a dict: `cov` (p, p), `std` (p,), `s2`, `dof`, `sv` (relative
    singular values, descending), `Vt` (right singular vectors, rows, in
    column-scaled coordinates), `colnorm` (p,), `rank`, `gn_step` (length of
    the remaining Gauss–Newton step in standard errors), `gn_delta` (that
    step in θ, (p,)).
    """
    return _statistics(J, r, rank_tol, leak_tol, jnp)


def statistics_host(J, r, rank_tol: float = 1e-8, leak_tol: float = 1e-4) -> dict:
    """`statistics` in NumPy (no program to compile; NumPy arrays in and out)."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # as jax.numpy: inf/nan, no warning
        return _statistics(np.asarray(J), np.asarray(r), rank_tol, leak_tol, np)


def _statistics(J, r, rank_tol, leak_tol, xp):
    N, p = J.shape
    c = xp.linalg.norm(J, axis=0)
    c_safe = xp.where(c > 0, c, 1.0)
    U, s, Vt = thin_svd(J / c_safe, xp)
    rel = s / xp.where(s[0] > 0, s[0], 1.0)
    keep = (rel > rank_tol) & (s > 0)
    rank = xp.sum(keep)
    dof = xp.maximum(N - rank, 1)
    s2 = xp.dot(r, r) / dof
    inv = xp.where(keep, 1.0 / xp.where(keep, s, 1.0) ** 2, 0.0)
    cov = s2 * (Vt.T * inv) @ Vt / xp.outer(c_safe, c_safe)
    leak = xp.sum(xp.where(keep[:, None], 0.0, Vt**2), axis=0)
    undetermined = (leak > leak_tol) | (c == 0)
    std = xp.where(undetermined, xp.inf, xp.sqrt(xp.maximum(xp.diag(cov), 0.0)))
    Pr = xp.where(keep, U.T @ r, 0.0)
    gn_step = xp.linalg.norm(Pr) / xp.sqrt(xp.maximum(s2, xp.finfo(r.dtype).tiny))
    delta = -(Vt.T @ (Pr / xp.where(keep, s, 1.0))) / c_safe
    return {
        "cov": cov,
        "std": std,
        "s2": s2,
        "dof": dof,
        "sv": rel,
        "Vt": Vt,
        "colnorm": c,
        "rank": rank,
        "gn_step": gn_step,
        "gn_delta": delta,
        "undetermined": undetermined,
    }
