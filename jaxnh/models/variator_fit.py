"""Identification of the friction variator: J1, J2 and the ratio law U21(t).

The record supplies the encoder angles phi1, phi2 (rad) and the torques
M1, M2 (N·m); the torques become `profiles.Sampled` inputs, U21(t) a
`profiles.CubicSpline` on a uniform knot grid over the record, and J1, J2 and
the spline values are estimated as positive quantities (logarithms).

The starting guess, when not given, comes from the data by the equation-error
method: smoothed rates and accelerations (Savitzky–Golay) give U21 ≈ phi2'/phi1'
at the knots, and eq. (9), `(J1 + J2 U²) phi1'' + J2 U U' phi1' = M1 + U M2`,
is linear in J1 and J2, so ordinary least squares gives them.
"""

from __future__ import annotations

import json
import math
from importlib import resources
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._base.compile import one_shot_jit
from jaxnh._base.dataframe import json_safe
from jaxnh._model.profiles import CubicSpline, Sampled
from jaxnh.identify._experiment import encoder_noise, experiment
from jaxnh.identify._fit import fit, FitResult
from jaxnh.identify.data import load_default, Record
from jaxnh.models import variator as V


__all__ = [
    "FREE",
    "DEFAULT_KNOTS",
    "params_for",
    "ratio_knots",
    "starting_guess",
    "fit_variator",
    "report",
    "embedded_truth",
    "variator_experiment",
]

FREE = ("J1", "J2", "U21")
DEFAULT_KNOTS = 7
SMOOTHING_WINDOW = 0.12  # s, Savitzky–Golay window for the starting guess


def params_for(record: Record, J1, J2, U21) -> V.VariatorParams:
    """Variator params with the record's torques M1, M2 as `Sampled` inputs (N·m).

    A missing torque column counts as zero torque.
    """
    t = record.t
    M = {k: Sampled(t, record.inputs[k]) if k in record.inputs else 0.0 for k in ("M1", "M2")}
    return V.VariatorParams(J1, J2, U21, M["M1"], M["M2"])


def ratio_knots(record: Record, n_knots: int = DEFAULT_KNOTS) -> np.ndarray:
    """A uniform grid of `n_knots` knot times (s) spanning the record."""
    if int(n_knots) != n_knots or n_knots < 2:
        raise ValueError(f"knots: need an integer number of knots ≥ 2; got {n_knots!r}")
    return np.linspace(record.t[0], record.t[-1], int(n_knots))


def _spline_basis(knots, t):
    """Matrices (len(t), len(knots)) of the natural spline's values and time derivatives
    (1/s) at t: both are linear in the knot values."""
    B, dB = _basis(jnp.asarray(knots, dtype=float), jnp.asarray(t, dtype=float))
    return np.asarray(B), np.asarray(dB)


@one_shot_jit
def _basis(knots, t):
    def at(e):
        s = CubicSpline(knots, e)
        return jax.vmap(s)(t), jax.vmap(s.derivative)(t)

    B, dB = jax.vmap(at)(jnp.eye(knots.shape[0], dtype=t.dtype))
    return B.T, dB.T


def savgol_derivative(y, window: int, order: int, deriv: int, dt: float) -> np.ndarray:
    """The `deriv`-th time derivative of samples `y` (spaced `dt` s) by a Savitzky–Golay
    filter: at each sample, the derivative of the least-squares polynomial of degree
    `order` through the `window` (odd) samples centred on it; within half a window of
    either end, of the polynomial through the first or last `window` samples (the same
    result as SciPy's `savgol_filter(..., mode="interp")`, without importing scipy.signal,
    which takes a second). Units: those of y per s**deriv."""
    y = np.asarray(y, dtype=float)
    half = window // 2
    x = np.arange(-half, half + 1, dtype=float)
    P = np.linalg.pinv(np.vander(x, order + 1, increasing=True))  # window samples → coefficients

    def at(coef, xs):  # d^deriv/dx^deriv of Σ coef_k x^k at xs, per dt^deriv
        out = np.zeros_like(xs)
        for k in range(deriv, order + 1):
            out += coef[k] * math.factorial(k) / math.factorial(k - deriv) * xs ** (k - deriv)
        return out / dt**deriv

    w = P[deriv] * math.factorial(deriv) / dt**deriv
    res = np.empty_like(y)
    res[half : len(y) - half] = np.correlate(y, w, mode="valid")
    res[:half] = at(P @ y[:window], x[:half])
    res[len(y) - half :] = at(P @ y[-window:], x[half + 1 :])
    return res


def starting_guess(record: Record, knots, observe=("phi1", "phi2")):
    """Starting J1, J2 (kg·m²) and U21 spline from the data by the equation-error method.

    Needs the torques; with only one encoder, U21 starts at 1. Falls back to
    equal shares of one effective inertia when least squares gives a
    non-positive value.

    Returns:
        `(J1, J2, U21)` with U21 a `CubicSpline` on `knots`.
    """
    t = record.t
    dt = float(np.median(np.diff(t)))
    win = max(7, int(round(SMOOTHING_WINDOW / dt)) | 1)  # odd window of about 0.12 s
    if win > len(t):
        win = len(t) if len(t) % 2 else len(t) - 1
    d = {
        c: (
            savgol_derivative(record.channels[c], win, 3, 1, dt),
            savgol_derivative(record.channels[c], win, 3, 2, dt),
        )
        for c in observe
        if c in record.channels
    }
    B, dB = _spline_basis(knots, t)
    if "phi1" in d and "phi2" in d:
        w1, w2 = d["phi1"][0], d["phi2"][0]
        ok = np.abs(w1) > 0.2 * np.max(np.abs(w1))
        if ok.sum() < len(knots):
            ok = np.ones_like(ok)
        u, *_ = np.linalg.lstsq(B[ok], (w2[ok] / np.where(ok, w1, 1.0)[ok]), rcond=None)
        u = np.clip(u, 0.05 * np.max(np.abs(u)), None) if np.max(u) > 0 else np.ones(len(knots))
    else:
        u = np.ones(len(knots))
    U21 = CubicSpline(knots, u)
    U, dU = B @ u, dB @ u
    if "phi1" in d:
        w, a = d["phi1"]
    else:
        w, a = d["phi2"][0] / U, (d["phi2"][1] - dU * d["phi2"][0] / U) / U
    M1 = record.inputs.get("M1", np.zeros_like(t))
    M2 = record.inputs.get("M2", np.zeros_like(t))
    A = np.stack([a, U**2 * a + U * dU * w], axis=1)
    b = M1 + U * M2
    inner = slice(win, len(t) - win) if len(t) > 3 * win else slice(None)
    (J1, J2), *_ = np.linalg.lstsq(A[inner], b[inner], rcond=None)
    if not (J1 > 0 and J2 > 0):
        I, *_ = np.linalg.lstsq(a[inner, None] * (1 + U[inner, None] ** 2), b[inner], rcond=None)
        J1 = J2 = float(abs(I[0])) if I[0] != 0 else 1.0
    return float(J1), float(J2), U21


def fit_variator(
    record: Record, *, knots=DEFAULT_KNOTS, J1=None, J2=None, U21=None, observe=None, noise=None, **kwargs
) -> FitResult:
    """Fit J1, J2 and U21(t) of the variator to a record.

    Arguments:
        record: a `Record` with channels phi1 and/or phi2 (rad) and inputs
            M1, M2 (N·m).
        knots: number of U21 spline knots (uniform over the record), or the
            knot times (s).
        J1, J2: starting inertias, kg·m² (default: equation-error guess).
        U21: starting ratio, a number or a `CubicSpline` on the knots
            (default: from phi2'/phi1').
        observe, noise, **kwargs: passed to `jaxnh.identify.fit` (e.g.
            `progress=True`, `shooting=4`, `optimizer=optax.adam(1e-2)`).

    Returns:
        The `FitResult`; U21 is `result.params.U21`, its band
        `result.profile_band("U21", ts)`.
    """
    knots = ratio_knots(record, knots) if np.ndim(knots) == 0 else np.asarray(knots, dtype=float)
    observe = tuple(c for c in ("phi1", "phi2") if c in record.channels) if observe is None else tuple(observe)
    if J1 is None or J2 is None or U21 is None:
        g1, g2, gU = starting_guess(record, knots, observe)
        J1 = g1 if J1 is None else J1
        J2 = g2 if J2 is None else J2
        U21 = gU if U21 is None else U21
    if not isinstance(U21, CubicSpline):
        U21 = CubicSpline(knots, np.broadcast_to(np.asarray(U21, dtype=float), knots.shape))
    p = params_for(record, J1, J2, U21)
    return fit(V.mechanism(), p, record, free=FREE, positive=FREE, observe=observe, noise=noise, **kwargs)


def report(result: FitResult, n_grid: int = 201, source: str = "") -> dict[str, Any]:
    """The fit as a JSON-ready dict: `result.to_dict()` plus the variator's own keys.

    Every number is a finite float or None (JSON null): an undetermined
    standard error or a non-finite value is None, and then "status" (from
    `to_dict`) is not "fitted". Variator keys: "J1", "J2" ({"value", "std"},
    kg·m²), "U21" ({"t", "value", "std"} on a uniform grid of `n_grid` times
    over the record), "relative_std", "U21_knots", "data", "units"; and from
    `to_dict`: "status", "ok", "rms_residual" (rad), "iterations",
    "converged", "initial_state", "rms_by_channel", "noise", "chi2_dof",
    "lack_of_fit" (is the misfit significantly above the noise, and the
    model error relative to it), "identifiable", "message", "observe",
    "elapsed_s", "parameters", "identifiability", ...
    """
    ts = np.linspace(result.t[0], result.t[-1], n_grid)
    u, us = result.profile_band("U21", ts)
    est = result.estimates
    out = result.to_dict()
    knots = np.asarray(result.params.U21.knots)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = {k: np.float64(est[k]["std"]) / np.float64(est[k]["value"]) for k in ("J1", "J2")}
    out.update(
        {
            "J1": {"value": est["J1"]["value"], "std": est["J1"]["std"]},
            "J2": {"value": est["J2"]["value"], "std": est["J2"]["std"]},
            "U21": {"t": ts, "value": u, "std": us},
            "relative_std": rel,
            "U21_knots": {"t": knots, "value": est["U21"]["value"], "std": est["U21"]["std"]},
            "messages": list(result.identifiability.messages),
            "data": source,
            "units": {"J1": "kg m^2", "J2": "kg m^2", "U21": "1", "rms_residual": "rad", "t": "s"},
        }
    )
    if out["status"] == "fitted" and not all(np.all(np.isfinite(np.asarray(x, dtype=float))) for x in (u, us)):
        out["status"], out["ok"] = "non_finite", False
    return json_safe(out)


# --- the variator's embedded set-up -----------------------------------------------------------------


def embedded_truth() -> dict[str, Any]:
    """The values the embedded record was made with (`jaxnh/data/variator_truth.json`):
    J1, J2 (kg·m²), U21 knots and values, phi0 (rad), w0 (rad/s), duration (s),
    rate (Hz), counts_per_rev, jitter_std (rad)."""
    return json.loads(resources.files("jaxnh").joinpath("data", "variator_truth.json").read_text())


def variator_experiment(
    record: Optional[Record] = None,
    *,
    J1=None,
    J2=None,
    U21=None,
    w0=None,
    counts_per_rev=None,
    jitter_std=None,
    rtol: float = 1e-8,
):
    """The friction variator's identification experiment as `jaxnh fit` sets it up.

    Defaults are the embedded record's: its sample times (6 s at 250 Hz) and
    torques (as `Sampled` inputs), the true J1, J2 and U21 spline (7 knots) as
    nominal values, phi(0) = 0, phi1'(0) = w0 = 4 rad/s, and its two
    encoders (8192 and 4096 counts/rev with 0.3 and 0.6 mrad jitter). The
    unknowns are J1, J2 and the U21 knot values (positive: logarithms) and the
    initial state phi1(0), phi2(0), phi1'(0).

    Returns:
        `(exp, params)`: the `Experiment` and the nominal params (with the
        record's torques) it was made with.
    """
    T = embedded_truth()
    record = load_default() if record is None else record
    U21 = CubicSpline(T["U21_knots"], T["U21_values"]) if U21 is None else U21
    params = params_for(record, T["J1"] if J1 is None else J1, T["J2"] if J2 is None else J2, U21)
    counts = T["counts_per_rev"] if counts_per_rev is None else counts_per_rev
    jitter = T["jitter_std"] if jitter_std is None else jitter_std
    noise = {c: encoder_noise(n, j) for c, n, j in zip(("phi1", "phi2"), counts, jitter)}
    w0 = T["w0"] if w0 is None else w0
    qd0 = [w0, float(U21(record.t[0])) * w0]
    exp = experiment(
        V.mechanism(), params, record.t, free=FREE, positive=FREE, noise=noise, q0=T["phi0"], qd0=qd0, rtol=rtol
    )
    return exp, params
