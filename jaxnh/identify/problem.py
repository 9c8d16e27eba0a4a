"""The least-squares problem of identification, as pure JAX (jit, vmap).

Unknowns θ = [free parameters | initial state | segment states]:

* free parameters, as set up by `Parametrisation` (logarithms for positive ones);
* the initial positions of the observed coordinates (encoder zero offsets
  and quantisation bias are absorbed here) and the independent velocities
  at the first sample (the dependent ones follow from the constraints);
* with multiple shooting, the full state (q, independent v) at the start of
  every further segment.

Residuals are `(q_sim − y) / sigma` for every observed channel and sample,
plus, with multiple shooting, the continuity defects between segments.
Their Jacobian comes from forward sensitivities integrated with the state
(`jaxnh._sensitivity.ForwardSensitivity`: one solve of the state and one
sensitivity column per unknown), wrapped in a `jax.custom_jvp` so that any
consumer (optimistix's Levenberg–Marquardt, `jax.grad` for optax) gets it
from one `jax.jacfwd` pass: with tens of unknowns and thousands of residuals
this costs about 1.3–2 plain solves (benchmarks/FIT_COST.md), far less than
reverse mode (one adjoint pass per residual), `jax.jacfwd` through
`diffrax.ForwardMode` (≈ 6× slower here) or optimistix's default
re-linearisation.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._mechanism import Mechanism
from .._sensitivity import ForwardSensitivity
from .._simulate import simulate
from ..equations.split import VelocitySplit
from .parameters import Parametrisation


__all__ = [
    "Observations",
    "Problem",
    "LevenbergMarquardt",
    "solve_least_squares",
    "column_scale",
    "value_and_jacobian",
    "statistics",
]

LM_TAU = 1e-3  # initial Levenberg–Marquardt damping relative to diag(JᵀJ)
TRUST_HIGH_CUTOFF = 0.75  # actual/predicted decrease above which the trust region grows
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
        q0_fixed: initial coordinates (s,) used for the unobserved ones.
        observed: indices of the observed coordinates (static).
        independent: indices of the independent velocities (static).
        starts: sample index where each shooting segment starts (static;
            `(0,)` for single shooting).
        length: samples per segment (static).
        method, solver, max_steps: passed to `simulate`.
        tol: (rtol, atol) of the step control, as data: a fit that tightens
            its tolerance (`fit(rtol="auto")`) reuses its compiled programs.
            `rtol`, `atol` read them as floats; `with_tolerances` replaces them.
        differentiation: "forward" (Jacobian by `jax.jacfwd` with
            `jaxnh._sensitivity.ForwardSensitivity`) or "reverse"
            (`RecursiveCheckpointAdjoint`; for gradients of a scalar loss
            with many unknowns).
    """

    mech: Mechanism
    par: Parametrisation
    q0_fixed: jax.Array
    observed: tuple = eqx.field(static=True)
    independent: tuple = eqx.field(static=True)
    starts: tuple = eqx.field(static=True)
    length: int = eqx.field(static=True)
    method: str = eqx.field(static=True)
    solver: object = eqx.field(static=True)
    tol: jax.Array
    max_steps: int = eqx.field(static=True)
    differentiation: str = eqx.field(static=True)
    defect_weight: float = eqx.field(static=True)

    @property
    def rtol(self) -> float:
        """Relative tolerance of the ODE solves (concrete problems only)."""
        return float(self.tol[0])

    @property
    def atol(self) -> float:
        """Absolute tolerance of the ODE solves, in the units of the state (concrete problems only)."""
        return float(self.tol[1])

    def with_tolerances(self, rtol, atol) -> "Problem":
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
        """Number s of coordinates of the mechanism."""
        return int(self.q0_fixed.shape[0])

    @property
    def n_initial(self) -> int:
        """Entries of θ for the initial state: observed positions, independent velocities."""
        return len(self.observed) + len(self.independent)

    @property
    def n_segment_state(self) -> int:
        """Entries of θ per further shooting segment: all positions, independent velocities."""
        return self.n_coords + len(self.independent)

    @property
    def size(self) -> int:
        """Length of θ."""
        return self.n_params + self.n_initial + (len(self.starts) - 1) * self.n_segment_state

    def labels(self, names) -> tuple:
        """Labels of θ's entries, given the coordinate names."""
        lab = list(self.par.labels)
        lab += [f"{names[i]}(t0)" for i in self.observed]
        lab += [f"{names[i]}'(t0)" for i in self.independent]
        for k in range(1, len(self.starts)):
            lab += [f"{n}(seg{k})" for n in names] + [f"{names[i]}'(seg{k})" for i in self.independent]
        return tuple(lab)

    def split(self) -> VelocitySplit:
        """The map from independent to all velocities (paper eq. 17)."""
        s = self.n_coords
        m = s - len(self.independent)
        return VelocitySplit(self.mech, s, m)

    def initial_state(self, theta, t0, params):
        """(q0, qd0) at the first sample from θ (dependent velocities from the constraints)."""
        P, k = self.n_params, len(self.observed)
        q0 = self.q0_fixed
        if k:
            q0 = q0.at[jnp.asarray(self.observed)].set(theta[P : P + k])
        v0 = theta[P + k : P + self.n_initial]
        return q0, self.split().velocities(q0, v0, t0, params, self.independent)

    def segment_states(self, theta, t_starts, params):
        """(q, qd) at the start of segments 1.. (each (S−1, s))."""
        base = self.n_params + self.n_initial
        X = theta[base:].reshape(len(self.starts) - 1, self.n_segment_state)
        q, v = X[:, : self.n_coords], X[:, self.n_coords :]
        qd = jax.vmap(lambda q_, v_, t_: self.split().velocities(q_, v_, t_, params, self.independent))(q, v, t_starts)
        return q, qd

    # --- simulation and residuals ----------------------------------------------

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
            independent=self.independent,
            max_steps=self.max_steps,
            adjoint=adjoint,
            throw=False,
        )
        return sol.q, sol.qd

    def trajectory(self, theta, t, adjoint=None):
        """Simulated coordinates (n, s) at the sample times t from θ (single shooting)."""
        params = self.par.unpack(theta[: self.n_params])
        q0, qd0 = self.initial_state(theta, t[0], params)
        return self._simulate(params, q0, qd0, t, adjoint)[0]

    def raw_residuals(self, theta, data: Observations):
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
            q, _ = self._simulate(params, q0, qd0, data.t, adjoint)
            r = (q[:, obs] - data.y) / data.sigma
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
        q, qd = jax.vmap(lambda a, b, c: self._simulate(params, a, b, c, adjoint))(Q0, QD0, ts)  # (S, L, s)
        owner = np.searchsorted(np.asarray(self.starts), idx_np, side="right") - 1
        own = jnp.asarray(owner == np.arange(len(self.starts))[:, None])  # each sample counted once
        r = jnp.where(own[..., None], (q[..., obs] - data.y[idx]) / data.sigma, 0.0)
        # continuity defects at the start of segments 1..: state reached by the previous segment
        local = np.asarray(self.starts[1:]) - np.asarray(self.starts[:-1])
        prev = np.arange(len(self.starts) - 1)
        scale_q = jnp.full((self.n_coords,), jnp.mean(data.sigma)).at[obs].set(data.sigma)
        seg_T = (data.t[-1] - data.t[0]) / len(self.starts)
        ind = jnp.asarray(self.independent)
        dq = (q[prev, local] - qs) / scale_q
        dv = (qd[prev, local][:, ind] - qds[:, ind]) * seg_T / jnp.mean(scale_q)
        defects = self.defect_weight * jnp.concatenate([dq.reshape(-1), dv.reshape(-1)])
        return _finite(jnp.concatenate([r.reshape(-1), defects]))

    def residuals(self, theta, data: Observations):
        """Weighted residuals; forward-mode problems carry a one-pass Jacobian rule."""
        if self.differentiation == "forward":
            return _residuals_fwd(self, theta, data)
        return self.raw_residuals(theta, data)


def _finite(r):
    return jnp.where(jnp.isfinite(r), r, FAILED_RESIDUAL)


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


@eqx.filter_jit
def value_and_jacobian(problem: Problem, theta, data: Observations):
    """Residuals r (N,) and their Jacobian J (N, size) at θ, by forward mode."""
    return _jacfwd(problem, theta, data)


def column_scale(J):
    """Scaling of the unknowns for Levenberg–Marquardt: √τ · (column norms of J)."""
    c = jnp.linalg.norm(J, axis=0)
    return jnp.sqrt(LM_TAU) * jnp.where(c > 0, c, 1.0)


class _Progress(eqx.Module):
    """Prints one line per Levenberg–Marquardt iteration (via a host callback).

    The solver works in scaled coordinates z = (θ − θ0) · scale; the line
    shows the first few free parameters in natural units.
    """

    labels: tuple = eqx.field(static=True)
    log: tuple = eqx.field(static=True)
    n_residuals: int = eqx.field(static=True)
    theta0: Optional[jax.Array] = None
    scale: Optional[jax.Array] = None

    def __call__(self, **kw):
        shown = len(self.labels)
        theta = self.theta0 + kw["y"][1] / self.scale
        jax.debug.callback(
            _print_progress,
            kw["num_steps"][1],
            kw["loss_this_step"][1],
            kw["loss_last_accepted_step"][1],
            kw["step_size"][1],
            theta[:shown],
            self.labels,
            self.log,
            self.n_residuals,
        )


def _print_progress(k, loss, best, step, y, labels, log, n):
    vals = "  ".join(f"{lab}={(np.exp(v) if lg else v):.6g}" for lab, v, lg in zip(labels, np.asarray(y), log))
    rms = np.sqrt(2 * float(loss) / n)
    best = f"{float(best):12.6e}" if int(k) > 0 else f"{'-':>12}"
    print(
        f"  iter {int(k):3d}  loss {float(loss):12.6e}  rms {rms:9.4g}  "
        f"best {best}  trust radius {float(step):8.2e}  {vals}",
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


class LevenbergMarquardt(optx.LevenbergMarquardt):
    """optimistix's Levenberg–Marquardt, working in scaled coordinates
    z = (θ − θ0) · scale, that also stops when the remaining Gauss–Newton
    step is negligible.

    Near the optimum the loss changes by less than its rounding, so
    trust-region steps are rejected at random and the Cauchy test (small step
    *and* small change) can take many iterations to pass, shrinking the trust
    region to nothing. Two scale-free tests end that: with `P r` the part of
    the residuals the Jacobian can explain and `s² = |r|² / (N − p)`, the full
    Gauss–Newton step has length `|P r| / s` in standard errors (stop below
    `gn_tol`); and for data fitted to rounding level (noise-free records, where
    s is itself rounding) the step changes no unknown by more than
    `step_rtol · (1 + |θ|)`.
    """

    gn_tol: float
    step_rtol: float
    theta0: jax.Array
    scale: jax.Array

    def __init__(self, rtol, atol, theta0, scale, gn_tol=GN_STOP_TOL, step_rtol=1e-10, verbose=False):
        super().__init__(rtol, atol, verbose=verbose)
        self.gn_tol, self.step_rtol = gn_tol, step_rtol
        self.theta0, self.scale = theta0, scale
        # widen the trust region once the model predicts the decrease fairly well
        # (optimistix's default waits for 99 % agreement, which on this problem
        # leaves it creeping along at constant damping for many iterations)
        self.search = optx.ClassicalTrustRegion(high_cutoff=TRUST_HIGH_CUTOFF)

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        r = state.f_info.residual
        J = state.f_info.jac.as_matrix()
        U, sv, Vt = jnp.linalg.svd(J, full_matrices=False)
        keep = sv > 1e-12 * sv[0]
        Pr = jnp.where(keep, U.T @ r, 0.0)
        s = jnp.sqrt(jnp.dot(r, r) / max(J.shape[0] - J.shape[1], 1))
        small_in_std = jnp.linalg.norm(Pr) <= self.gn_tol * s
        dtheta = (Vt.T @ (Pr / jnp.where(keep, sv, 1.0))) / self.scale
        theta = self.theta0 + y / self.scale
        small_change = jnp.max(jnp.abs(dtheta) / (1 + jnp.abs(theta))) <= self.step_rtol
        started = (~state.first_step) & (state.num_accepted_steps > 0)
        return done | (started & (small_in_std | small_change)), result


@eqx.filter_jit
def solve_least_squares(
    problem: Problem,
    theta0,
    data: Observations,
    tol: float = 1e-8,
    max_steps: int = 100,
    progress: Optional[_Progress] = None,
    gn_tol: float = GN_STOP_TOL,
    scale=None,
):
    """Levenberg–Marquardt (optimistix) from θ0; pure JAX, so it vmaps over data.

    Stops on optimistix's Cauchy test with rtol = atol = `tol`, or when the
    remaining Gauss–Newton step is below `gn_tol` standard errors or changes
    no unknown by more than 1e-10 of its size.

    `scale` (size,): the scaling of the unknowns, `column_scale(J)` of the
    Jacobian at θ0; computed here when not given (passing it, from a separately
    compiled `value_and_jacobian`, keeps this function's compilation smaller).

    Returns a dict: `theta`, `result` (optimistix RESULTS as int; 0 = stopped
    on a tolerance), `steps` (LM iterations), `r` and `J` at the solution.
    """
    # Solve in z = (θ − θ0) · scale with scale = √τ · (column norms of J at θ0):
    # then optimistix's damping λ·I, starting at λ = 1, acts like Marquardt's
    # τ · diag(JᵀJ) (Nielsen's τ = 1e-3), whatever the units of the unknowns.
    if scale is None:
        _, J0 = _jacfwd(problem, theta0, data)
        scale = column_scale(J0)

    def fn(z, args):
        return problem.residuals(theta0 + z / scale, args)

    verbose = (
        False
        if progress is None
        else eqx.tree_at(lambda p: (p.theta0, p.scale), progress, (theta0, scale), is_leaf=lambda x: x is None)
    )
    solver = LevenbergMarquardt(tol, tol, theta0, scale, gn_tol=gn_tol, verbose=verbose)
    sol = optx.least_squares(fn, solver, jnp.zeros_like(theta0), args=data, max_steps=max_steps, throw=False)
    info = sol.state.f_info
    return {
        "theta": theta0 + sol.value / scale,
        "result": sol.result._value,
        "steps": sol.stats["num_steps"],
        "r": info.residual,
        "J": info.jac.as_matrix() * scale,
    }


def statistics(J, r, rank_tol: float = 1e-8, leak_tol: float = 1e-4):
    """Gauss–Newton covariance of θ from the weighted Jacobian J (N, p) and residuals r (N,).

    Columns of J are scaled to unit length before the SVD, so the singular
    values compare parameters of any units. Directions with a relative
    singular value below `rank_tol` are not determined by the data: they are
    dropped from the covariance (pseudo-inverse) and every entry of θ with a
    component above `leak_tol` along them gets an infinite standard error.
    The covariance is scaled by the residual variance
    `s² = Σ r² / (N − rank)`. Pure JAX (vmaps).

    Returns a dict: `cov` (p, p), `std` (p,), `s2`, `dof`, `sv` (relative
    singular values, descending), `Vt` (right singular vectors, rows, in
    column-scaled coordinates), `colnorm` (p,), `rank`, `gn_step` (length of
    the remaining Gauss–Newton step in standard errors), `gn_delta` (that
    step in θ, (p,)).
    """
    N, p = J.shape
    c = jnp.linalg.norm(J, axis=0)
    c_safe = jnp.where(c > 0, c, 1.0)
    U, s, Vt = jnp.linalg.svd(J / c_safe, full_matrices=False)
    rel = s / jnp.where(s[0] > 0, s[0], 1.0)
    keep = (rel > rank_tol) & (s > 0)
    rank = jnp.sum(keep)
    dof = jnp.maximum(N - rank, 1)
    s2 = jnp.dot(r, r) / dof
    inv = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0) ** 2, 0.0)
    cov = s2 * (Vt.T * inv) @ Vt / jnp.outer(c_safe, c_safe)
    leak = jnp.sum(jnp.where(keep[:, None], 0.0, Vt**2), axis=0)
    undetermined = (leak > leak_tol) | (c == 0)
    std = jnp.where(undetermined, jnp.inf, jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)))
    Pr = jnp.where(keep, U.T @ r, 0.0)
    gn_step = jnp.linalg.norm(Pr) / jnp.sqrt(jnp.maximum(s2, jnp.finfo(r.dtype).tiny))
    delta = -(Vt.T @ (Pr / jnp.where(keep, s, 1.0))) / c_safe
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
