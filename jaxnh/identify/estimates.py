"""Estimates with standard errors: what a fit reports, and what an experiment design predicts.

`Estimates` holds, for every unknown of a `Problem` (the free parameters, then
the initial state), its value in natural units, its standard error and
covariance, the identifiability report, and what it takes to propagate the
covariance to a derived quantity (`Estimates.band`). A fit's `FitResult` and
a design's `Prediction` are both `Estimates`: `estimate_fields` builds the
shared part from θ and the statistics of the weighted Jacobian
(`jaxnh.identify.problem.statistics_host`), and `Estimates.table_lines`
prints it as one table.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._base.compile import one_shot_jit
from jaxnh._base.linalg import value_and_jacfwd
from jaxnh.identify.diagnostics import analyse, Identifiability
from jaxnh.identify.parameters import resolve
from jaxnh.identify.problem import Problem


__all__ = ["Estimates", "estimate_fields", "estimate_band", "Z95"]

Z95 = 1.959963984540054  # two-sided 95 % normal quantile


@dataclasses.dataclass
class Estimates:
    """Values and standard errors of the unknowns θ of a `Problem`.

    Attributes:
        labels: label of every unknown (free parameters, then the initial state).
        values: values in natural units (the parameter's own; exp of θ for
            positive parameters, which enter θ as logarithms).
        std: standard errors, natural units (inf for a combination the data
            do not determine).
        covariance: covariance of `values` (natural units; linearised for
            log-parametrised ones).
        identifiability: the `Identifiability` report (undetermined
            combinations named in words, e.g. "only J1/J2 is determined").
        estimates: {name: {"value", "std"}} for every free parameter (scalars
            as floats, profiles' trainable values as arrays) and for the
            initial state (entries like "phi1(t0)", "phi1'(t0)"); units of
            the parameter.
        problem, theta, cov_theta, null_directions: the `Problem`, θ (log
            units for positive parameters), the covariance of θ and the
            undetermined directions of θ (rows), for `band`.
    """

    labels: tuple
    values: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    identifiability: Identifiability
    estimates: dict
    problem: Problem = dataclasses.field(repr=False)
    theta: np.ndarray = dataclasses.field(repr=False)
    cov_theta: np.ndarray = dataclasses.field(repr=False)
    null_directions: np.ndarray = dataclasses.field(repr=False)

    @property
    def identifiable(self) -> bool:
        """Whether every free parameter is determined (by the data of a fit, by a predicted experiment)."""
        return self.identifiability.identifiable

    def band(
        self, fn: object, ts: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Value and standard error of a derived quantity `fn(params, t)` at times ts.

        The standard error is the linearised (delta-method) propagation of
        the covariance; it is inf where `fn` depends on a combination the
        data do not determine. Example: `result.band(lambda p, t: p.U21(t), ts)`
        (pass the same function object again to reuse its compilation).

        Returns:
            `(value, std)`, NumPy arrays like ts.
        """
        return estimate_band(self.problem, self.theta, self.cov_theta, self.null_directions, fn, ts)

    def profile_band(
        self, name: str, ts: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Value and standard error of the free profile `name` (e.g. "U21") at times ts."""
        return self.band(_ProfileAt(name), ts)

    def table_lines(
        self,
        truth: Optional[dict] = None,
        *,
        heads: tuple = ("estimate", "± std error"),
        units: Optional[dict] = None,
    ) -> list:
        """The table of values ± standard errors, one line per unknown, with relative errors and 95 % intervals.

        A profile's entries are labelled by their knot times when it has knots
        ("U21(1.5 s)"). `truth`: {name: true value} for scalars and
        {"<name>_values": array} for profiles, adds the true value and whether
        it lies in the interval. `units`: {name: unit text} shown after the
        name (e.g. {"J1": " kg·m²"}). `heads`: the titles of the value and
        standard-error columns.
        """
        units = units or {}
        head = f"  {'parameter':<14}{heads[0]:>13}{heads[1]:>13}{'rel.':>9}   {'95 % interval':<27}"
        lines = [(head + (f"{'true':>10}  inside" if truth is not None else "")).rstrip()]
        free = tuple(self.problem.par.names)
        for k in free:
            v, s = self.estimates[k]["value"], self.estimates[k]["std"]
            if np.ndim(v) == 0:
                lines.append(_row(k + units.get(k, ""), v, s, None if truth is None else truth.get(k)))
                continue
            try:
                knots = np.asarray(resolve(self.problem.par.params, k).knots)
            except (AttributeError, ValueError):
                knots = None
            tv = truth.get(f"{k}_values") if truth is not None else None
            for i, (vi, si) in enumerate(zip(np.asarray(v).ravel(), np.asarray(s).ravel())):
                lab = f"{k}({knots[i]:.3g} s)" if knots is not None and knots.shape == np.shape(v) else f"{k}[{i}]"
                lines.append(_row(lab, vi, si, None if tv is None else tv[i]))
        for k, e in self.estimates.items():
            if k not in free:
                lines.append(_row(k, e["value"], e["std"]))
        return lines

    def identifiability_lines(self) -> list:
        """The identifiability report in words (indented lines for the tables)."""
        ident = self.identifiability
        if ident.messages:
            return ["  " + m for m in ident.messages]
        return [f"  all parameters identifiable (condition number of the scaled Jacobian {ident.condition:.3g})"]


def _fmt(x, spec) -> str:
    return format(x, spec) if np.isfinite(x) else "n/a"


def _row(name, v, s, true=None) -> str:
    v, s = float(v), float(s)
    rel = f"{s / abs(v):8.3%}" if np.isfinite(s) and np.isfinite(v) and v != 0 else "     n/a"
    ci = f"[{v - Z95 * s:.6g}, {v + Z95 * s:.6g}]" if np.isfinite(s) and np.isfinite(v) else "undetermined"
    line = f"  {name:<14}{_fmt(v, '>13.6g'):>13}{_fmt(s, '>13.3g'):>13}{rel:>9}   {ci:<27}"
    if true is not None:
        inside = bool(abs(true - v) <= Z95 * s)
        line += f"{true:>10.6g}  {'yes' if inside else 'NO'}"
    return line.rstrip()


def estimate_fields(problem: Problem, labels, theta, stats: dict, rank_tol: float) -> dict:
    """The fields of `Estimates` at θ, from `statistics_host` of the weighted Jacobian there.

    Values and standard errors are converted to natural units (the standard
    error of a positive parameter, estimated as a logarithm, is the relative
    one times the value), and the identifiability report comes from `analyse`.
    """
    par = problem.par
    theta = np.asarray(theta)
    log = np.concatenate([par.log_mask(), np.zeros(theta.shape[0] - par.size, bool)])
    values = np.where(log, np.exp(theta), theta)
    D = np.where(log, values, 1.0)
    std = np.where(np.isfinite(stats["std"]), stats["std"] * D, np.inf)
    estimates = {}
    for name, sl in par.slices().items():
        v, s = values[sl], std[sl]
        scalar = par.shapes[par.names.index(name)] == ((),)
        estimates[name] = {"value": float(v[0]) if scalar else v, "std": float(s[0]) if scalar else s}
    for j in range(par.size, theta.shape[0]):
        estimates[labels[j]] = {"value": float(values[j]), "std": float(std[j])}
    null = stats["Vt"][~(stats["sv"] > rank_tol)] / np.where(stats["colnorm"] > 0, stats["colnorm"], 1.0)
    return dict(
        labels=labels,
        values=values,
        std=std,
        covariance=stats["cov"] * np.outer(D, D),
        identifiability=analyse(stats, labels, log, rank_tol),
        estimates=estimates,
        problem=problem,
        theta=theta,
        cov_theta=stats["cov"],
        null_directions=null,
    )


def estimate_band(problem: Problem, theta, cov_theta, null_directions, fn, ts):
    """`(value, std)` of `fn(params, t)` at times ts for the estimate θ with covariance `cov_theta`
    (`Estimates.band`)."""
    ts = jnp.asarray(ts, dtype=jnp.result_type(float))
    P = problem.par.size
    val, G = (np.asarray(x) for x in _band_jacobian(problem.par, jnp.asarray(theta[:P]), ts.reshape(-1), fn))
    C = cov_theta[:P, :P]
    std = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", G, C, G), 0.0))
    if null_directions.size:
        leak = np.abs(G @ null_directions[:, :P].T)
        scale = np.maximum(np.abs(G).sum(axis=1), np.finfo(float).tiny)
        std = np.where(np.any(leak > 1e-6 * scale[:, None], axis=1), np.inf, std)
    return val.reshape(np.shape(ts)), std.reshape(np.shape(ts))


class _ProfileAt(eqx.Module):
    """`params ↦ profile name at t`, hashable by name (so its band compiles once)."""

    name: str = eqx.field(static=True)

    def __call__(self, params, t):
        return resolve(params, self.name)(t)


@one_shot_jit
def _band_jacobian(par, theta, ts, fn):
    def g(th):
        p = par.unpack(th)
        return jax.vmap(lambda t: fn(p, t))(ts)

    return value_and_jacfwd(g, theta)
