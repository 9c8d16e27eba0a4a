"""Figures of a variator fit: data against fit with residuals, and U21(t) with its band."""

from __future__ import annotations

import numpy as np

from ._fit import FitResult

__all__ = ["plot_fit", "plot_ratio"]

Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_fit(result: FitResult, path: str, record=None, title: str = "") -> str:
    """Measured and fitted angles, the residuals per channel with ±2σ noise
    lines, and (given the record) the applied torques. Writes a PNG to `path`."""
    plt = _plt()
    k = len(result.observe)
    rows = 1 + k + (record is not None and bool(record.inputs))
    fig, ax = plt.subplots(rows, 1, figsize=(10, 2.4 * rows + 0.6), sharex=True,
                           gridspec_kw={"height_ratios": [1.6] + [1] * (rows - 1)})
    t = result.t
    for i, c in enumerate(result.observe):
        ax[0].plot(t, result.measured[:, i], ".", ms=2, color=f"C{i}", alpha=0.5, label=f"{c} measured")
        ax[0].plot(t, result.fitted[:, i], "-", lw=1, color="k" if i == 0 else "0.35", label=f"{c} fit")
    ax[0].set(ylabel="angle [rad]", title=title or "encoder angles: measured (dots) and fitted simulation (lines)")
    ax[0].legend(loc="upper left", fontsize=8, ncol=2)
    for i, c in enumerate(result.observe):
        a = ax[1 + i]
        r = 1e3 * result.residuals[:, i]
        s = 1e3 * result.noise[c]
        a.plot(t, r, ".", ms=2, color=f"C{i}")
        for sign in (-2, 2):
            a.axhline(sign * s, color="0.5", lw=0.8, ls="--")
        a.axhline(0, color="k", lw=0.6)
        a.set(ylabel=f"{c} residual\n[mrad]")
        a.text(0.99, 0.95, f"rms {1e3 * result.rms_by_channel[c]:.3f} mrad, noise σ {s:.3f} mrad (dashed ±2σ)",
               transform=a.transAxes, ha="right", va="top", fontsize=8)
    if rows > 1 + k:
        a = ax[-1]
        for j, (name, v) in enumerate(record.inputs.items()):
            a.plot(record.t, v, color=f"C{j + 2}", label=name)
        a.axhline(0, color="k", lw=0.6)
        a.set(ylabel="torque [N·m]")
        a.legend(loc="upper left", fontsize=8)
    ax[-1].set(xlabel="t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_ratio(result: FitResult, path: str, truth=None, n: int = 401) -> str:
    """U21(t) estimated, with its knots and 95 % pointwise band; below, the
    band around zero (it is too narrow to see at full scale) and, if `truth`
    (a function of t) is given, the true minus the estimated ratio. Writes a PNG."""
    plt = _plt()
    ts = np.linspace(result.t[0], result.t[-1], n)
    u, s = result.profile_band("U21", ts)
    spline = result.params.U21
    kt = np.asarray(spline.knots)
    kv = np.asarray(result.estimates["U21"]["value"])
    ks = np.asarray(result.estimates["U21"]["std"])
    fig, ax = plt.subplots(2, 1, figsize=(10, 6.2), sharex=True, gridspec_kw={"height_ratios": [1.4, 1]})
    ax[0].plot(ts, u, "C0", label="U21(t) estimate")
    ax[0].fill_between(ts, u - Z95 * s, u + Z95 * s, color="C0", alpha=0.25, label="95 % band")
    ax[0].errorbar(kt, kv, yerr=Z95 * ks, fmt="o", color="C0", ms=4, capsize=3, label="spline knots")
    if truth is not None:
        ax[0].plot(ts, [truth(x) for x in ts], "k--", lw=1, label="true U21")
    ax[0].set(ylabel="U21 = r / rho", title="transmission ratio U21(t)")
    ax[0].legend(fontsize=8)
    ax[1].fill_between(ts, -Z95 * s, Z95 * s, color="C0", alpha=0.25, label="95 % band of the estimate")
    ax[1].errorbar(kt, np.zeros_like(kt), yerr=Z95 * ks, fmt="o", color="C0", ms=3, capsize=3)
    if truth is not None:
        ax[1].plot(ts, np.array([truth(x) for x in ts]) - u, "k-", lw=1, label="true − estimate")
    ax[1].axhline(0, color="k", lw=0.6)
    ax[1].set(xlabel="t [s]", ylabel="U21 deviation")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
