"""Identifiability: what the data determine, said in words.

From the singular values of the column-scaled Jacobian (`statistics`), a
direction in θ along which the residuals do not change (relative singular
value below the rank tolerance) is a combination of parameters the data
cannot determine. For logarithmic entries a direction (a, b) in
(log J1, log J2) means "multiply J1 by c^a and J2 by c^b": with a = b the
data determine only the ratio J1/J2, which is what happens for the variator
when no torque acts (eq. 9 is then homogeneous in J1, J2).
"""

from __future__ import annotations

import dataclasses

import numpy as np


__all__ = ["Identifiability", "analyse", "LackOfFit", "lack_of_fit"]

SHOW_COMPONENT = 0.05  # components of a direction smaller than this (relative) are not named
POOR_RELATIVE_STD = 0.5  # a positive parameter known only to ±50 % (1σ) is called poorly determined


@dataclasses.dataclass
class Identifiability:
    """What the data determine.

    Attributes:
        identifiable: False when some combination of the free parameters is
            not determined by the data (its standard errors are infinite).
        condition: ratio of the largest to the smallest singular value of the
            column-scaled Jacobian (inf when rank deficient).
        singular_values: relative singular values, descending.
        undetermined: one entry per undetermined direction: a dict with
            `direction` {label: coefficient} (coefficients of log-parameters
            for positive ones), `singular_value`, `message`, and `identifiable`
            (a combination the data do determine, when one can be named).
        poorly_determined: labels of parameters whose relative standard
            error exceeds 50 %.
        messages: plain-language statements, for printing.
    """

    identifiable: bool
    condition: float
    singular_values: np.ndarray
    undetermined: list
    poorly_determined: list
    messages: list


def _fmt_power(x: float) -> str:
    return "" if abs(x - 1) < 0.05 else f"^{x:.2g}"


def analyse(stats: dict, labels, log_mask, rank_tol: float) -> Identifiability:
    """Turn `statistics(J, r)` (NumPy values) into an `Identifiability` report.

    Arguments:
        stats: output of `problem.statistics` (standard errors of θ itself,
            i.e. relative ones for the logarithmic entries).
        labels: label of every entry of θ.
        log_mask: which entries of θ are logarithms of positive parameters.
        rank_tol: the relative singular value below which a direction is undetermined.
    """
    sv = np.asarray(stats["sv"])
    Vt = np.asarray(stats["Vt"])
    c = np.asarray(stats["colnorm"])
    std = np.asarray(stats["std"])
    log_mask = np.asarray(log_mask)
    messages, undetermined = [], []
    dead = [labels[j] for j in range(len(labels)) if c[j] == 0]
    if dead:
        messages.append(
            f"{', '.join(dead)} do(es) not affect the observed channels at all: not identifiable from these data."
        )
    for i in np.nonzero(~(sv > rank_tol))[0]:
        d = Vt[i] / np.where(c > 0, c, 1.0)  # direction in θ (log units for positive parameters)
        d = d / np.max(np.abs(d))
        if d[np.argmax(np.abs(d))] < 0:
            d = -d
        # largest components first; components equal to 6 digits (a pure scaling: all ±1) keep the
        # parameters' order, so that rounding in the solve cannot swap the names of a ratio
        order = sorted(range(len(d)), key=lambda j: (-round(float(abs(d[j])), 6), j))
        comp = {labels[j]: float(d[j]) for j in order if abs(d[j]) >= SHOW_COMPONENT and c[j] > 0}
        if not comp:
            continue
        parts = []
        for lab, a in comp.items():
            j = labels.index(lab)
            parts.append(f"{'log ' if log_mask[j] else ''}{lab} by {a:+.2f}·ε")
        entry = {"direction": comp, "singular_value": float(sv[i]), "identifiable": None}
        names = list(comp)
        all_log = all(log_mask[labels.index(n)] for n in names)
        coeff = [comp[n] for n in names]
        if all_log and len(names) >= 2 and all(a > 0 for a in coeff) and np.ptp(coeff) < 0.05:
            what = f"scaling {', '.join(names[:-1])} and {names[-1]} by the same factor"
        else:
            what = "changing " + ", ".join(parts)
        if len(names) == 2 and all_log:
            a, b = coeff
            if a * b > 0:  # θ1^b / θ2^a is invariant
                ratio = (
                    f"{names[0]}{_fmt_power(b / a)}/{names[1]}" if abs(b / a - 1) >= 0.05 else f"{names[0]}/{names[1]}"
                )
                entry["identifiable"] = ratio
            else:
                entry["identifiable"] = f"{names[0]}{_fmt_power(-b / a)}·{names[1]}"
        elif len(names) == 2:
            a, b = coeff
            entry["identifiable"] = f"{b:+.3g}·{names[0]} {-a:+.3g}·{names[1]}"
        msg = (
            f"NOT IDENTIFIABLE: {what} leaves the simulated channels unchanged "
            f"(relative singular value {sv[i]:.1e}); the data do not determine "
            f"{' and '.join(names) if len(names) <= 3 else 'these parameters'} separately"
        )
        msg += (
            f" — only {entry['identifiable']} is determined."
            if entry["identifiable"]
            else " — only combinations orthogonal to this direction are determined."
        )
        entry["message"] = msg
        undetermined.append(entry)
        messages.append(msg)
    poor = []
    for j, lab in enumerate(labels):
        if not np.isfinite(std[j]):
            continue
        if log_mask[j] and std[j] > POOR_RELATIVE_STD:  # std of log θ = relative standard error
            poor.append(lab)
    if poor:
        messages.append(f"Poorly determined (relative standard error > {POOR_RELATIVE_STD:.0%}): {', '.join(poor)}.")
    identifiable = not undetermined and not dead
    positive = sv[sv > 0]
    condition = float(1.0 / np.min(sv)) if identifiable and positive.size == sv.size else float("inf")
    return Identifiability(identifiable, condition, sv, undetermined, poor, messages)


# Relative variance of the third-difference noise estimate `noise_level` from n
# samples of white Gaussian noise is 2 (1 + 2 Σ ρ_k²) / n with ρ = (−15, 6, −1)/20
# the autocorrelations of Δ³ noise: 4.625 / n.
NOISE_ESTIMATE_REL_VAR = 2 * (1 + 2 * (0.75**2 + 0.3**2 + 0.05**2))
LACK_OF_FIT_Z = 2.3263478740408408  # one-sided 99 % normal quantile


@dataclasses.dataclass
class LackOfFit:
    """How large the misfit is compared with the measurement noise.

    When the model contains the truth, the weighted residual variance s² is
    about 1 (residuals are noise). A model error — a law the model class
    cannot represent, an unmodelled effect — adds a systematic part: with
    noise σ per channel, its rms is estimated as σ·√(s² − 1).

    Attributes:
        s2: weighted residual variance s² = Σ r² / (N − rank).
        threshold: s² above which the misfit is significant at the 1 % level
            (one-sided), `1 + 2.33 · sd(s²)` with `sd(s²)² = 2/dof` plus,
            when the noise levels were estimated from the same record, the
            variance of that estimate (4.6 / (n · channels)).
        significant: s² > threshold: the model does not reproduce the data
            to within the noise; standard errors (scaled by s²) then include
            the model error only as if it were noise — they are indicative.
        model_error_over_noise: √max(s² − 1, 0), the rms of the systematic
            misfit in units of the noise.
        model_error_rms: the same per channel, in the channel's units (rad).
        autocorrelation: lag-1 autocorrelation of each channel's residuals
            (≈ 0 ± 1/√n for white noise; near 1 when a smooth model error dominates).
        message: one sentence, for printing.
    """

    s2: float
    threshold: float
    significant: bool
    model_error_over_noise: float
    model_error_rms: dict
    autocorrelation: dict
    message: str


def lack_of_fit(
    residuals, sigma, s2: float, dof: int, noise_estimated: bool, channels, converged: bool = True
) -> LackOfFit:
    """The `LackOfFit` of a fit from its residuals (n, k) (units of the channels),
    the noise σ per channel (k,), s², the degrees of freedom, and whether σ was
    estimated from the same record (then its uncertainty widens the test).
    For a fit that has not converged the misfit is not attributed to the model."""
    residuals = np.asarray(residuals, dtype=float)
    sigma = np.asarray(sigma, dtype=float)
    n, k = residuals.shape
    var = 2.0 / max(dof, 1)
    if noise_estimated:
        var += NOISE_ESTIMATE_REL_VAR / (max(n - 3, 1) * k)
    threshold = 1.0 + LACK_OF_FIT_Z * np.sqrt(var)
    ratio = float(np.sqrt(max(s2 - 1.0, 0.0)))
    per = {}
    rho = {}
    for i, c in enumerate(channels):
        ms = float(np.mean((residuals[:, i] / sigma[i]) ** 2))
        per[c] = float(sigma[i] * np.sqrt(max(ms - 1.0, 0.0)))
        r = residuals[:, i] - residuals[:, i].mean()
        den = float(r @ r)
        rho[c] = float(r[1:] @ r[:-1] / den) if den > 0 else 0.0
    significant = bool(s2 > threshold)
    ac = ", ".join(f"{c} {v:+.2f}" for c, v in rho.items())
    if not (np.all(np.isfinite(residuals)) and np.all(np.isfinite(sigma)) and np.isfinite(s2)):
        msg = (
            "The misfit cannot be judged: the residuals or the noise levels are not finite "
            "(a failed simulation, or data whose values overflow in double precision)."
        )
        return LackOfFit(
            float(s2),
            float(threshold),
            False,
            float("nan"),
            {c: float("nan") for c in channels},
            {c: float("nan") for c in channels},
            msg,
        )
    if significant and not converged:
        msg = (
            f"The residuals are {np.sqrt(s2):.3g}× the noise level (s² = {s2:.4g}), but the fit has not "
            "converged: the misfit may be the optimiser's rather than the model's."
        )
    elif significant:
        msg = (
            f"LACK OF FIT: the residuals are {np.sqrt(s2):.3g}× the noise level (s² = {s2:.4g} > {threshold:.3g}, "
            f"the 1 % significance limit): a model error of about {ratio:.3g}× the noise ("
            + ", ".join(f"{c} {v:.3g}" for c, v in per.items())
            + f" rms) that the model cannot represent; residual lag-1 autocorrelation {ac}. "
            "Standard errors treat it as noise and are only indicative."
        )
    else:
        msg = (
            f"The model fits to within the noise: s² = {s2:.4g} (1 % significance limit {threshold:.3g}); "
            f"model error below about {np.sqrt(max(threshold - 1, 0)):.2g}× the noise; residual lag-1 "
            f"autocorrelation {ac}."
        )
    return LackOfFit(float(s2), float(threshold), significant, ratio, per, rho, msg)
