"""`fit`: estimate parameters of a mechanism from a measured record.

Least squares of simulated against measured channels (coordinates and, for
a mechanism in speeds, speeds too), with gradients through the ODE solver,
then the Gauss–Newton covariance scaled by the residual variance, and an identifiability check that says in words which
combinations the data cannot determine.
"""

from __future__ import annotations

import dataclasses
import math
import textwrap
import time
import warnings
from typing import Any, Optional, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxnh._base.compile import one_shot_jit, solve_jit
from jaxnh._base.dataframe import fit_result_to_dict
from jaxnh._base.linalg import value_and_jacfwd
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._equations.split import choose_independent
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.profiles import Sampled
from jaxnh._solve.sensitivity import FORWARD_MAX_PARAMETERS
from jaxnh._solve.simulate import default_solver, DOP853_BELOW_RTOL
from jaxnh.identify.data import noise_level, Record
from jaxnh.identify.diagnostics import lack_of_fit, LackOfFit
from jaxnh.identify.estimates import estimate_fields, Estimates
from jaxnh.identify.parameters import Parametrisation
from jaxnh.identify.problem import (
    _Progress,
    FAILED_RESIDUAL,
    lm_message,
    Observations,
    Problem,
    solve_least_squares_host,
    statistics_host,
    thin_svd,
    value_and_jacobian,
)


__all__ = [
    "fit",
    "prepare",
    "FitResult",
    "OPTIMIZERS",
    "GN_STEP_TOL",
    "FORWARD_MAX_UNKNOWNS",
    "ode_error_in_std",
    "ODE_ERROR_STD",
]

OPTIMIZERS = ("levenberg-marquardt",)
GN_STEP_TOL = 0.1  # converged: the remaining Gauss–Newton step is below 0.1 standard errors ...
STEP_RTOL = 1e-9  # ... or below 1e-9 of every unknown (data fitted to rounding: noise-free records)
AUTO_RTOL_START = 1e-8  # rtol="auto": where the fit starts ...
AUTO_RTOL_MIN = 1e-12  # ... and the tightest it goes
ODE_ERROR_STD = 0.05  # rtol="auto": the solver's error may move no estimate by more than this many standard
# errors: the precision at which Levenberg–Marquardt stops (problem.GN_STOP_TOL); measured on the embedded record
# at rtol 1e-8: 0.03 (no tightening), on issue 18's informative record: see benchmarks/EXPERIMENT.md
AUTO_REFINEMENTS = 3  # rtol="auto": at most this many tightenings
FORWARD_MAX_UNKNOWNS = FORWARD_MAX_PARAMETERS  # the one policy of simulate and fit (jaxnh.choose_adjoint)
RATE_WINDOW = 15  # samples used to estimate a starting velocity from the data


@dataclasses.dataclass
class FitResult(Estimates):
    """The outcome of `fit`: the `Estimates` of the free parameters and the initial state, and how the fit went.

    Attributes:
        params: the fitted params pytree (same structure as the starting one).
        q0, qd0: fitted initial coordinates (n_q,) and velocities at t[0]:
            the speeds u0 (n_u,) of a mechanism with `kinematics` (what
            `jaxnh.simulate` takes as qd0), else q̇0 (n_q,).
        estimates: {name: {"value", "std"}} for every free parameter (scalars
            as floats, profiles' trainable values as arrays) and for the
            fitted initial state (entries like "phi1(t0)", "phi1'(t0)"; for
            a mechanism in speeds "<speed>(t0)", and "rot_x[e0..e3](t0)"
            etc. for the rotation vector of an estimated quaternion, rad).
            Units are those of the parameter; `std` is the standard error
            (inf when the data do not determine it).
        labels, values, std: the same, flat, one entry per unknown.
        covariance: covariance of `values` (natural units; linearised for
            log-parametrised ones), scaled by the residual variance.
        converged: the optimiser stopped on its tolerances and the remaining
            Gauss–Newton step is below `GN_STEP_TOL` standard errors (or, for
            data fitted to rounding level, below `STEP_RTOL` of every unknown).
        iterations: optimiser iterations.
        message: why it stopped, in words.
        rms_residual: root mean square of measured − fitted over all observed
            samples, units of the channels (rad).
        rms_by_channel: the same per channel.
        noise: noise standard deviation used to weight each channel (given or
            estimated from the data).
        chi2_dof: weighted residual variance s² (≈ 1 when the noise levels
            are right and the model fits).
        lack_of_fit: the `LackOfFit` report: whether s² is significantly
            above 1 and how large the model error is relative to the noise.
        identifiability: the `Identifiability` report.
        t, observe, measured, fitted, residuals: sample times (n,), observed
            channel names, and (n, k) arrays of data, fit and data − fit.
        gn_step: remaining Gauss–Newton step, in standard errors.
        optimizer, differentiation, shooting, elapsed: how it was done, and the
            wall time in seconds.
    """

    params: Any
    q0: np.ndarray
    qd0: np.ndarray
    converged: bool
    iterations: int
    message: str
    rms_residual: float
    rms_by_channel: dict
    noise: dict
    chi2_dof: float
    lack_of_fit: LackOfFit
    t: np.ndarray
    observe: tuple
    measured: np.ndarray
    fitted: np.ndarray
    residuals: np.ndarray
    gn_step: float
    optimizer: str
    differentiation: str
    shooting: int
    elapsed: float

    def to_dict(self, arrays: bool = False) -> dict:
        """The result as plain Python data, ready for `json.dump` (any mechanism).

        Non-finite numbers (an undetermined standard error, a failed
        simulation) become None (JSON null), and "status" then says why the
        fit is not usable. Keys: "status" ("fitted", "not_converged",
        "not_identifiable", "simulation_failed" or "non_finite"), "ok",
        "parameters" ({name: {"value", "std"}}, lists for profiles),
        "initial_state", "labels"/"values"/"std"/"covariance" (flat),
        "q0", "qd0", residual statistics, "lack_of_fit", "identifiability",
        "converged", "iterations", "message", and how it was done. With
        `arrays=True` also "t", "measured", "fitted", "residuals".
        See `jaxnh._base.dataframe.fit_result_to_dict`.
        """
        return fit_result_to_dict(self, arrays=arrays)

    def __repr__(self) -> str:
        status = "converged" if self.converged else "NOT converged"
        ident = "identifiable" if self.identifiable else "NOT identifiable"
        est = ", ".join(f"{lab}={v:.6g}" for lab, v in list(zip(self.labels, self.values))[:6])
        more = f", … ({len(self.labels)} unknowns)" if len(self.labels) > 6 else ""
        return (
            f"FitResult({status}, {ident}, {self.iterations} iterations, rms residual "
            f"{self.rms_residual:.4g}; {est}{more}; .summary() for the table, .to_dict() for all values)"
        )

    def __str__(self) -> str:
        return self.summary()

    def summary(
        self,
        truth: Optional[dict] = None,
        *,
        units: Optional[dict] = None,
        residual_unit: tuple[float, str] = (1.0, ""),
    ) -> str:
        """A table of estimates ± standard errors with 95 % intervals, then the residual
        statistics, convergence, the lack-of-fit test and the identifiability report.

        Arguments:
            truth: true values, when known, to show next to the estimates
                ({name: value}; {"<name>_values": array} for a profile).
            units: {parameter name: unit text} shown after the names, e.g. {"J1": " kg·m²"}.
            residual_unit: (factor, unit text): residuals and noise levels are
                shown multiplied by factor, followed by the unit, e.g.
                (1e3, " mrad") for channels in rad.
        """
        scale, unit = residual_unit
        lines = self.table_lines(truth, units=units)
        # one line each, so that the summary fits a page or a terminal of 100 columns
        lines.append(
            f"  rms residual {scale * self.rms_residual:.4g}{unit} ("
            + ", ".join(f"{c} {scale * v:.4g}" for c, v in self.rms_by_channel.items())
            + ")"
        )
        lines.append(
            "  noise σ "
            + ", ".join(f"{c} {scale * v:.4g}" for c, v in self.noise.items())
            + f"{unit}; s² = {self.chi2_dof:.3f}"
        )
        lines.append(_wrapped(self.lack_of_fit.message))
        lines.append(
            _wrapped(
                f"{self.optimizer}: {self.iterations} iterations, "
                f"{'converged' if self.converged else 'NOT CONVERGED'}: {self.message}; {self.elapsed:.1f} s"
            )
        )
        lines += self.identifiability_lines()
        return "\n".join(lines)


def _wrapped(text: str) -> str:
    """`text` indented by two spaces and wrapped at 100 columns (a page or a terminal shows it whole)."""
    return textwrap.fill(text, width=100, initial_indent="  ", subsequent_indent="    ", break_long_words=False)


def _as_list(x):
    return (x,) if isinstance(x, str) else tuple(x)


def _local_rates(t, y, i0, window=RATE_WINDOW):
    """Value and slope of each column of y at sample i0 from a local quadratic fit, and their
    standard errors (each (k,)), from the fit's residuals: noise and the part of the motion a
    quadratic misses alike."""
    n = t.shape[0]
    lo = max(0, min(i0 - window // 2, n - window))
    sl = slice(lo, min(n, lo + window))
    tt = t[sl] - t[i0]
    V = np.stack([np.ones_like(tt), tt, tt**2], axis=1)
    coef, *_ = np.linalg.lstsq(V, y[sl], rcond=None)
    s2 = np.sum((y[sl] - V @ coef) ** 2, axis=0) / max(V.shape[0] - 3, 1)
    C = np.linalg.pinv(V.T @ V)
    return coef[0], coef[1], np.sqrt(s2 * C[0, 0]), np.sqrt(s2 * C[1, 1])


@one_shot_jit
def _velocity_map(problem: Problem, q, t, params):
    """b, B with the observed channels' rates = B v + b for independent velocities (speeds) v: a
    coordinate channel's rate is its q̇ (`Mechanism.rate`), a velocity channel's value is itself."""

    def f(v):
        u = problem.split().velocities(q, v, t, params, problem.independent)
        return problem.channel_values(problem.mech.rate(q, u, t, params), u)[jnp.asarray(problem.observed)]

    v0 = jnp.zeros(len(problem.independent), q.dtype)
    return value_and_jacfwd(f, v0)


@one_shot_jit
def _estimate_state(problem: Problem, theta, t0):
    """The params pytree at θ and the initial state (q0, qd0) it implies (one small program)."""
    params = problem.par.unpack(theta[: problem.par.size])
    return (params, *problem.initial_state(theta, t0, params))


@solve_jit
def _trajectory(problem: Problem, theta, t):
    return problem.trajectory(theta, t)


@solve_jit
def _channels(problem: Problem, theta, t):
    return problem.channels(theta, t)


def speed_names_of(mech: Mechanism, names: Sequence[str], n_u: int, speed_names: Optional[Sequence[str]]) -> tuple:
    """The names of the n_u velocities: `speed_names` when given; else "<coordinate>'" for a
    mechanism without `kinematics` (u is q̇), and "u0", "u1", ... for one in speeds."""
    if speed_names is not None:
        out = _as_list(speed_names)
        if len(out) != n_u or not all(isinstance(c, str) for c in out):
            raise ValueError(f"speed_names: expected {n_u} names (one per speed u); got {speed_names!r}")
    elif mech.kinematics is None:
        out = tuple(f"{c}'" for c in names)
    else:
        out = tuple(f"u{j}" for j in range(n_u))
    clash = sorted(set(out) & set(names)) + sorted({c for c in out if out.count(c) > 1})
    if clash:
        raise ValueError(f"speed_names: {clash} name more than one channel (coordinates are {tuple(names)})")
    return out


def nominal_coordinates(mech: Mechanism, s: int, q0: Optional[ArrayInput]) -> np.ndarray:
    """q0 (s,) as floats, zeros when None, with each quaternion group (`Mechanism.quaternions`) at unit
    norm: divided by its norm, or the identity (1, 0, 0, 0) when q0 is None."""
    q = np.zeros(s) if q0 is None else np.array(q0, dtype=float)
    if q.shape != (s,):
        raise ValueError(f"q0 must have shape ({s},); got {q.shape}")
    for g in mech.quaternions:
        if max(g) >= s:
            raise ValueError(f"quaternions={mech.quaternions!r} name coordinate {max(g)}, but there are {s}")
        if q0 is None:
            q[list(g)] = (1.0, 0.0, 0.0, 0.0)
        norm = float(np.linalg.norm(q[list(g)]))
        if not norm > 0:
            raise ValueError(f"q0: the quaternion group {g} is zero; give a unit quaternion (w, x, y, z)")
        q[list(g)] /= norm
    return q


def _independent_from_rates(problem: Problem, q, rates, t, params, weights=None):
    """Independent velocities (speeds) whose constraint-consistent u best match the observed
    channels' rates (q̇ of coordinate channels, values of velocity channels), in least squares
    with the rows weighted by `weights` (default equal)."""
    b, B = (np.asarray(x) for x in _velocity_map(problem, q, jnp.asarray(t, q.dtype), params))
    if not (np.all(np.isfinite(B)) and np.all(np.isfinite(b)) and np.all(np.isfinite(rates))):
        raise ValueError(
            "qd0: the initial velocities cannot be estimated from the record (the constraints give a "
            "non-finite velocity map at the first sample, or the rates are not finite); pass qd0="
        )
    w = np.ones(B.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    v, *_ = np.linalg.lstsq(B * w[:, None], (np.asarray(rates) - b) * w, rcond=None)
    return v


def prepare(
    mech: Mechanism,
    params: PyTree,
    data: Record,
    *,
    free: Sequence[str],
    positive: Sequence[str] = (),
    observe: Optional[Sequence[str]] = None,
    noise: dict[str, float] | ArrayInput | None = None,
    q0: Optional[ArrayInput] = None,
    qd0: Optional[ArrayInput] = None,
    method: str = "lagrange",
    solver: Optional[diffrax.AbstractSolver[Any]] = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    shooting: int = 1,
    differentiation: str = "forward",
    defect_weight: float = 10.0,
    speed_names: Optional[Sequence[str]] = None,
) -> tuple[Problem, jax.Array, Observations, tuple[str, ...]]:
    """Set up the least-squares problem without solving it.

    Takes the same arguments as `fit` (see there). Returns
    `(problem, theta0, observations, names)`: the `Problem` (a pytree), the
    starting vector θ0, the `Observations` (times, data, noise levels) and
    the channel names: the n_q coordinate names, then the n_u speed names
    ("<coordinate>'" for a mechanism without `kinematics`).
    `problem.residuals(theta0, observations)` works under `jit`/`vmap`, so
    many records of the same shape can be fitted in a batch with `jax.vmap(solve_least_squares, in_axes=(None, 0, 0))`.
    """
    if not isinstance(mech, Mechanism):
        raise TypeError(f"mech must be a jaxnh.Mechanism; got {type(mech).__name__}")
    if not isinstance(data, Record):
        raise TypeError(f"data must be a jaxnh.identify.Record (e.g. from read_csv); got {type(data).__name__}")
    if differentiation not in ("forward", "reverse"):
        raise ValueError(f"differentiation must be 'forward' or 'reverse'; got {differentiation!r}")
    if q0 is not None:
        s = int(np.shape(q0)[0])
    elif mech.names is not None:
        s = len(mech.names)
    else:
        raise ValueError("q0: the mechanism has no coordinate names, so pass q0 (s,) to give the number of coordinates")
    names = mech.coordinate_names(s)
    # the velocities: q̇ without `kinematics`; with it, the speeds u (four quaternion coordinates
    # turn with three angular speeds, so n_u = n_q − groups unless qd0 or speed_names say otherwise)
    if qd0 is not None:
        n_u = int(np.shape(qd0)[0])
    elif speed_names is not None:
        n_u = len(_as_list(speed_names))
    else:
        n_u = s - len(mech.quaternions) if mech.kinematics is not None else s
    speeds = speed_names_of(mech, names, n_u, speed_names)
    channels = tuple(names) + speeds
    observe = tuple(c for c in channels if c in data.channels) if observe is None else _as_list(observe)
    if not observe:
        raise ValueError(
            f"observe: none of the coordinates {names} or speeds {speeds} is a channel of the record "
            f"({list(data.channels)})"
        )
    for c in observe:
        if c not in channels:
            raise ValueError(
                f"observe: {c!r} is not a coordinate or speed of the mechanism; coordinates are {names}, "
                f"speeds {speeds} (name the speeds with speed_names=)"
            )
    y = data.observed(observe)
    n = data.n
    sigma = _noise(noise, observe, y)
    _check_tolerance("rtol", rtol, positive=True)
    _check_tolerance("atol", atol, positive=False)
    par = Parametrisation(params, free, positive)
    for name, x in (("q0", q0), ("qd0", qd0)):
        if x is not None and not np.all(np.isfinite(np.asarray(x, dtype=float))):
            raise ValueError(f"{name} must be finite (a starting guess of the initial state); got {np.asarray(x)}")
    start = np.asarray(par.pack())
    if not np.all(np.isfinite(start)):
        bad = [lab for lab, v in zip(par.labels, start) if not np.isfinite(v)]
        raise ValueError(f"params: the starting values of the free parameters must be finite; {', '.join(bad)} are not")
    params = par.params
    f = jnp.result_type(float)
    t0 = float(data.t[0])
    observed = tuple(channels.index(c) for c in observe)
    column = {i: j for j, i in enumerate(observed)}  # channel index -> column of y
    in_group = {i for g in mech.quaternions for i in g}
    positions = tuple(i for i in observed if i < s and i not in in_group)
    rotations = tuple(g for g in mech.quaternions if any(i in column for i in g))
    q0_fixed = nominal_coordinates(mech, s, q0)
    if q0 is None:  # an orientation measured whole: its nominal value is the first sample
        for g in rotations:
            if all(i in column for i in g):
                e = np.asarray(y[0, [column[i] for i in g]], dtype=float)
                if np.all(np.isfinite(e)) and np.linalg.norm(e) > 0:
                    q0_fixed[list(g)] = e / np.linalg.norm(e)
    if not isinstance(shooting, (int, np.integer)) or shooting < 1:
        raise ValueError(f"shooting must be a positive integer (number of segments); got {shooting!r}")
    qd_guess = np.zeros(n_u) if qd0 is None else np.asarray(qd0, dtype=float)
    mech.check_shapes(jnp.asarray(q0_fixed, f), jnp.asarray(qd_guess, f), t0, params, arguments=("q0", "qd0"))
    independent = mech.independent
    if independent is None:
        independent = choose_independent(mech, jnp.asarray(q0_fixed), jnp.asarray(qd_guess), t0, params)
    if shooting == 1:
        starts, length = (0,), n
    else:
        length = math.ceil((n - 1) / shooting) + 1
        starts = tuple(k * (length - 1) for k in range(shooting - 1)) + (n - length,)
        if length < 2 * RATE_WINDOW or any(b <= a for a, b in zip(starts, starts[1:])):
            raise ValueError(
                f"shooting={shooting}: segments of {length} samples are too short for a record "
                f"of {n} samples; use at most {max(1, (n - 1) // (2 * RATE_WINDOW))} segments"
            )
    problem = Problem(
        mech=mech,
        par=par,
        q0_fixed=jnp.asarray(q0_fixed, f),
        observed=observed,
        independent=tuple(independent),
        starts=starts,
        length=length,
        method=method,
        solver=fit_solver(solver, params, rtol),
        tol=jnp.asarray([rtol, atol], f),
        max_steps=max_steps,
        differentiation=differentiation,
        defect_weight=defect_weight,
        positions=positions,
        rotations=rotations,
        n_speeds=n_u,
    )
    coordinate = np.asarray([i < s for i in observed])

    def targets(values, slopes):  # the observed channels' rates: q̇ of a coordinate, a velocity itself
        return np.where(coordinate, slopes, values)

    def weights(value_std, slope_std):  # 1/(standard error) of those rates, at least the noise's share
        floor = np.asarray(sigma, dtype=float) / np.where(coordinate, window, 1.0)
        return 1.0 / np.maximum(np.where(coordinate, slope_std, value_std), 1e-3 * floor)

    window = float(data.t[min(RATE_WINDOW, n) - 1] - data.t[0])  # s
    # starting initial state: data at t0 for the observed coordinates, rates from a local fit
    q_start, rates, q_err, rate_err = _local_rates(data.t, y, 0)
    q_init = q0_fixed.copy()
    if q0 is None:
        q_init[list(positions)] = y[0, [column[i] for i in positions]]
    if qd0 is not None:
        v0 = np.asarray(qd0, dtype=float)[list(problem.independent)]
    else:
        v0 = _independent_from_rates(
            problem, jnp.asarray(q_init, f), targets(q_start, rates), t0, params, weights(q_err, rate_err)
        )
    theta0 = [np.asarray(par.pack()), q_init[list(positions)], np.zeros(3 * len(rotations)), v0]
    if shooting > 1:
        observed_q = [i for i in observed if i < s]
        if len(observed_q) < s:  # unobserved coordinates at the segment starts: simulate the starting guess
            th = jnp.concatenate([jnp.asarray(x, f) for x in theta0])
            single = dataclasses.replace(problem, starts=(0,), length=n)
            q_guess = np.asarray(_trajectory(single, th, jnp.asarray(data.t, f)))
        else:
            q_guess = np.zeros((n, s))
        for st in starts[1:]:
            q_seg = q_guess[st].copy()
            val, rate, val_err, rate_err = _local_rates(data.t, y, st)
            q_seg[observed_q] = val[[column[i] for i in observed_q]]
            q_seg = nominal_coordinates(mech, s, q_seg)  # a measured quaternion at unit norm
            v_seg = _independent_from_rates(
                problem,
                jnp.asarray(q_seg, f),
                targets(val, rate),
                float(data.t[st]),
                params,
                weights(val_err, rate_err),
            )
            theta0 += [q_seg, v_seg]
    theta0 = jnp.concatenate([jnp.asarray(x, f).reshape(-1) for x in theta0])
    obs = Observations(jnp.asarray(data.t, f), jnp.asarray(y, f), jnp.asarray(sigma, f))
    return problem, theta0, obs, channels


def _check_tolerance(name: str, value, positive: bool):
    number = isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
    if not number or not (value > 0 if positive else value >= 0) or not np.isfinite(value):
        raise ValueError(
            f"{name}={value!r}: the ODE tolerance must be a finite number "
            + ("> 0 (or 'auto')" if positive else "≥ 0")
            + ", e.g. rtol=1e-8, atol=1e-10"
        )


def _noise(noise, observe, y):
    if noise is None:
        sigma = np.asarray(noise_level(np.asarray(y)))
        if not np.all(sigma > 0):
            zero = [c for c, s in zip(observe, sigma) if not s > 0]
            raise ValueError(
                f"noise=None: the noise level estimated from the data is zero for {zero} "
                "(noise-free data?); pass noise= with the measurement standard deviation"
            )
        return sigma
    if isinstance(noise, dict):
        missing = [c for c in observe if c not in noise]
        if missing:
            raise ValueError(f"noise: no standard deviation given for observed channel(s) {missing}")
        sigma = np.asarray([float(noise[c]) for c in observe])
    else:
        sigma = np.broadcast_to(np.asarray(noise, dtype=float), (len(observe),)).copy()
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(
            f"noise: standard deviations must be finite and > 0; got { {c: float(x) for c, x in zip(observe, sigma)} }"
        )
    return sigma


def fit_solver(solver, params, rtol: float):
    """The ODE solver a fit uses: `solver` if given; else, when params hold
    measured inputs (`Sampled` profiles) and rtol ≥ 1e-9, `diffrax.Tsit5`;
    else `default_solver(rtol)` for a small vector field.

    A sampled input is a spline through samples a few ms apart, whose third
    derivative jumps at every sample, so the motion is only C⁴ there and an
    8th-order method loses its advantage. Measured on the embedded variator
    record at rtol 1e-8: `jaxnh fit` took the same time with diffrax's Dopri8
    (what `default_solver` picks for this vector field size) as with Tsit5,
    but Dopri8's step control made the least-squares objective rough: a fit
    to noise-free data stalled at relative errors of 7e-8 after 46 iterations
    instead of reaching 1e-12 in 13.
    """
    if solver is not None:
        return solver

    sampled = any(
        isinstance(x, Sampled) for x in jax.tree_util.tree_leaves(params, is_leaf=lambda x: isinstance(x, Sampled))
    )
    if sampled and rtol >= DOP853_BELOW_RTOL:
        return diffrax.Tsit5()
    # an explicit solver keeps fits on diffrax's loop (the lean loop steps onto every report
    # time; the fits' measured convergence and calibration were established on diffrax's steps)

    return default_solver(rtol, None, "appell")


def fit(
    mech: Mechanism,
    params: PyTree,
    data: Record,
    *,
    free: Sequence[str],
    positive: Sequence[str] = (),
    observe: Optional[Sequence[str]] = None,
    noise: dict[str, float] | ArrayInput | None = None,
    q0: Optional[ArrayInput] = None,
    qd0: Optional[ArrayInput] = None,
    method: str = "lagrange",
    solver: Optional[diffrax.AbstractSolver[Any]] = None,
    rtol: float | str = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    optimizer: str | optax.GradientTransformation = "levenberg-marquardt",
    tol: float = 1e-8,
    max_iterations: int = 100,
    shooting: int = 1,
    differentiation: str = "auto",
    rank_tol: float = 1e-8,
    progress: bool = False,
    speed_names: Optional[Sequence[str]] = None,
) -> FitResult:
    """Estimate the free parameters of `mech` and its initial state from a record.

    Minimises `Σ_channels Σ_samples ((y_sim − y) / sigma)²` over the free
    parameters and the initial state, simulating with `jaxnh.simulate`. A
    channel is a coordinate or a velocity: for a mechanism with
    `kinematics` (speeds u, `q̇ = kinematics(q, u, t, p)`), a speed such as a
    gyro's angular velocity (rad/s); without it, a q̇ named "<coordinate>'".

    Arguments:
        mech: the `Mechanism`.
        params: starting params pytree; the free parameters' values are the
            starting guess, everything else is held fixed (torques from the
            record must already be in it, e.g. as `profiles.Sampled`).
        data: the measured `Record`.
        free: names (paths) of the parameters to estimate, e.g.
            `("J1", "J2", "U21")`; a profile contributes its trainable values.
        positive: the subset of `free` kept positive by estimating logarithms
            (inertias, ratios). Their standard errors are then relative ones.
        observe: channel names to fit (default: every coordinate and speed
            the record has), e.g. `("phi1",)` for one encoder; coordinates by
            `Mechanism.names`, velocities by `speed_names`.
        noise: measurement standard deviation per channel (a dict by name, or
            one number), units of the channel; default: the record's `sigma`
            when it has one, else estimated from the data (`noise_level`). The covariance is scaled by the residual
            variance either way.
        q0, qd0: starting guesses of the initial coordinates (n_q,) and
            velocities — the speeds u0 (n_u,) of a mechanism with
            `kinematics`, else q̇0 (n_q,). The initial positions of observed
            coordinates and the independent velocities (speeds) are always
            estimated; unobserved positions are held at q0 (default 0, and
            the identity (1, 0, 0, 0) for a quaternion group). A unit
            quaternion (`Mechanism(quaternions=...)`) with any observed
            component is estimated as a rotation vector δθ (3 unknowns,
            rad, labelled "rot_x[e0..e3](t0)" etc.) in the body axes of its
            nominal value e_nom: e(t0) = e_nom ⊗ exp(δθ/2), which stays a
            unit quaternion; e_nom is q0's group (normalised) or, without
            q0, the first sample of the group when all four components are
            observed, else the identity.
        method, solver, rtol, atol, max_steps: passed to `simulate`; with
            `solver=None` and measured inputs (`jaxnh.profiles.Sampled`) in
            params, `diffrax.Tsit5` (see `fit_solver`). rtol default 1e-8 (the
            calibrated setting, benchmarks/CALIBRATION.md). `rtol="auto"`:
            the ODE tolerance follows the precision the data
            demand — the fit starts at `AUTO_RTOL_START` (1e-8, atol as
            given) and, once fitted, measures the solver's own error against
            a solve 1000× tighter; if that error, projected on what the
            parameters can explain, exceeds `ODE_ERROR_STD` standard errors,
            rtol and atol are tightened in proportion (at most to
            `AUTO_RTOL_MIN`) and the fit is continued from where it stopped
            (`ode_error_in_std`). A number fixes rtol.
        optimizer: "levenberg-marquardt" (jaxnh's own, default) or an optax
            `GradientTransformation` (e.g. `optax.adam(1e-2)`), which works on
            θ (log-parameters for positive ones).
        tol: relative and absolute tolerance of the optimiser's termination.
        max_iterations: iteration limit.
        shooting: number of segments for multiple shooting (1 = single
            shooting). With more, the record is cut into segments whose
            initial states are estimated too, with continuity enforced by
            penalties; this tolerates long records and poor starting guesses.
            The answer is then polished by single shooting, from which the
            statistics come.
        differentiation: "forward" (Jacobian from forward sensitivities
            integrated with the solve, `jaxnh.ForwardSensitivity`), "reverse"
            (checkpointed adjoint; optax only), or "auto":
            Levenberg–Marquardt always uses forward mode (it needs the full
            Jacobian of thousands of residuals by tens of unknowns); optax
            uses forward mode up to `FORWARD_MAX_UNKNOWNS` unknowns.
        rank_tol: relative singular value of the column-scaled Jacobian below
            which a direction counts as undetermined by the data.
        progress: print one line per iteration (iteration, loss, step).
        speed_names: names of the n_u velocities, for `observe`, `noise` and
            the labels (default "<coordinate>'" without `kinematics`, i.e.
            q̇; "u0", "u1", ... with it), e.g. `("vx", "vy", "wx", "wy", "wz")`.
            With `kinematics` and neither qd0 nor speed_names, n_u is taken
            as n_q minus one per quaternion group.

    Returns:
        A `FitResult`.
    """
    started = time.perf_counter()
    sigma = getattr(data, "sigma", None)
    if noise is None and sigma:
        noise = dict(sigma)  # the record's own noise levels (Record.sigma, a dict once checked)
    lm = isinstance(optimizer, str)
    if lm and optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {OPTIMIZERS} or an optax GradientTransformation; got {optimizer!r}")
    if not lm and not hasattr(optimizer, "update"):
        raise TypeError(
            f"optimizer must be one of {OPTIMIZERS} or an optax GradientTransformation; got {type(optimizer).__name__}"
        )
    if differentiation not in ("auto", "forward", "reverse"):
        raise ValueError(f"differentiation must be 'auto', 'forward' or 'reverse'; got {differentiation!r}")
    if lm and differentiation == "reverse":
        raise ValueError(
            "differentiation='reverse' is not available with Levenberg–Marquardt, which needs the "
            "Jacobian of every residual (forward mode); use an optax optimizer for reverse mode"
        )
    if not isinstance(shooting, (int, np.integer)) or isinstance(shooting, bool) or shooting < 1:
        raise ValueError(f"shooting must be a positive integer (number of segments); got {shooting!r}")
    auto_rtol = isinstance(rtol, str)
    if auto_rtol and rtol != "auto":
        raise ValueError(f"rtol must be a number or 'auto'; got {rtol!r}")
    rtol = AUTO_RTOL_START if auto_rtol else rtol
    _check_tolerance("rtol", rtol, positive=True)
    _check_tolerance("atol", atol, positive=False)
    kw: dict[str, Any] = dict(
        free=free,
        positive=positive,
        observe=observe,
        noise=noise,
        q0=q0,
        qd0=qd0,
        method=method,
        solver=solver,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        speed_names=speed_names,
    )
    iterations = 0
    theta_ms = None
    if shooting > 1:
        problem, theta0, obs, names = prepare(mech, params, data, shooting=shooting, **kw)
        if progress:
            print(f"multiple shooting: {shooting} segments, {problem.size} unknowns")
        # always Levenberg–Marquardt, to a looser tolerance: single shooting polishes the answer
        theta_ms, _, _, its, _, _ = _optimise(
            problem, OPTIMIZERS[0], theta0, obs, names, max(tol, 1e-6), max_iterations, progress
        )
        iterations += its
        theta_ms = np.asarray(theta_ms)[: problem.n_params + problem.n_initial]
    problem, theta0, obs, names = prepare(mech, params, data, **kw)
    if differentiation == "auto":
        differentiation = "forward" if lm or problem.size <= FORWARD_MAX_UNKNOWNS else "reverse"
    problem = dataclasses.replace(problem, differentiation=differentiation)
    if theta_ms is not None:
        theta0 = jnp.asarray(theta_ms)
    if progress:
        print(
            f"{'Levenberg–Marquardt' if lm else 'optax'} on {problem.size} unknowns, {obs.y.size} residuals "
            f"({', '.join(problem.labels(names)[:6])}{', …' if problem.size > 6 else ''})"
        )
    theta, r, J, its, stopped, why = _optimise(problem, optimizer, theta0, obs, names, tol, max_iterations, progress)
    iterations += its
    # The ODE tolerance follows the precision the data demand: tighten it while the solver's own error is
    # not negligible against the standard errors, and continue the fit from where it stopped.
    first_err = None
    for _ in range(AUTO_REFINEMENTS if auto_rtol else 0):
        err = ode_error_in_std(problem, theta, obs, r, J)
        first_err = err if first_err is None else first_err
        if err <= ODE_ERROR_STD or problem.rtol <= AUTO_RTOL_MIN:
            break
        factor = max(min(0.5 * ODE_ERROR_STD / err, 0.1), 1e-3)  # error ∝ tolerance; at least 10× tighter
        new_rtol = max(problem.rtol * factor, AUTO_RTOL_MIN)
        problem = problem.with_tolerances(new_rtol, problem.atol * new_rtol / problem.rtol)
        if progress:
            print(
                f"  the ODE solver's error is {err:.2g} standard errors (> {ODE_ERROR_STD}): "
                f"continuing at rtol {problem.rtol:.2g}, atol {problem.atol:.2g}"
            )
        theta, r, J, its, stopped, why = _optimise(problem, optimizer, theta, obs, names, tol, max_iterations, progress)
        iterations += its
    if first_err is not None and problem.rtol < AUTO_RTOL_START:
        why += (
            f" (ODE rtol tightened to {problem.rtol:.2g}: at rtol {AUTO_RTOL_START:g} the solver's error "
            f"was {first_err:.2g} standard errors)"
        )
    how = dict(
        iterations=iterations,
        optimizer=OPTIMIZERS[0] if lm else "optax",
        differentiation=differentiation,
        shooting=shooting,
        elapsed=time.perf_counter() - started,
    )
    return _result(problem, names, obs, theta, r, J, stopped, why, rank_tol, noise_estimated=noise is None, how=how)


def ode_error_in_std(problem: Problem, theta, obs: Observations, r, J) -> float:
    """The ODE solver's error at θ, in standard errors of the estimates.

    The fitted channels (from the weighted residuals r at θ) are compared
    with a solve at 1000× tighter tolerances; the difference, in noise
    units, is projected on the range of the weighted Jacobian J — the part
    that would move the estimates. Its length is the shift of the estimate
    that the solver's error causes, in standard errors (for noise levels as
    stated; the fit's own s² is not used, so noise-free records count against
    their stated noise). Returns inf when a solve failed.
    """
    n, k = obs.y.shape
    fine = problem.with_tolerances(problem.rtol * 1e-3, problem.atol * 1e-3)
    q_fine = np.asarray(_channels(fine, jnp.asarray(theta), obs.t))[:, list(problem.observed)]
    sigma = np.asarray(obs.sigma)
    w = np.asarray(r)[: n * k].reshape(n, k)
    if np.any(w == FAILED_RESIDUAL) or not np.all(np.isfinite(q_fine)):
        return float("inf")
    e = ((np.asarray(obs.y) + w * sigma - q_fine) / sigma).reshape(-1)
    Jd = np.asarray(J)[: n * k]
    c = np.linalg.norm(Jd, axis=0)
    U, sv, _ = thin_svd(Jd / np.where(c > 0, c, 1.0))
    U = U[:, sv > 1e-10 * sv[0]]
    return float(np.linalg.norm(U.T @ e))


def _optimise(problem: Problem, optimizer, theta0, obs: Observations, names, tol, max_iterations, progress):
    """One run of the optimiser from θ0: `(θ, r, J, iterations, stopped on its tolerances, why in words)`.

    Levenberg–Marquardt (`optimizer` a name) is `solve_least_squares_host`; an
    optax `GradientTransformation` runs `_optax_loop`, and the forward-mode
    Jacobian at its answer is evaluated for the statistics when it has none."""
    if isinstance(optimizer, str):
        out = solve_least_squares_host(
            problem,
            theta0,
            obs,
            tol=tol,
            max_steps=max_iterations,
            progress=_progress(problem, names, obs) if progress else None,
        )
        code = int(out["result"])
        return out["theta"], out["r"], out["J"], int(out["steps"]), code == 0, lm_message(code, max_iterations)
    theta, r, J, its, stopped = _optax_loop(problem, optimizer, jnp.asarray(theta0), obs, tol, max_iterations, progress)
    if J is None:
        r, J = value_and_jacobian(dataclasses.replace(problem, differentiation="forward"), theta, obs)
    why = "loss stopped changing" if stopped else f"iteration limit ({max_iterations}) reached"
    return theta, r, J, its, stopped, why


def _progress(problem, names, obs):
    labels = problem.par.labels
    show = tuple(i for i, lab in enumerate(labels) if "[" not in lab)[:3]
    log = problem.par.log_mask()
    return _Progress(tuple(labels[i] for i in show), show, tuple(bool(log[i]) for i in show), int(obs.y.size))


@eqx.filter_jit
def _optax_update(optimizer, theta, state, g):
    updates, state = optimizer.update(g, state, theta)
    return theta + updates, state


@solve_jit
def _loss_and_grad_reverse(problem, theta, obs):
    def loss(th):
        res = problem.residuals(th, obs)
        return 0.5 * jnp.dot(res, res), res

    (_, r), g = jax.value_and_grad(loss, has_aux=True)(theta)
    return r, g


def _optax_step(problem, optimizer, theta, state, obs):
    """One optax update; also returns the loss, residuals and (forward mode) Jacobian at θ.

    In forward mode the gradient of ½|r|² is Jᵀ r from `value_and_jacobian`
    (compiled once per problem and shared with the final statistics); in
    reverse mode it comes from an adjoint pass and J is None.
    """
    if problem.differentiation == "forward":
        r, J = value_and_jacobian(problem, theta, obs)
        g = J.T @ r
    else:
        r, g = _loss_and_grad_reverse(problem, theta, obs)
        J = None
    new, state = _optax_update(optimizer, theta, state, g)
    return new, state, 0.5 * jnp.dot(r, r), r, J


def _optax_loop(problem, optimizer, theta, obs, tol, max_iterations, progress, patience: int = 10):
    """Plain optax iterations; stop when the loss changed by less than tol (relative) over `patience` steps.

    Returns the best θ seen, with its residuals and Jacobian (None in reverse mode),
    the number of iterations and whether the loss stopped changing.
    """
    state = optimizer.init(theta)
    history, best = [], (np.inf, theta, None, None)
    stopped, k = False, 0
    for k in range(1, max_iterations + 1):
        new, state, value, r, J = _optax_step(problem, optimizer, theta, state, obs)
        value = float(value)
        history.append(value)
        if value < best[0]:
            best = (value, theta, r, J)
        if progress:
            print(
                f"  iter {k - 1:3d}  loss {value:12.6e}  rms {np.sqrt(2 * value / r.size):9.4g}  "
                f"step {float(jnp.max(jnp.abs(new - theta))):8.2e}",
                flush=True,
            )
        theta = new
        if len(history) > patience and abs(history[-1 - patience] - value) <= tol * max(abs(value), 1e-300):
            stopped = True
            break
    return best[1], best[2], best[3], k, stopped


def _result(problem, names, obs, theta, r, J, stopped, why, rank_tol, *, noise_estimated: bool, how: dict) -> FitResult:
    """The `FitResult` at θ from the weighted residuals r and their Jacobian J there; `how` holds the
    fields that say how the fit was done (iterations, optimizer, differentiation, shooting, elapsed)."""
    stats = statistics_host(J, r, rank_tol=rank_tol)
    fields = estimate_fields(problem, problem.labels(names), theta, stats, rank_tol)
    theta = fields["theta"]
    params, q0, qd0 = _estimate_state(problem, jnp.asarray(theta), jnp.asarray(obs.t[0]))
    q0, qd0 = np.asarray(q0), np.asarray(qd0)
    n, k = obs.y.shape
    sigma = np.asarray(obs.sigma)
    weighted = np.asarray(r)[: n * k].reshape(n, k)
    failed = bool(np.any(weighted == FAILED_RESIDUAL))
    fitted = np.asarray(obs.y) + weighted * sigma
    res = np.asarray(obs.y) - fitted
    observe = tuple(names[i] for i in problem.observed)
    gn = float(stats["gn_step"])
    tiny = bool(np.all(np.abs(stats["gn_delta"]) <= STEP_RTOL * (1 + np.abs(theta))))
    converged = bool(stopped and (gn < GN_STEP_TOL or tiny) and not failed)
    message = why + (
        f"; remaining Gauss–Newton step {gn:.2g} standard errors"
        if not tiny or gn < GN_STEP_TOL
        else "; remaining Gauss–Newton step below 1e-9 of every unknown (residuals at rounding level)"
    )
    if failed:
        message += "; THE SIMULATION FAILED at the final parameters (see jaxnh.simulate's status)"
    lof = lack_of_fit(res, sigma, float(stats["s2"]), int(stats["dof"]), noise_estimated, observe, converged)
    ident = fields["identifiability"]
    if not ident.identifiable:
        warnings.warn("jaxnh.fit: " + " ".join(ident.messages), stacklevel=3)
    if lof.significant and converged:
        warnings.warn("jaxnh.fit: " + lof.message, stacklevel=3)
    return FitResult(
        **fields,
        params=params,
        q0=q0,
        qd0=qd0,
        converged=converged,
        message=message,
        rms_residual=float(np.sqrt(np.mean(res**2))),
        rms_by_channel={c: float(np.sqrt(np.mean(res[:, i] ** 2))) for i, c in enumerate(observe)},
        noise={c: float(s) for c, s in zip(observe, sigma)},
        chi2_dof=float(stats["s2"]),
        lack_of_fit=lof,
        t=np.asarray(obs.t),
        observe=observe,
        measured=np.asarray(obs.y),
        fitted=fitted,
        residuals=res,
        gn_step=gn,
        **how,
    )
