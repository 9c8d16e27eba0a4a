"""Differentiable functions of time held in parameters.

A profile is an `eqx.Module` called as `profile(t)`; its array fields are
pytree leaves, so `jax.grad`/`jax.jacfwd` with respect to params reach them,
and its time derivatives come from autodiff (`profile.derivative(t)`). Units
are those of the quantity it describes (a ratio is dimensionless, a torque
N·m). Which leaves are meant to be estimated (the values, not the knot
times or the period) is said by `trainable(tree)`.

Kinds:

* `Constant` — one value.
* `PiecewiseLinear` — straight lines between knots (C⁰: an adaptive solver
  must shorten its steps at every kink).
* `CubicSpline` — the natural cubic spline through values at knots (C², so
  the solver's step control is undisturbed); the values are the trainable
  leaves. For a handful to a few dozen knots.
* `Fourier` — a truncated Fourier series.
* `SmoothStep` — a change from one value to another over a given width
  (tanh): a ratio shift, a clutch engaging. However steep, it is resolved:
  `simulate` ends a step at its middle and its edges (see below).
* `Sampled` — a measured signal (e.g. an applied torque) given at many
  sample times, interpolated by a C² cubic spline prepared once; an input,
  not something to fit.
* `Positive`, `Bounded` — map any profile into (0, ∞) or (lower, upper), so a
  physical limit holds for every value of the trainable leaves.

Breakpoints. An adaptive solver sees a law only at its stage times, so a
change much shorter than its steps (a 0.1 µs ratio step in a run whose
steps are 0.1 s) can fall between two stages and be stepped over without
any sign in the error estimate; a kink costs rejected steps. A profile
therefore declares the times where it has such features
(`Profile.breakpoints()`: the knots of `PiecewiseLinear` and of a linear
`Sampled`, the middle and edges of a `SmoothStep`), and `simulate` collects
them from the profiles in `params` and ends a step at each (diffrax's
`ClipStepSizeController`); from there the error control resolves the
feature. A steep feature written by hand inside `kinetic`, `constraints`
or `forces` is invisible to any step-size control: pass its time in
`simulate(..., step_ts=...)`, or write it as a `SmoothStep`.
"""

from __future__ import annotations

import abc
from typing import ClassVar, Optional

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxnh._base.types import PyTree


__all__ = [
    "Profile",
    "Constant",
    "Fourier",
    "SmoothStep",
    "PiecewiseLinear",
    "CubicSpline",
    "Sampled",
    "Positive",
    "Bounded",
    "trainable",
]


class Profile(eqx.Module):
    """A scalar function of time t (s).

    Subclasses name the fields an estimator may change in `trainable_fields`
    (the other array fields — knot times, a period — are held fixed).
    """

    trainable_fields: ClassVar[tuple] = ()

    @abc.abstractmethod
    def __call__(self, t) -> jax.Array:
        """Value at time t."""

    def breakpoints(self) -> Optional[jax.Array]:
        """Times (s, an array) at which `simulate` ends a step: kinks, and the middle and
        edges of changes steeper than the solver's steps would see; None when there are
        none (the default)."""
        return None

    def derivative(self, t: jax.typing.ArrayLike) -> jax.Array:
        """d/dt of the profile at t, by automatic differentiation."""
        return jax.jvp(self.__call__, (t,), (jnp.ones_like(t),))[1]


def trainable(tree: PyTree) -> PyTree:
    """A pytree of bools like `tree` marking the leaves that may be estimated.

    Inside a `Profile` only its `trainable_fields` are marked (recursively for
    wrapped profiles); outside profiles every inexact array is marked. Use it
    with `equinox.partition(tree, trainable(tree))`.
    """

    def mark(x):
        if isinstance(x, Profile):
            marks = jax.tree_util.tree_map(lambda _: False, x)
            for name in x.trainable_fields:
                marks = eqx.tree_at(lambda m: getattr(m, name), marks, trainable(getattr(x, name)))
            return marks
        return eqx.is_inexact_array(x)

    return jax.tree_util.tree_map(mark, tree, is_leaf=lambda x: isinstance(x, Profile))


def declared_breakpoints(params, dtype=None):
    """The breakpoints of all profiles in a params pytree, one sorted 1-D array (s), or
    None when no profile declares any. Batched profiles (under `vmap`) give batched
    arrays, each sorted."""
    found = [
        leaf.breakpoints()
        for leaf in jax.tree_util.tree_leaves(params, is_leaf=lambda x: isinstance(x, Profile))
        if isinstance(leaf, Profile)
    ]
    found = [jnp.ravel(jnp.asarray(b, dtype=dtype)) for b in found if b is not None]
    if not found:
        return None
    return jnp.sort(jnp.concatenate(found))


def _float(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _knots(name: str, knots, values):
    """Validate a knot grid and its values (concrete values only); return arrays."""
    knots, values = _float(knots), _float(values)
    if knots.ndim != 1 or knots.shape[0] < 2:
        raise ValueError(f"{name}: knots must be a 1-D array of at least 2 times (s); got shape {knots.shape}")
    if values.shape != knots.shape:
        raise ValueError(f"{name}: values must have the shape of knots, {knots.shape}; got {values.shape}")
    if not isinstance(knots, jax.core.Tracer):
        k = np.asarray(knots)
        if not np.all(np.isfinite(k)) or not np.all(np.diff(k) > 0):
            raise ValueError(f"{name}: knots must be finite and strictly increasing; got {k}")
    return knots, values


def _interval(knots, t):
    """Index i of the knot interval [knots[i], knots[i+1]] holding t (clipped to the ends)."""
    return jnp.clip(jnp.searchsorted(knots, t, side="right", method="scan_unrolled") - 1, 0, knots.shape[0] - 2)


class Constant(Profile):
    """A value that does not change with time."""

    value: Float[Array, ""]
    trainable_fields: ClassVar[tuple] = ("value",)

    def __init__(self, value: jax.typing.ArrayLike):
        self.value = jnp.asarray(value, dtype=jnp.result_type(float))

    def __call__(self, t):
        return self.value + 0 * t


class Fourier(Profile):
    """A truncated Fourier series of period `period` (s):

    `mean + Σ_k cos[k-1] cos(2π k t / period) + sin[k-1] sin(2π k t / period)`.

    The coefficients are trainable; the period is held fixed.
    """

    mean: Float[Array, ""]
    cos: Float[Array, " K"]
    sin: Float[Array, " K"]
    period: Float[Array, ""]
    trainable_fields: ClassVar[tuple] = ("mean", "cos", "sin")

    def __init__(
        self,
        mean: jax.typing.ArrayLike,
        cos: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...] = (),
        sin: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...] = (),
        period: jax.typing.ArrayLike = 1.0,
    ):
        f = jnp.result_type(float)
        self.mean = jnp.asarray(mean, dtype=f)
        c, s = jnp.atleast_1d(jnp.asarray(cos, dtype=f)), jnp.atleast_1d(jnp.asarray(sin, dtype=f))
        K = max(c.shape[0], s.shape[0])
        self.cos = jnp.zeros(K, f).at[: c.shape[0]].set(c)
        self.sin = jnp.zeros(K, f).at[: s.shape[0]].set(s)
        self.period = jnp.asarray(period, dtype=f)

    def __call__(self, t):
        k = jnp.arange(1, self.cos.shape[-1] + 1, dtype=self.mean.dtype)
        w = 2 * jnp.pi * k * t / self.period
        return self.mean + jnp.sum(self.cos * jnp.cos(w) + self.sin * jnp.sin(w))


class SmoothStep(Profile):
    """A smooth change from `before` to `after` centred at time `at` (s) over the
    time scale `width` (s): `before + (after − before) · (1 + tanh((t − at)/width)) / 2`.

    Units are those of the quantity (a ratio is dimensionless). 76 % of the
    change happens within `at ± width`, 99.5 % within `at ± 3 width`. Its
    breakpoints are `at − 3 width`, `at` and `at + 3 width`, so `simulate`
    resolves it however short it is compared with the rest of the motion.
    The two values are trainable; the time and the width are held fixed.
    """

    before: Float[Array, ""]
    after: Float[Array, ""]
    at: Float[Array, ""]
    width: Float[Array, ""]
    trainable_fields: ClassVar[tuple] = ("before", "after")

    def __init__(
        self,
        before: jax.typing.ArrayLike,
        after: jax.typing.ArrayLike,
        at: jax.typing.ArrayLike,
        width: jax.typing.ArrayLike,
    ):
        self.before, self.after, self.at, self.width = (_float(x) for x in (before, after, at, width))
        w = self.width
        if not isinstance(w, jax.core.Tracer) and not np.all(np.asarray(w) > 0):
            raise ValueError(f"SmoothStep: width must be > 0 (s); got {np.asarray(w)}")

    def __call__(self, t):
        return self.before + (self.after - self.before) * 0.5 * (1.0 + jnp.tanh((t - self.at) / self.width))

    def breakpoints(self) -> Optional[jax.Array]:
        return jnp.stack([self.at - 3 * self.width, self.at, self.at + 3 * self.width])


class PiecewiseLinear(Profile):
    """Straight lines through `values` at the knot times `knots` (s); constant
    beyond the first and last knot.

    Continuous but with a kink at every knot, where an adaptive ODE solver
    has to shorten its steps; prefer `CubicSpline` inside equations of motion.
    The values are trainable; the knots are held fixed.
    """

    knots: Float[Array, " n"]
    values: Float[Array, " n"]
    trainable_fields: ClassVar[tuple] = ("values",)

    def __init__(
        self,
        knots: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
        values: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
    ):
        self.knots, self.values = _knots("PiecewiseLinear", knots, values)

    def __call__(self, t):
        return _linear(self.knots, self.values, t)

    def breakpoints(self) -> Optional[jax.Array]:
        return self.knots


@jax.jit
def _linear(knots, values, t):
    """The piecewise-linear interpolant through (knots, values) at t, constant beyond the ends."""
    i = _interval(knots, t)
    t0, t1 = knots[i], knots[i + 1]
    s = jnp.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return values[i] + s * (values[i + 1] - values[i])


@jax.jit
def _natural_moments(knots, values):
    """Second derivatives m at the knots of the natural cubic spline (m[0] = m[-1] = 0).

    The continuity of the first derivative gives the tridiagonal system
    `h[i-1] m[i-1] + 2 (h[i-1] + h[i]) m[i] + h[i] m[i+1] = 6 (d[i] − d[i-1])`,
    `d[i] = (values[i+1] − values[i]) / h[i]`, solved by the Thomas algorithm
    written out for the static number of knots (a few dozen operations that
    XLA fuses into the caller; linear in the values, so autodiff is exact).
    Jitted so that its trace is made once per shape and reused wherever the
    spline is called (every stage of every traced solve, and their
    derivatives), instead of re-tracing its unrolled loop each time; XLA
    inlines it, so the compiled program is the same.
    """
    n = knots.shape[0]
    zero = jnp.zeros_like(values[0])
    if n <= 2:
        return jnp.zeros_like(values)
    h = knots[1:] - knots[:-1]
    d = (values[1:] - values[:-1]) / h
    # forward sweep over the interior unknowns m[1] .. m[n-2]
    cp, rp = [], []
    for i in range(1, n - 1):
        a = h[i - 1] if i > 1 else zero
        b = 2 * (h[i - 1] + h[i])
        r = 6 * (d[i] - d[i - 1])
        if i > 1:
            b = b - a * cp[-1]
            r = r - a * rp[-1]
        cp.append(h[i] / b)
        rp.append(r / b)
    m = [zero] * n
    m[n - 2] = rp[-1]
    for j in range(n - 3, 0, -1):
        m[j] = rp[j - 1] - cp[j - 1] * m[j + 1]
    return jnp.stack(m)


@jax.jit
def _cubic(knots, values, moments, t):
    """Evaluate the cubic spline with given second derivatives at the knots;
    extended by straight lines (the end slopes) beyond the first and last knot."""
    tc = jnp.clip(t, knots[0], knots[-1])
    i = _interval(knots, tc)
    t0, t1 = knots[i], knots[i + 1]
    h = t1 - t0
    y0, y1, m0, m1 = values[i], values[i + 1], moments[i], moments[i + 1]
    a, b = (t1 - tc) / h, (tc - t0) / h
    inside = a * y0 + b * y1 + ((a**3 - a) * m0 + (b**3 - b) * m1) * h**2 / 6
    slope = (y1 - y0) / h + h * ((1 - 3 * a**2) * m0 + (3 * b**2 - 1) * m1) / 6
    return inside + slope * (t - tc)


class CubicSpline(Profile):
    """The natural cubic spline through `values` at the knot times `knots` (s).

    Twice continuously differentiable (C²), so an adaptive solver integrating
    equations of motion that contain it keeps its step; zero second
    derivative at the end knots, continued by straight lines beyond them
    (still C²). The value at each knot is a trainable leaf and the spline is
    linear in them; the knots are held fixed. Its second derivatives are
    solved for on every call (O(n) operations), which suits up to a few dozen
    knots; for a long measured signal use `Sampled`.
    """

    knots: Float[Array, " n"]
    values: Float[Array, " n"]
    trainable_fields: ClassVar[tuple] = ("values",)

    def __init__(
        self,
        knots: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
        values: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
    ):
        self.knots, self.values = _knots("CubicSpline", knots, values)

    def __call__(self, t):
        return _cubic(self.knots, self.values, _natural_moments(self.knots, self.values), t)


class Sampled(Profile):
    """A measured signal, e.g. an applied torque (N·m), given at sample times
    `ts` (s) and interpolated between them.

    `kind="cubic"` (default): the natural cubic spline through the samples
    (C², continued by straight lines beyond the ends); its second derivatives
    are computed once here, with NumPy, so evaluation costs a binary search
    and a few operations however long the record. `kind="linear"`: straight
    lines (kinks at every sample make an adaptive solver take small steps).
    A known input, not something to fit: it has no trainable leaves.
    """

    knots: Float[Array, " n"]
    values: Float[Array, " n"]
    moments: Float[Array, " n"]
    kind: str = eqx.field(static=True)

    def __init__(
        self,
        ts: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
        values: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
        kind: str = "cubic",
    ):
        if kind not in ("cubic", "linear"):
            raise ValueError(f"Sampled: kind must be 'cubic' or 'linear'; got {kind!r}")
        knots, vals = _knots("Sampled", ts, values)
        if isinstance(knots, jax.core.Tracer) or isinstance(vals, jax.core.Tracer):
            raise ValueError("Sampled: ts and values must be concrete (the spline is prepared with NumPy)")
        if not np.all(np.isfinite(np.asarray(vals))):
            bad = np.nonzero(~np.isfinite(np.asarray(vals)))[0]
            raise ValueError(f"Sampled: values must be finite; non-finite at samples {bad}")
        self.knots, self.values, self.kind = knots, vals, kind
        m = np.zeros(knots.shape[0]) if kind == "linear" else _natural_moments_np(np.asarray(knots), np.asarray(vals))
        self.moments = jnp.asarray(m, dtype=vals.dtype)

    def __call__(self, t):
        if self.kind == "linear":
            return _linear(self.knots, self.values, t)
        return _cubic(self.knots, self.values, self.moments, t)

    def breakpoints(self) -> Optional[jax.Array]:
        return self.knots if self.kind == "linear" else None


def _natural_moments_np(x, y):
    """Natural-spline second derivatives by the tridiagonal (Thomas) solve, in NumPy.

    The system is strictly diagonally dominant (diagonal 2 (h_i + h_{i+1}) against
    off-diagonals h_i, h_{i+1}), so elimination without pivoting is stable."""
    n = x.shape[0]
    m = np.zeros(n)
    if n <= 2:
        return m
    h = np.diff(x)
    d = np.diff(y) / h
    diag = 2 * (h[:-1] + h[1:])
    off = h[1:-1]  # sub- and super-diagonal (symmetric)
    rhs = 6 * np.diff(d)
    k = n - 2
    c = np.zeros(k)
    r = np.zeros(k)
    c[0], r[0] = (off[0] / diag[0] if k > 1 else 0.0), rhs[0] / diag[0]
    for i in range(1, k):
        denom = diag[i] - off[i - 1] * c[i - 1]
        c[i] = off[i] / denom if i < k - 1 else 0.0
        r[i] = (rhs[i] - off[i - 1] * r[i - 1]) / denom
    for i in range(k - 2, -1, -1):
        r[i] -= c[i] * r[i + 1]
    m[1:-1] = r
    return m


class Positive(Profile):
    """`scale · exp(inner(t))`: a law that stays strictly positive (an inertia,
    a transmission ratio) for any values of the inner profile's leaves.

    Units are those of `scale`; `inner` is dimensionless (the logarithm of
    the value in units of `scale`). `Positive.of(profile)` builds one whose
    inner profile holds the logarithms of a spline's or constant's values.
    """

    inner: Profile
    scale: Float[Array, ""]
    trainable_fields: ClassVar[tuple] = ("inner",)

    def __init__(self, inner: Profile, scale: jax.typing.ArrayLike = 1.0):
        if not isinstance(inner, Profile):
            raise TypeError(f"Positive: inner must be a jaxnh Profile; got {type(inner).__name__}")
        self.inner, self.scale = inner, _float(scale)

    def __call__(self, t):
        return self.scale * jnp.exp(self.inner(t))

    def breakpoints(self) -> Optional[jax.Array]:
        return self.inner.breakpoints()

    @classmethod
    def of(cls, profile: Profile) -> "Positive":
        """The positive profile whose inner profile is `profile` with the
        logarithm of its trainable values (for `Constant`, `PiecewiseLinear`,
        `CubicSpline`): equal to `profile` at its knots."""
        for name in ("value", "values"):
            if name in getattr(profile, "trainable_fields", ()):
                v = np.asarray(getattr(profile, name))
                if np.any(v <= 0):
                    raise ValueError(f"Positive.of: the {name} of the profile must be > 0; got {v}")
                return cls(eqx.tree_at(lambda p: getattr(p, name), profile, jnp.log(getattr(profile, name))))
        raise TypeError(
            f"Positive.of: expected a Constant, PiecewiseLinear or CubicSpline; got {type(profile).__name__}"
        )


class Bounded(Profile):
    """`lower + (upper − lower) · sigmoid(inner(t))`: a law that stays strictly
    inside (lower, upper) for any inner profile — e.g. a transmission ratio
    the variator's geometry keeps within [U_min, U_max].

    Units are those of `lower`/`upper`; `inner` is dimensionless (0 maps to
    the middle of the interval). `Bounded.inverse` gives the inner value of a
    target value.
    """

    inner: Profile
    lower: Float[Array, ""]
    upper: Float[Array, ""]
    trainable_fields: ClassVar[tuple] = ("inner",)

    def __init__(self, inner: Profile, lower: jax.typing.ArrayLike, upper: jax.typing.ArrayLike):
        if not isinstance(inner, Profile):
            raise TypeError(f"Bounded: inner must be a jaxnh Profile; got {type(inner).__name__}")
        self.inner, self.lower, self.upper = inner, _float(lower), _float(upper)
        if not isinstance(self.lower, jax.core.Tracer) and not isinstance(self.upper, jax.core.Tracer):
            if not np.all(np.asarray(self.upper) > np.asarray(self.lower)):
                raise ValueError(f"Bounded: need upper > lower; got lower={self.lower}, upper={self.upper}")

    def __call__(self, t):
        return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(self.inner(t))

    def breakpoints(self) -> Optional[jax.Array]:
        return self.inner.breakpoints()

    @staticmethod
    def inverse(value: jax.typing.ArrayLike, lower: float | jax.Array, upper: float | jax.Array) -> jax.Array:
        """The inner value that maps to `value` (strictly between the bounds)."""
        s = (jnp.asarray(value) - lower) / (upper - lower)
        return jnp.log(s) - jnp.log1p(-s)
