"""Figures of a fit: data against fit with residuals (any mechanism), and U21(t) with its band (variator).

matplotlib is optional and imported only when a figure is drawn. The
functions never change matplotlib's backend: they draw into the Axes you
pass (`ax=`, one per panel), into the Figure you pass (`fig=`, cleared first)
or into a new one from `matplotlib.pyplot.subplots`, and return the Figure;
save it with `fig.savefig(path)` (and `plt.close(fig)` in loops).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, TYPE_CHECKING

import numpy as np

from jaxnh.identify._fit import FitResult
from jaxnh.identify.estimates import Z95
from jaxnh.identify.parameters import resolve


if TYPE_CHECKING:  # matplotlib is optional (the plot extra): annotations only
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["plot_fit", "plot_ratio"]


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("plots need matplotlib (pip install matplotlib, or jaxnh[plot])") from None
    return plt


def _given_axes(ax, rows: int, what: str, name: str) -> tuple[Figure, list[Any]]:
    """The `rows` Axes of `ax=` (a sequence or array of Axes) as a list, and the Figure holding them."""
    axes = list(np.ravel(np.asarray(ax, dtype=object)))
    if len(axes) != rows:
        raise ValueError(f"{name}: ax= must be {rows} Axes ({what}); got {len(axes)}")
    if not all(hasattr(a, "plot") and hasattr(a, "figure") for a in axes):
        raise TypeError(f"{name}: ax= must be matplotlib Axes; got {', '.join(type(a).__name__ for a in axes)}")
    # the root Figure (an Axes in a SubFigure has the SubFigure as its .figure)
    figs = {id(a.figure.figure): a.figure.figure for a in axes}
    if len(figs) != 1:
        raise ValueError(f"{name}: the {rows} Axes of ax= must belong to one Figure, not {len(figs)}")
    return next(iter(figs.values())), axes


def _figure(fig, rows: int, figsize, height_ratios, ax=None, what: str = "", name: str = "") -> tuple[Figure, Any]:
    """`rows` stacked axes sharing x, in `fig` (cleared) or in a new pyplot figure; or the Axes of `ax=`
    as given (neither cleared nor shared)."""
    if ax is not None:
        if fig is not None:
            raise ValueError(f"{name}: pass fig= (a Figure to clear and fill) or ax= (Axes to draw into), not both")
        return _given_axes(ax, rows, what, name)
    kw: dict[str, Any] = dict(sharex=True, squeeze=False, gridspec_kw={"height_ratios": height_ratios})
    if fig is None:
        fig, ax = _pyplot().subplots(rows, 1, figsize=figsize, **kw)
    else:
        fig.clear()
        ax = fig.subplots(rows, 1, **kw)
    return fig, ax[:, 0]


def _finite_or_nan(x):
    x = np.asarray(x, dtype=float)
    return np.where(np.isfinite(x), x, np.nan)


def _check_path_arg(x, name):
    if isinstance(x, (str, bytes)) or hasattr(x, "__fspath__"):
        raise TypeError(
            f"{name}: the plot functions return a Figure and no longer take a file path; "
            f"use fig = {name}(...) then fig.savefig({str(x)!r})"
        )


def plot_fit(
    result: FitResult,
    record=None,
    *,
    fig: Figure | None = None,
    ax: Sequence[Axes] | np.ndarray | None = None,
    title: str = "",
    ylabel: str = "coordinate",
    input_label: str = "input",
) -> Figure:
    """Measured and fitted coordinates, the residuals per channel with ±2σ noise
    lines, and (given the record) the applied inputs.

    Arguments:
        result: a `FitResult` (any mechanism; units as the record's, rad for angles).
        record: the fitted `Record`, to draw its inputs (torques, N·m) below.
        fig: a matplotlib Figure to draw into (it is cleared); default a new one.
        ax: instead of `fig`, the matplotlib Axes to draw into, one per panel, top
            to bottom: 1 + `len(result.observe)` of them (the coordinates, then one
            residual panel per observed channel), plus one for the inputs when
            `record` has inputs (a list, or the array `plt.subplots` returns). They
            are drawn into as they are: not cleared, no shared x, no `tight_layout`.
        title: the top panel's title.
        ylabel, input_label: axis labels of the coordinates and the inputs
            (with units, e.g. "angle [rad]", "torque [N·m]").

    Returns:
        The matplotlib Figure (with `ax=`, the Figure that holds the Axes).
    """
    _check_path_arg(record, "plot_fit")
    if fig is None and ax is None:
        _pyplot()  # a clear ImportError first when matplotlib is missing
    k = len(result.observe)
    rows = 1 + k + (record is not None and bool(record.inputs))
    what = f"the coordinates, {k} residual panel{'s' * (k > 1)}" + (", the inputs" if rows > 1 + k else "")
    given = ax is not None
    figure, axs = _figure(fig, rows, (10, 2.4 * rows + 0.6), [1.6] + [1] * (rows - 1), ax, what, "plot_fit")
    t = result.t
    for i, c in enumerate(result.observe):
        axs[0].plot(t, result.measured[:, i], ".", ms=2, color=f"C{i}", alpha=0.5, label=f"{c} measured")
        axs[0].plot(t, result.fitted[:, i], "-", lw=1, color="k" if i == 0 else "0.35", label=f"{c} fit")
    axs[0].set(ylabel=ylabel, title=title or "measured (dots) and fitted simulation (lines)")
    axs[0].legend(loc="upper left", fontsize=8, ncol=2)
    for i, c in enumerate(result.observe):
        a = axs[1 + i]
        r = 1e3 * result.residuals[:, i]
        s = 1e3 * result.noise[c]
        a.plot(t, r, ".", ms=2, color=f"C{i}")
        for sign in (-2, 2):
            a.axhline(sign * s, color="0.5", lw=0.8, ls="--")
        a.axhline(0, color="k", lw=0.6)
        a.set(ylabel=f"{c} residual\n[×1e-3]")
        a.text(
            0.99,
            0.95,
            f"rms {1e3 * result.rms_by_channel[c]:.3f}e-3, noise σ {s:.3f}e-3 (dashed ±2σ)",
            transform=a.transAxes,
            ha="right",
            va="top",
            fontsize=8,
        )
    if rows > 1 + k and record is not None:
        a = axs[-1]
        for j, (name, v) in enumerate(record.inputs.items()):
            a.plot(record.t, v, color=f"C{j + 2}", label=name)
        a.axhline(0, color="k", lw=0.6)
        a.set(ylabel=input_label)
        a.legend(loc="upper left", fontsize=8)
    axs[-1].set(xlabel="t [s]")
    if not given:
        figure.tight_layout()
    return figure


def plot_ratio(
    result: FitResult,
    truth=None,
    n: int = 401,
    *,
    fig: Figure | None = None,
    ax: Sequence[Axes] | np.ndarray | None = None,
    name: str = "U21",
) -> Figure:
    """A fitted profile (the variator's U21(t)) with its knots and 95 % pointwise
    band; below, the band around zero (too narrow to see at full scale) and,
    if `truth` (a function of t) is given, the true minus the estimated law.

    Arguments:
        result: a `FitResult` whose free parameters include the spline profile `name`.
        truth: the true law, a function of t (s), or None.
        n: number of times at which the band is drawn.
        fig: a matplotlib Figure to draw into (it is cleared); default a new one.
        ax: instead of `fig`, the 2 matplotlib Axes to draw into: the profile
            with its band, then the deviations (a list, or the array `plt.subplots`
            returns). They are drawn into as they are: not cleared, no shared x,
            no `tight_layout`.
        name: the free profile to draw (default "U21").

    Returns:
        The matplotlib Figure (with `ax=`, the Figure that holds the Axes).
    """
    _check_path_arg(truth, "plot_ratio")
    if fig is None and ax is None:
        _pyplot()
    ts = np.linspace(result.t[0], result.t[-1], n)

    u, s = result.profile_band(name, ts)
    spline = resolve(result.params, name)
    kt = np.asarray(spline.knots)
    kv = np.asarray(result.estimates[name]["value"])
    ks = _finite_or_nan(result.estimates[name]["std"])
    s = _finite_or_nan(s)  # an undetermined (infinite) error is left out of the band, not drawn to infinity
    given = ax is not None
    figure, axs = _figure(fig, 2, (10, 6.2), [1.4, 1], ax, "the profile, then its deviations", "plot_ratio")
    axs[0].plot(ts, u, "C0", label=f"{name}(t) estimate")
    axs[0].fill_between(ts, u - Z95 * s, u + Z95 * s, color="C0", alpha=0.25, label="95 % band")
    axs[0].errorbar(kt, kv, yerr=Z95 * ks, fmt="o", color="C0", ms=4, capsize=3, label="spline knots")
    if truth is not None:
        axs[0].plot(ts, [truth(x) for x in ts], "k--", lw=1, label=f"true {name}")
    if name == "U21":
        axs[0].set(ylabel="U21 = r / rho", title="transmission ratio U21(t)")
    else:
        axs[0].set(ylabel=name, title=f"{name}(t)")
    axs[0].legend(fontsize=8)
    axs[1].fill_between(ts, -Z95 * s, Z95 * s, color="C0", alpha=0.25, label="95 % band of the estimate")
    axs[1].errorbar(kt, np.zeros_like(kt), yerr=Z95 * ks, fmt="o", color="C0", ms=3, capsize=3)
    if truth is not None:
        axs[1].plot(ts, np.array([truth(x) for x in ts]) - u, "k-", lw=1, label="true − estimate")
    axs[1].axhline(0, color="k", lw=0.6)
    axs[1].set(xlabel="t [s]", ylabel=f"{name} deviation")
    axs[1].legend(fontsize=8)
    if not given:
        figure.tight_layout()
    return figure
