"""Design an experiment before measuring: Fisher information, predicted
standard errors, identifiability, and optimal inputs.

For white measurement noise of standard deviation σ_c on channel c, the
weighted residuals of a fit are `r = (q_sim(θ) − y) / σ`, and near the truth
the least-squares estimate has covariance `(JᵀJ)⁻¹` with `J = ∂r/∂θ` — the
Fisher information `F = JᵀJ` of the experiment (Gauss–Newton; e.g. Walter &
Pronzato, *Identification of Parametric Models from Experimental Data*,
Springer 1997, ch. 6). J depends on the inputs, the duration, the sensors
and the nominal parameters, but not on the data, so it can be computed
before any data exist: simulate the nominal motion and differentiate it
(forward sensitivities, as the fit does).

Everything here reuses the fit's own set-up: `prepare` builds the same
`Problem` (unknowns θ = free parameters, logarithms for positive ones, plus
the initial positions of the observed coordinates and the independent
initial velocities, which a fit always estimates), `statistics` gives the
covariance from the same column-scaled SVD, and `analyse` the same
identifiability report. A predicted standard error is therefore what `fit`
would report on a record of this experiment (up to the residual-variance
scaling, ≈ 1 when the noise model is right).

* `experiment(...)` → `Experiment`: the pure-JAX object (jit, vmap, grad
  through forward mode) that maps a params pytree (with the inputs in it)
  to J, F and the criterion.
* `predict(...)` → `Prediction`: F, covariance, standard errors, bands of
  profiles, and the identifiability diagnosis, as NumPy.
* `optimal_design(...)` → `DesignResult`: inputs that minimise a
  D-optimal, A-optimal or named-variance criterion subject to the limits of
  a test rig (input bounds by `jaxnh.profiles.Bounded`, energy and power
  budgets, contact-force limit |λ| ≤ λmax), by gradient through
  `jaxnh.design.optimize`, from several starts.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Optional, Sequence, Union

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxnh._base.compat import status_code
from jaxnh._base.compile import solve_jit
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.profiles import trainable
from jaxnh._solve.sensitivity import ForwardSensitivity
from jaxnh._solve.simulate import simulate, STATUS
from jaxnh.identify._fit import nominal_coordinates, prepare, speed_names_of
from jaxnh.identify.data import Record
from jaxnh.identify.design import multistart
from jaxnh.identify.estimates import estimate_fields, Estimates
from jaxnh.identify.parameters import resolve
from jaxnh.identify.problem import Problem, statistics_host


__all__ = [
    "ChannelNoise",
    "encoder_noise",
    "Experiment",
    "experiment",
    "Prediction",
    "predict",
    "Limits",
    "StickLimit",
    "stick_utilisation",
    "LIMIT_KEYS",
    "DesignResult",
    "optimal_design",
    "design_loss",
    "evaluate_design",
    "input_spec",
    "CRITERIA",
]

CRITERIA = ("D", "A")
CONSTRAINT_MARGIN = 0.99  # the penalties act from 99 % of a limit, so the optimum keeps to the limit itself
PENALTY = 1e3  # weight of a squared relative violation against the criterion (a log, ~1 per factor e)


# --- the noise model -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ChannelNoise:
    """Measurement error of one channel: white Gaussian noise of standard
    deviation `std` and, optionally, quantisation to steps of `step` (an
    encoder's count, same units, rad), whose error is uniform over one step
    (variance step²/12) when the motion sweeps many counts between samples.

    `total` is the standard deviation of the reading error,
    `sqrt(std² + step²/12)`.
    """

    std: float = 0.0
    step: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.std) and np.isfinite(self.step) and self.std >= 0 and self.step >= 0):
            raise ValueError(f"ChannelNoise: std and step must be finite and ≥ 0; got std={self.std}, step={self.step}")
        if self.total <= 0:
            raise ValueError(
                "ChannelNoise: std and step are both zero; a channel without noise has infinite information"
            )

    @property
    def total(self) -> float:
        return float(math.sqrt(self.std**2 + self.step**2 / 12.0))


NoiseSpec = Union[float, ChannelNoise, dict[str, float], dict[str, ChannelNoise], dict[str, Union[float, ChannelNoise]]]
"""The `noise` of `experiment`: one standard deviation or `ChannelNoise` for every channel, or a dict by channel."""


def encoder_noise(counts_per_rev: float, jitter_std: float = 0.0) -> ChannelNoise:
    """The reading error of an incremental encoder with `counts_per_rev` counts
    per revolution (step 2π/counts rad) and Gaussian jitter `jitter_std` (rad)
    added before the count (the embedded record's model)."""
    if not counts_per_rev > 0:
        raise ValueError(f"counts_per_rev must be > 0; got {counts_per_rev!r}")
    return ChannelNoise(std=float(jitter_std), step=2 * math.pi / float(counts_per_rev))


def _sigmas(noise, observe) -> dict:
    if noise is None:
        raise ValueError(
            "noise: give the measurement noise per observed channel, e.g. "
            "{'phi1': encoder_noise(8192, 3e-4), 'phi2': 7e-4} (rad); it sets the information"
        )
    if not isinstance(noise, dict):
        noise = {c: noise for c in observe}
    missing = [c for c in observe if c not in noise]
    if missing:
        raise ValueError(f"noise: no noise given for observed channel(s) {missing}")
    out = {}
    for c in observe:
        v = noise[c]
        s = v.total if isinstance(v, ChannelNoise) else float(v)
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"noise[{c!r}]: the standard deviation must be finite and > 0; got {v!r}")
        out[c] = s
    return out


# --- the experiment as a pure-JAX object -------------------------------------------------------------


class Experiment(eqx.Module):
    """An experiment as the fit would see it, before any data: the `Problem`
    of `prepare`, the report times, the noise, and the nominal initial state.

    Everything is a pure function of a params pytree (the nominal free
    parameters and the inputs inside it), so it works under `jax.jit` and
    forward-mode differentiation with respect to the inputs (use
    `jax.jacfwd`/`jax.jvp`; reverse mode through the sensitivity solve is not
    available).

    Attributes:
        problem: the `Problem` (`jaxnh.identify.prepare`), single shooting.
        ts: report (sample) times (n,), s.
        sigma: noise standard deviation per observed channel (k,), units of
            the channel (rad, m, rad/s).
        state: the initial-state entries of θ (observed positions, rotation
            vectors of observed quaternions (zero), independent velocities or
            speeds), nominal.
        labels: label of every entry of θ.
    """

    problem: Problem
    ts: jax.Array
    sigma: jax.Array
    state: jax.Array
    labels: tuple = eqx.field(static=True)

    @property
    def n_params(self) -> int:
        """Entries of θ that are free parameters (the rest is the initial state)."""
        return self.problem.par.size

    def theta(self, params: Optional[PyTree] = None) -> jax.Array:
        """θ at `params` (default: the nominal params)."""
        par = self.problem.par
        return jnp.concatenate([par.pack(par.params if params is None else params), self.state])

    def with_params(self, params: PyTree) -> "Experiment":
        """The same experiment with other inputs (and nominal values) from `params`."""
        return eqx.tree_at(lambda e: e.problem.par.params, self, params)

    def simulate(
        self,
        params: Optional[PyTree] = None,
        theta: Optional[jax.Array] = None,
        record: str | Sequence[str] = ("multipliers",),
        adjoint: Optional[diffrax.AbstractAdjoint | ForwardSensitivity] = None,
    ) -> Any:
        """The nominal motion at `params` (θ overrides the free values): a `Solution`."""
        pr = self.problem if params is None else self.with_params(params).problem
        th = self.theta(params) if theta is None else theta
        p = pr.par.unpack(th[: self.n_params])
        q0, qd0 = pr.initial_state(th, self.ts[0], p)
        return simulate(
            pr.mech,
            p,
            q0,
            qd0,
            self.ts,
            method=pr.method,
            solver=pr.solver,
            stepsize_controller=pr.controller(),
            independent=pr.solve_independent,
            max_steps=pr.max_steps,
            adjoint=ForwardSensitivity() if adjoint is None else adjoint,
            throw=False,
            record=record,
        )

    def jacobian(self, params: Optional[PyTree] = None) -> tuple[jax.Array, Any]:
        """Whitened sensitivities J = ∂(y_obs/σ)/∂θ (n·k, size) at `params` (y: the observed channels,
        coordinates and speeds), and the nominal `Solution` (with multipliers) from the same solve."""
        obs = jnp.asarray(self.problem.observed)

        def f(th):
            sol = self.simulate(params, th)
            y = self.problem.channel_values(sol.q, sol.u)
            return (y[:, obs] / self.sigma).reshape(-1), sol

        J, sol = jax.jacfwd(f, has_aux=True)(self.theta(params))
        return J, sol

    def fisher(self, params: Optional[PyTree] = None) -> jax.Array:
        """Fisher information F = JᵀJ (size, size) of θ, for unit-variance whitened noise."""
        J, _ = self.jacobian(params)
        return J.T @ J


def _nominal_record(mech, params, ts, q0, qd0, observe, names, method, rtol, atol, max_steps) -> Record:
    """The noise-free record of the observed channels (`names`: the coordinates', then the speeds')."""
    sol = simulate(mech, params, q0, qd0, ts, method=method, rtol=rtol, atol=atol, max_steps=max_steps, throw=False)
    if not bool(sol.status == STATUS.successful):
        raise ValueError(f"the nominal experiment cannot be simulated: {sol.message}")
    y = np.concatenate([np.asarray(sol.q), np.asarray(sol.u)], axis=1)
    return Record(np.asarray(ts), {c: y[:, names.index(c)] for c in observe}, {}, "nominal (noise-free) simulation")


def experiment(
    mech: Mechanism,
    params: PyTree,
    ts: ArrayInput,
    *,
    free: Sequence[str],
    positive: Sequence[str] = (),
    observe: Optional[Sequence[str]] = None,
    noise: Optional[NoiseSpec] = None,
    q0: Optional[ArrayInput] = None,
    qd0: Optional[ArrayInput] = None,
    method: str = "lagrange",
    solver: Optional[diffrax.AbstractSolver[Any]] = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    speed_names: Optional[Sequence[str]] = None,
) -> Experiment:
    """Set up an `Experiment`: the fit's least-squares problem on the nominal
    (noise-free) motion, before any data.

    Arguments:
        mech: the `Mechanism`.
        params: nominal params pytree, with the inputs (torques as profiles of
            time, N·m) in it; the free parameters' values are the nominal ones.
        ts: sample times (n,), s: duration and sampling rate of the record.
        free, positive: as for `fit` (positive ones enter θ as logarithms, so
            their standard errors are relative ones).
        observe: measured channels (default: all coordinates), e.g.
            ("phi1", "phi2"): coordinates by `Mechanism.names`, velocities by
            `speed_names` (a gyro's angular velocity of a mechanism in
            speeds, rad/s).
        noise: per observed channel, a standard deviation (its units: rad,
            m, rad/s), a `ChannelNoise` (Gaussian plus quantisation) or
            `encoder_noise(...)`; a dict by channel or one value for all.
        q0, qd0: the nominal initial state, must satisfy the constraints:
            coordinates (n_q,) (default 0, and the identity for a quaternion
            group) and velocities — the speeds u0 (n_u,) of a mechanism with
            `kinematics`, else q̇0 (n_q,) (required).
        method, solver, rtol, atol, max_steps, speed_names: as for `fit`
            (the unknowns are those `fit` estimates, rotation vectors of
            observed quaternions included).
    """
    if not isinstance(mech, Mechanism):
        raise TypeError(f"mech must be a jaxnh.Mechanism; got {type(mech).__name__}")
    ts = np.asarray(ts, dtype=float)
    if ts.ndim != 1 or ts.size < 20 or not np.all(np.diff(ts) > 0):
        raise ValueError("ts: need a strictly increasing 1-D array of at least 20 sample times (s)")
    if qd0 is None:
        raise ValueError("qd0: give the nominal initial velocities (speeds) of the experiment")
    qd0 = np.asarray(qd0, dtype=float)
    if q0 is not None:
        s = int(np.shape(q0)[0])
    elif mech.names is not None:
        s = len(mech.names)
    elif mech.kinematics is None:
        s = int(qd0.shape[0])
    else:
        raise ValueError("q0: the mechanism in speeds has no coordinate names; pass q0 (n_q,)")
    names = mech.coordinate_names(s)
    q0 = nominal_coordinates(mech, s, q0)
    speeds = speed_names_of(mech, names, int(qd0.shape[0]), speed_names)
    channels = tuple(names) + speeds
    observe = tuple(names) if observe is None else ((observe,) if isinstance(observe, str) else tuple(observe))
    bad = [c for c in observe if c not in channels]
    if bad:
        raise ValueError(
            f"observe: {bad} are not coordinates or speeds of the mechanism; coordinates are {names}, speeds {speeds}"
        )
    sig = _sigmas(noise, observe)
    rec = _nominal_record(
        mech,
        params,
        jnp.asarray(ts),
        jnp.asarray(q0),
        jnp.asarray(qd0),
        observe,
        list(channels),
        method,
        rtol,
        atol,
        max_steps,
    )
    problem, theta0, obs, names = prepare(
        mech,
        params,
        rec,
        free=free,
        positive=positive,
        observe=observe,
        noise=sig,
        q0=q0,
        qd0=qd0,
        method=method,
        solver=solver,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        speed_names=speeds,
    )
    P = problem.par.size
    return Experiment(
        problem=problem,
        ts=jnp.asarray(ts),
        sigma=jnp.asarray(obs.sigma),
        state=jnp.asarray(theta0)[P:],
        labels=problem.labels(names),
    )


# --- predicted covariance and identifiability ----------------------------------------------------------


@dataclasses.dataclass
class Prediction(Estimates):
    """What a fit of this experiment would report, predicted before the data: `Estimates`
    at the nominal values, with predicted standard errors.

    Attributes:
        labels: label of every unknown (free parameters, then the initial state).
        values: nominal values (natural units).
        std: predicted standard errors (natural units; inf for an undetermined
            combination).
        relative_std: std / |value| (nan where the value is 0).
        covariance: predicted covariance of `values` (natural units,
            linearised for log-parametrised ones).
        fisher: Fisher information of θ (log units for positive parameters),
            (size, size), for the given noise.
        identifiability: the `Identifiability` report (undetermined
            combinations named in words, e.g. "only J1/J2 is determined").
        max_multiplier: max |λ| over the samples of the nominal motion
            (constraint forces in their units, e.g. N·m), per constraint.
        status: the nominal solve's status (0 = success).
        estimates: {name: {"value", "std"}} as for `FitResult.estimates`.
    """

    relative_std: np.ndarray
    fisher: np.ndarray
    max_multiplier: Optional[np.ndarray]
    status: int

    def summary(self) -> str:
        """A table of nominal values and predicted standard errors (95 % intervals), and the diagnosis."""
        lines = self.table_lines(heads=("nominal", "± pred. std"))
        return "\n".join(lines + self.identifiability_lines())

    def to_dict(self) -> dict:
        """JSON-ready: {label: {"value", "std", "relative_std"}} plus "identifiable" and "messages"."""

        def num(x):
            x = float(x)
            return x if np.isfinite(x) else None

        return {
            "parameters": {
                lab: {"value": num(v), "std": num(s), "relative_std": num(r)}
                for lab, v, s, r in zip(self.labels, self.values, self.std, self.relative_std)
            },
            "identifiable": self.identifiable,
            "messages": list(self.identifiability.messages),
            "max_abs_multiplier": None if self.max_multiplier is None else self.max_multiplier.tolist(),
        }


@solve_jit
def _jacobian(exp: Experiment, params):
    J, sol = exp.jacobian(params)
    return J, sol.multipliers, status_code(sol.status)


def predict(exp: Experiment, params: Optional[PyTree] = None, *, rank_tol: float = 1e-8) -> Prediction:
    """Predicted standard errors and identifiability of `exp` with the inputs
    and nominal values in `params` (default: those `exp` was made with).

    The covariance is the pseudo-inverse of the Fisher information through
    `jaxnh.identify.statistics` (the fit's column-scaled SVD, directions with
    relative singular value below `rank_tol` undetermined) with the residual
    variance set to 1 (the noise model is taken as known), and the diagnosis
    is the fit's `analyse`: with zero torques on the variator it says that
    only J1/J2 is determined.
    """
    if params is not None:
        exp = exp.with_params(params)
    J, lam, status = _jacobian(exp, None)
    J = np.asarray(J)
    N = J.shape[0]
    # statistics() scales the covariance by s² = |r|²/(N − rank); a residual of length √(N − rank) makes s² = 1
    st0 = statistics_host(J, np.zeros(N), rank_tol=rank_tol)
    dof = max(N - int(st0["rank"]), 1)
    r = np.zeros(N)
    r[0] = math.sqrt(dof)
    stats = statistics_host(J, r, rank_tol=rank_tol)
    fields = estimate_fields(exp.problem, exp.labels, exp.theta(), stats, rank_tol)
    values, std = fields["values"], fields["std"]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(values != 0, std / np.abs(values), np.nan)
    lam = None if lam is None else np.max(np.abs(np.asarray(lam)), axis=0)
    return Prediction(**fields, relative_std=rel, fisher=J.T @ J, max_multiplier=lam, status=int(status))


# --- design criterion and constraints -----------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class StickLimit:
    """A friction contact's static cone as a limit: along the motion, the force that
    constraint row `row` needs must stay within what friction can hold,

        |λ_row(t)| ≤ μs N · lever(t, params),

    i.e. its stick margin `1 − |λ_row| / (μs N lever)` must stay ≥ 0 (above, the
    contact would slip: `jaxnh.FrictionContact`).

    Attributes:
        capacity: μs N, the largest tangential force the contact holds, N.
        lever: `lever(t, params) -> scalar`, the factor that turns the tangential
            force into the row's multiplier: 1 for a row written as a slip velocity
            (m/s; its multiplier is the force, N), the contact radius (m) for a row
            written as an angular rate (rad/s; its multiplier is a torque, N·m),
            e.g. ρ(t) = r / U21(t) for the variator's eq. (4). Must be hashable
            (a module-level function or a frozen dataclass).
        row: the constraint row (index into the multipliers).
    """

    capacity: float
    lever: Any
    row: int = 0


@dataclasses.dataclass(frozen=True)
class Limits:
    """What a test rig allows; None = no limit.

    Attributes:
        multiplier: max |λ| of every constraint multiplier along the motion (its
            units; for the variator the tangential contact force times the
            roller radius, N·m: above it the friction drive slips).
        stick: a friction contact's static cone (`StickLimit`): the utilisation
            |λ|/(μs N lever) of its row must stay ≤ 1 along the motion.
        energy: max energy drawn from the drives over the experiment, J:
            `∫ Σ_i max(Q_i u_i, 0) dt` over the generalized forces Q and the velocities u (speeds, or q̇).
        power: max drawn power `Σ_i max(Q_i u_i, 0)` at any sample, W.
        std: {label: max standard error in θ units} (relative for positive
            parameters), e.g. "no worse than the present experiment".
    Input amplitude bounds are built into the inputs (`jaxnh.profiles.Bounded`).
    """

    multiplier: Optional[float] = None
    energy: Optional[float] = None
    power: Optional[float] = None
    std: Optional[dict] = None
    stick: Optional[StickLimit] = None


def stick_utilisation(stick: StickLimit, params, sol):
    """|λ_row(t)| / (μs N lever(t, params)) at the report times: ≤ 1 while the contact can hold."""
    lever = jax.vmap(lambda t: stick.lever(t, params))(sol.ts)
    return jnp.abs(sol.multipliers[:, stick.row]) / (stick.capacity * lever)


LIMIT_KEYS = ("multiplier", "stick", "energy", "power", "std")
"""The limits `evaluate_design` reports, each as the ratio of the largest value to the limit."""


def _hinge2(x):
    return jnp.sum(jnp.maximum(x - 1.0, 0.0) ** 2)


def _positive_power(exp: Experiment, params, sol):
    """Σ_i max(Q_i u_i, 0) at the report times, W: the forces Q are conjugate to the velocities u
    (the speeds of a mechanism with `kinematics`, else q̇)."""
    forces = exp.problem.mech.forces
    Q = (
        jax.vmap(lambda q, u, t: forces(q, u, t, params))(sol.q, sol.u, sol.ts)
        if forces is not None
        else jnp.zeros_like(sol.u)
    )
    return jnp.sum(jnp.maximum(Q * sol.u, 0.0), axis=1)


def _criterion_terms(
    exp: Experiment,
    params,
    kind: str,
    of_idx: tuple,
    limits: Limits,
    std_idx: tuple,
    std_max: tuple,
    margin: float = CONSTRAINT_MARGIN,
):
    """(criterion, penalties dict, covariance of θ, solution) — pure JAX."""
    J, sol = exp.jacobian(params)
    F = J.T @ J
    c = jnp.sqrt(jnp.diag(F))
    c = jnp.where(c > 0, c, 1.0)
    Fs = F / jnp.outer(c, c)
    cov = jnp.linalg.inv(Fs) / jnp.outer(c, c)  # unit noise; the scaling keeps the inverse well conditioned
    idx = jnp.asarray(of_idx)
    C = cov[idx][:, idx]
    if kind == "D":
        value = jnp.linalg.slogdet(C)[1]
    else:
        value = jnp.log(jnp.trace(C))
    pen = {}
    p = exp.problem.par.unpack(exp.theta(params)[: exp.n_params])
    if limits.multiplier is not None and sol.multipliers is not None:
        pen["multiplier"] = _hinge2(jnp.abs(sol.multipliers) / (margin * limits.multiplier))
    if limits.stick is not None and sol.multipliers is not None:
        pen["stick"] = _hinge2(stick_utilisation(limits.stick, p, sol) / margin)
    if limits.energy is not None or limits.power is not None:
        pw = _positive_power(exp, p, sol)
        if limits.energy is not None:
            e = jnp.sum(0.5 * (pw[1:] + pw[:-1]) * jnp.diff(sol.ts))
            pen["energy"] = _hinge2(e / (margin * limits.energy))
        if limits.power is not None:
            pen["power"] = _hinge2(pw / (margin * limits.power))
    if std_idx:
        s = jnp.sqrt(jnp.diag(cov)[jnp.asarray(std_idx)])
        pen["std"] = _hinge2(s / (margin * jnp.asarray(std_max)))
    failed = sol.status != STATUS.successful
    value = jnp.where(failed, jnp.inf, value)
    return value, pen, cov, sol


def _indices(labels, names, n_params) -> tuple:
    if names is None:
        return tuple(range(n_params))
    names = (names,) if isinstance(names, str) else tuple(names)
    out = []
    for n in names:
        hit = [i for i, lab in enumerate(labels) if lab == n or lab.startswith(n + "[")]
        if not hit:
            raise ValueError(f"of/limits: {n!r} is not an unknown of the experiment; unknowns are {list(labels)}")
        out += hit
    return tuple(dict.fromkeys(out))


class _Loss(eqx.Module):
    """criterion + PENALTY · Σ penalties, as a hashable callable (one compilation for every start)."""

    exp: Experiment
    kind: str = eqx.field(static=True)
    of_idx: tuple = eqx.field(static=True)
    limits: Limits = eqx.field(static=True)
    std_idx: tuple = eqx.field(static=True)
    std_max: tuple = eqx.field(static=True)
    penalty: float = eqx.field(static=True)

    def terms(self, params):
        return _criterion_terms(self.exp, params, self.kind, self.of_idx, self.limits, self.std_idx, self.std_max)

    def __call__(self, params):
        value, pen, _, _ = self.terms(params)
        return value + self.penalty * sum(pen.values(), jnp.zeros(()))


def design_loss(
    exp: Experiment, criterion: str = "D", *, of=None, limits: Optional[Limits] = None, penalty: float = PENALTY
) -> _Loss:
    """The design objective as a function of a params pytree: the criterion
    plus `penalty` times the squared relative violations of `limits`
    (counted from 99 % of each limit).

    criterion: "D" — log det of the predicted covariance of the unknowns
    named by `of` (default: all free parameters, in θ units: relative for
    positive ones; the initial state is a nuisance, marginalised); "A" — log
    of the trace of that covariance (with `of=("J1",)`: the log variance of
    J1 alone).
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}; got {criterion!r}")
    limits = Limits() if limits is None else limits
    for k in ("multiplier", "energy", "power"):
        v = getattr(limits, k)
        if v is not None and not (np.isfinite(v) and v > 0):
            raise ValueError(f"limits.{k} must be a finite number > 0; got {v!r}")
    if limits.stick is not None:
        st = limits.stick
        if not (np.isfinite(st.capacity) and st.capacity > 0) or not callable(st.lever):
            raise ValueError(
                "limits.stick: capacity (μs N, N) must be a finite number > 0 and lever a function (t, params); "
                f"got {st!r}"
            )
    of_idx = _indices(exp.labels, of, exp.n_params)
    std_idx, std_max = (), ()
    if limits.std:
        for name, m in limits.std.items():
            ii = _indices(exp.labels, name, exp.n_params)
            mm = np.broadcast_to(np.asarray(m, dtype=float), (len(ii),))
            if not np.all(np.isfinite(mm) & (mm > 0)):
                raise ValueError(f"limits.std[{name!r}] must be finite and > 0; got {m!r}")
            std_idx += ii
            std_max += tuple(float(x) for x in mm)
    return _Loss(exp, criterion, of_idx, limits, std_idx, std_max, float(penalty))


# --- optimal design -----------------------------------------------------------------------------------


@dataclasses.dataclass
class DesignResult:
    """The outcome of `optimal_design`.

    Attributes:
        params: the params pytree with the designed inputs (best feasible start).
        value: its criterion (without penalties).
        feasible: whether every limit holds at the design (checked exactly on
            the report times, without margins).
        violations: {limit: ratio of the largest value to the limit} (≤ 1 when held).
        starts: per start, a dict with "value", "feasible", "violations", "history".
        best_start: index of the kept start.
    """

    params: Any
    value: float
    feasible: bool
    violations: dict
    starts: list
    best_start: int


@solve_jit
def _evaluate(loss: _Loss, params):
    value, pen, cov, sol = loss.terms(params)
    out = {"value": value, "status": status_code(sol.status)}
    lim = loss.limits
    if lim.multiplier is not None and sol.multipliers is not None:
        out["multiplier"] = jnp.max(jnp.abs(sol.multipliers)) / lim.multiplier
    if lim.stick is not None and sol.multipliers is not None:
        p = loss.exp.problem.par.unpack(loss.exp.theta(params)[: loss.exp.n_params])
        out["stick"] = jnp.max(stick_utilisation(lim.stick, p, sol))
    if lim.energy is not None or lim.power is not None:
        p = loss.exp.problem.par.unpack(loss.exp.theta(params)[: loss.exp.n_params])
        pw = _positive_power(loss.exp, p, sol)
        if lim.energy is not None:
            out["energy"] = jnp.sum(0.5 * (pw[1:] + pw[:-1]) * jnp.diff(sol.ts)) / lim.energy
        if lim.power is not None:
            out["power"] = jnp.max(pw) / lim.power
    if loss.std_idx:
        out["std"] = jnp.max(jnp.sqrt(jnp.diag(cov)[jnp.asarray(loss.std_idx)]) / jnp.asarray(loss.std_max))
    return out


def evaluate_design(loss: _Loss, params) -> dict:
    """Criterion value and the ratio of each limited quantity to its limit (floats)."""
    out = {k: float(v) for k, v in _evaluate(loss, params).items()}
    out["status"] = int(out["status"])
    return out


def input_spec(params, inputs: Sequence[str]):
    """The `trainable` mask of `params` marking only the trainable leaves of the named inputs."""
    inputs = (inputs,) if isinstance(inputs, str) else tuple(inputs)
    spec = jax.tree_util.tree_map(lambda _: False, params)
    for name in inputs:
        sub = resolve(params, name)
        mask = trainable(sub)
        if not any(jax.tree_util.tree_leaves(mask)):
            raise ValueError(f"inputs: {name!r} has no trainable leaves to design (got {type(sub).__name__})")
        spec = eqx.tree_at(lambda s: resolve(s, name), spec, mask)
    return spec


def optimal_design(
    exp: Experiment,
    params: PyTree,
    inputs: Sequence[str],
    criterion: str = "D",
    *,
    of: Optional[Sequence[str]] = None,
    limits: Optional[Limits] = None,
    starts: int = 4,
    steps: int = 100,
    learning_rate: float = 0.1,
    spread: float = 1.0,
    seed: int = 0,
    penalty: float = PENALTY,
    progress: bool = False,
) -> DesignResult:
    """Choose the inputs of an experiment by gradient descent on a design criterion.

    Arguments:
        exp: the `Experiment` (free parameters, sensors, noise, duration).
        params: the starting params with the inputs to design as profiles
            whose trainable leaves are the design variables — bound them with
            `jaxnh.profiles.Bounded` (torque amplitude limits hold by
            construction), e.g. `Bounded(Fourier(0, cos, sin, period=T), −M, M)`.
        inputs: names of the params entries to design, e.g. ("M1",).
        criterion, of, limits, penalty: see `design_loss` and `Limits`.
        starts: number of starts: the first from `params`, the others from
            its design leaves plus Gaussian noise of standard deviation
            `spread` (seeded by `seed`). The best feasible one is kept.
        steps, learning_rate: Adam iterations and initial step size per start
            (cosine decay to 5 % of it; `jaxnh.design.optimize`, forward-mode
            gradients).

    Returns:
        A `DesignResult`.
    """
    loss = design_loss(exp, criterion, of=of, limits=limits, penalty=penalty)
    spec = input_spec(params, inputs)
    theta, rest = eqx.partition(params, spec)
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    rng = np.random.default_rng(seed)
    inits = [params]
    for _ in range(int(starts) - 1):
        new = [x + spread * rng.standard_normal(np.shape(x)) for x in leaves]
        inits.append(eqx.combine(jax.tree_util.tree_unflatten(treedef, [jnp.asarray(x) for x in new]), rest))

    def accept(p):
        ev = evaluate_design(loss, p)
        ok = ev["status"] == 0 and all(ev[k] <= 1.0 for k in LIMIT_KEYS if k in ev)
        return ok, ev

    # Adam with a cosine decay of the step to 5 % at the end: large moves first, then settling on the limits
    optimizer = optax.adam(optax.cosine_decay_schedule(learning_rate, max(int(steps), 1), alpha=0.05))
    best, runs, k_best = multistart(
        loss,
        inits,
        accept=accept,
        trainable=spec,
        steps=steps,
        optimizer=optimizer,
        gradient="forward",
        progress=progress,
    )
    run = runs[k_best]
    ev = run["evaluation"]
    viol = {k: ev[k] for k in LIMIT_KEYS if k in ev}
    starts_out = [
        {
            "value": r["evaluation"]["value"],
            "feasible": r["accepted"],
            "violations": {k: r["evaluation"][k] for k in viol},
            "history": r["history"],
        }
        for r in runs
    ]
    return DesignResult(best, ev["value"], run["accepted"], viol, starts_out, k_best)
