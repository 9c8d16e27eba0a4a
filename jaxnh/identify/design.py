"""Gradient-based design: bounded laws of time, an optax loop, a gradient check.

A design study chooses parameters — often a whole law of time such as the
variator's ratio U21(t) — to minimise an objective computed from `simulate`
(energy drawn by a motor, time to reach a speed, a peak contact force). The
gradient comes from differentiating through the solver (diffrax's
`RecursiveCheckpointAdjoint`, the default of `simulate`).

* `Chebyshev`: a smooth, non-periodic law on a time window, for the inside of
  a bounded profile.
* `Bounded` (from `jaxnh.profiles`, re-exported): maps any profile into an
  interval (lower, upper) with a sigmoid, so physical limits (a ratio the
  mechanism can reach) hold for every value of the trainable coefficients
  and the optimiser needs no projection.
* `optimize`: an optax loop over the inexact-array leaves of a pytree
  (reverse- or forward-mode gradients); `multistart` runs it from several
  starts and keeps the best acceptable result.
* `fd_gradient`: central differences over the same leaves, to check a
  gradient obtained by autodiff.

Caution: a gradient through an adaptive solve is the exact derivative of the
*discrete* solution along the steps the controller chose for the current
parameters. Where those steps are too long to resolve the direction being
differentiated, it can be far off. The typical case is a law that does not
vary yet (a constant ratio): the motion is then a low-degree polynomial in t
that a Runge–Kutta method integrates exactly in a handful of long steps, and
the gradient with respect to high-order coefficients of the law is wrong
there (on the variator start-up of `examples/optimal_ratio.py`: 4 steps in
4 s, a derivative of 2.8 against 0.006 by central differences). It is right
again once the law varies and the steps shorten. Check with `fd_gradient`
at the point of interest; start optimisations from a varying law or accept
that the first, normalised Adam step only moves off the degenerate point.
"""

from __future__ import annotations

from typing import Any, Callable, ClassVar, Optional, Sequence

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from jaxnh._base.compile import solve_jit
from jaxnh._base.types import PyTree
from jaxnh._model.profiles import Bounded, Profile, trainable as trainable_leaves  # noqa: F401  (Bounded re-exported)


__all__ = ["Chebyshev", "Bounded", "optimize", "multistart", "fd_gradient"]


class Chebyshev(Profile):
    """`Σ_k coef[k] T_k(x)` with `x = 2 (t − t0) / (t1 − t0) − 1` (Chebyshev
    polynomials of the first kind), a smooth law on the window [t0, t1] s.

    Its value has the units of the coefficients. Outside the window the
    polynomial is extrapolated (keep report times inside it). The
    coefficients are the trainable leaves (`trainable_fields`); the window
    t0, t1 is held fixed by `optimize` and `fd_gradient` by default.
    """

    coef: Float[Array, " K"]
    t0: Float[Array, ""]
    t1: Float[Array, ""]
    trainable_fields: ClassVar[tuple] = ("coef",)

    def __init__(
        self,
        coef: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        t0: jax.typing.ArrayLike = 0.0,
        t1: jax.typing.ArrayLike = 1.0,
    ):
        f = jnp.result_type(float)
        self.coef = jnp.atleast_1d(jnp.asarray(coef, dtype=f))
        if self.coef.ndim != 1 or self.coef.shape[0] < 1:
            raise ValueError(f"Chebyshev: coef must be a non-empty 1-D array; got shape {self.coef.shape}")
        self.t0 = jnp.asarray(t0, dtype=f)
        self.t1 = jnp.asarray(t1, dtype=f)
        if not isinstance(self.t0, jax.core.Tracer) and not isinstance(self.t1, jax.core.Tracer):
            if not np.all(np.asarray(self.t1) > np.asarray(self.t0)):
                raise ValueError(f"Chebyshev: need t1 > t0; got t0={self.t0}, t1={self.t1}")

    def __call__(self, t):
        x = 2 * (t - self.t0) / (self.t1 - self.t0) - 1
        # Clenshaw recurrence: b_k = c_k + 2x b_{k+1} − b_{k+2}; value = c_0 + x b_1 − b_2.
        c = self.coef
        b1 = jnp.zeros_like(x * c[0])
        b2 = jnp.zeros_like(b1)
        for k in range(c.shape[0] - 1, 0, -1):
            b1, b2 = c[k] + 2 * x * b1 - b2, b1
        return c[0] + x * b1 - b2


def optimize(
    loss: Callable[[Any], Any],
    params: PyTree,
    *,
    optimizer: Optional[optax.GradientTransformation] = None,
    steps: int = 200,
    trainable: Any = None,
    callback: Optional[Callable[[int, float, Any], Any]] = None,
    gradient: str = "reverse",
) -> tuple[PyTree, np.ndarray]:
    """Minimise `loss(params)` with optax, differentiating through `simulate`.

    Arguments:
        loss: scalar function of the params pytree (may call `simulate`).
        params: initial pytree (e.g. a `VariatorParams` whose U21 is a
            `Bounded(Chebyshev(...), lo, hi)`).
        optimizer: an optax transformation (default `optax.adam(0.05)`).
        steps: number of updates.
        trainable: a pytree of bools with the structure of `params` (as for
            `equinox.partition`) marking the leaves to change; default
            `jaxnh.profiles.trainable(params)`: inside profiles only their
            `trainable_fields` (values, coefficients — not knot times,
            windows or bounds), elsewhere every inexact array. The rest are
            held fixed.
        callback: `callback(step, loss_value, params)` after every step.
        gradient: "reverse" (`jax.grad`, default) or "forward" (`jax.jacfwd`
            over the trainable entries: one tangent per design variable; for
            losses that are themselves built from forward-mode derivatives,
            e.g. a Fisher information, where reverse mode is not available).

    Returns:
        `(best_params, history)`: the params with the lowest loss seen
        (evaluated before each update, and after the last) and the loss
        values as a NumPy array of length `steps + 1`.

    The compiled update is cached on (loss, optimizer, the structure of
    params): calling `optimize` again with the same `loss` and `optimizer`
    objects (e.g. from several starts) does not compile again.
    """
    if int(steps) != steps or steps < 0:
        raise ValueError(f"optimize: steps must be a non-negative integer; got {steps!r}")
    if gradient not in ("reverse", "forward"):
        raise ValueError(f"optimize: gradient must be 'reverse' or 'forward'; got {gradient!r}")
    optimizer = optax.adam(0.05) if optimizer is None else optimizer
    spec = trainable_leaves(params) if trainable is None else trainable
    theta, rest = eqx.partition(params, spec)
    opt_state = optimizer.init(theta)

    history = []
    best, best_value = theta, np.inf
    value = np.inf
    for k in range(int(steps)):
        new, opt_state, value = _optimize_step(loss, optimizer, gradient, theta, rest, opt_state)
        value = float(value)
        if not np.isfinite(value):
            raise FloatingPointError(
                f"optimize: loss is {value} at step {k}; lower the learning rate or check the model"
            )
        history.append(value)
        if value < best_value:
            best, best_value = theta, value
        if callback is not None:
            callback(k, value, eqx.combine(theta, rest))
        theta = new
    # the last value by the step's program (its update unused): no second program to compile
    value = float(_optimize_step(loss, optimizer, gradient, theta, rest, opt_state)[2])
    history.append(value)
    if value < best_value:
        best = theta
    return eqx.combine(best, rest), np.asarray(history)


def _forward_value_and_grad(f, theta):
    """Value and gradient of the scalar f over the array leaves of theta by forward mode (jacfwd)."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    sizes = [int(np.prod(np.shape(x))) for x in leaves]
    flat = jnp.concatenate([jnp.ravel(x) for x in leaves])

    def g(v):
        parts, i = [], 0
        for x, n in zip(leaves, sizes):
            parts.append(v[i : i + n].reshape(jnp.shape(x)).astype(x.dtype))
            i += n
        out = f(jax.tree_util.tree_unflatten(treedef, parts))
        return out, out

    grad, value = jax.jacfwd(g, has_aux=True)(flat)
    parts, i = [], 0
    for x, n in zip(leaves, sizes):
        parts.append(grad[i : i + n].reshape(jnp.shape(x)).astype(x.dtype))
        i += n
    return value, jax.tree_util.tree_unflatten(treedef, parts)


@solve_jit
def _optimize_step(loss, optimizer, gradient, theta, rest, opt_state):
    def f(th):
        return loss(eqx.combine(th, rest))

    if gradient == "forward":
        value, g = _forward_value_and_grad(f, theta)
    else:
        value, g = eqx.filter_value_and_grad(f)(theta)
    updates, opt_state = optimizer.update(g, opt_state, theta)
    return eqx.apply_updates(theta, updates), opt_state, value


def multistart(
    loss: Callable[[Any], Any],
    starts: Sequence[PyTree],
    *,
    accept: Optional[Callable[[Any], Any]] = None,
    learning_rate: float = 0.05,
    optimizer: Optional[optax.GradientTransformation] = None,
    progress: bool = False,
    **kwargs: Any,
) -> tuple[PyTree, list[dict[str, Any]], int]:
    """`optimize` from several starting pytrees; keep the best acceptable result.

    Arguments:
        loss: scalar function of the params pytree.
        starts: a list of starting params pytrees (same structure).
        accept: `accept(params) -> (ok, evaluation)` judging a result (e.g.
            "every constraint holds"); default: every result is acceptable and
            its evaluation is {"value": loss}. Results that are not accepted
            are kept only when none is.
        learning_rate: step size of the default optimiser `optax.adam`.
        optimizer: an optax transformation (overrides `learning_rate`).
        progress: print one line per start.
        **kwargs: passed to `optimize` (`steps`, `trainable`, `gradient`).

    Returns:
        `(best_params, runs, index)`: the best result (lowest
        evaluation["value"] among accepted ones), a list of dicts per start
        ("params", "history", "accepted", "evaluation", "error" for a start
        whose loss became non-finite) and the index of the best. One
        compilation serves every start.
    """
    starts = list(starts)
    if not starts:
        raise ValueError("multistart: give at least one starting pytree")
    optimizer = optax.adam(learning_rate) if optimizer is None else optimizer
    runs = []
    for i, p0 in enumerate(starts):
        try:
            p, hist = optimize(loss, p0, optimizer=optimizer, **kwargs)
        except FloatingPointError as e:
            runs.append(
                {
                    "params": p0,
                    "history": np.asarray([]),
                    "accepted": False,
                    "evaluation": {"value": float("inf")},
                    "error": str(e),
                }
            )
            if progress:
                print(f"  start {i}: failed ({e})", flush=True)
            continue
        if accept is None:
            ok, ev = True, {"value": float(np.min(hist))}  # optimize returns the params of the lowest loss
        else:
            ok, ev = accept(p)
        runs.append({"params": p, "history": hist, "accepted": bool(ok), "evaluation": ev})
        if progress:
            more = ", ".join(f"{k} {v:.4g}" for k, v in ev.items() if k != "value" and isinstance(v, float))
            print(
                f"  start {i}: loss {hist[0]:.5g} -> {hist[-1]:.5g}, value {ev['value']:.5g}"
                f"{' (' + more + ')' if more else ''}, {'acceptable' if ok else 'NOT acceptable'}",
                flush=True,
            )
    pool = [i for i, r in enumerate(runs) if r["accepted"]] or list(range(len(runs)))
    k = min(pool, key=lambda i: runs[i]["evaluation"]["value"])
    return runs[k]["params"], runs, k


def fd_gradient(
    f: Callable[[Any], Any],
    params: PyTree,
    h: Optional[float] = None,
    trainable: Any = None,
    scale: Optional[float] = None,
) -> PyTree:
    """Central-difference gradient of the scalar `f` over the trainable leaves of `params`, to
    check a gradient obtained by automatic differentiation.

    Each entry x is moved by ±s and `∂f/∂x ≈ (f(x + s) − f(x − s)) / 2s`. The error of that
    quotient has two parts: truncation, `s² |f'''| / 6`, and rounding of the two values of f,
    `δ |f| / s` (δ the relative noise of f: the machine epsilon, or the tolerance of a solve
    inside f). The step is relative to the entry, `s = h · max(|x|, floor)`, so the result
    does not depend on the units of x: a function that varies on the scale of |x| itself
    (`1/x`, `log x` at x = 1e-8) is differenced on a fraction h of it, and its relative error
    is of order h² + δ/h. The floor is 0 (a purely relative step) unless rounding drowns the
    difference, `|f(x + s) − f(x − s)| < h |f|`, which happens where f varies on a scale L much
    longer than |x| (`exp x` at x = 1e-12, a loss 1e10 + g(x)): the step then grows towards
    `h · L` (at most ×1e4 per trial, eight trials), and stops growing where the difference no
    longer grows in proportion to the step (a longer step leaves the range where f is close to
    linear, or crosses a singularity) or f is not finite. An entry at exactly 0 starts from the
    step `h · scale`. Then the quotient at s is compared with the one at s/2 (truncation errors
    c s² and c s²/4), and the step is shortened until they agree: where f varies on a scale
    shorter than |x| (`cos x` at x = 1e8) the relative step is too long.

    Arguments:
        f: scalar function of the params pytree (may call `simulate`).
        params: the point, a pytree.
        h: the relative step. Default: `eps^(1/3)` of the entry's dtype (6.1e-6 in float64,
            4.9e-3 in float32), which balances truncation and rounding of f at machine
            precision, for an error of order `eps^(2/3)` (3.7e-11 in float64) of
            `|∂f/∂x| + |f| / L`; the quotients at s and s/2 must agree to that, or a ValueError
            says so. When f is noisier than rounding — a solve at tolerance rtol — pass
            `h ≈ rtol^(1/3)`: the same steps are tried, and where the quotients do not agree
            to h² the one whose two quotients agree best is returned (the caller judges it:
            its error is of the order of that disagreement).
        trainable: a pytree of bools marking the leaves to differentiate (default as in
            `optimize`: the trainable leaves of profiles, every other inexact array).
        scale: the typical magnitude of an entry, in its units: the floor of the step for
            entries at 0 and the largest floor rounding may call for (default: unbounded, and 1
            for entries at 0).

    Returns:
        A pytree like `params` with `∂f/∂x` at the differentiated leaves (units of f per unit
        of x) and None at the others (as `equinox.filter_grad` does). Costs four evaluations per
        entry (at x ± s and x ± s/2) when the relative step suffices, at most 48 when it must
        grow or shrink: meant for checking `jax.grad` on a handful of design variables.

    Raises:
        ValueError: `h` or `scale` not a positive finite number; f not finite at `params` or
            at x ± s for every step tried; with the default h, quotients that do not settle.
    """
    if h is not None and not (np.ndim(h) == 0 and np.isreal(h) and 0 < float(h) < 1):
        raise ValueError(f"fd_gradient: h (the relative step) must be a number in (0, 1); got {h!r}")
    if scale is not None and not (np.ndim(scale) == 0 and np.isreal(scale) and 0 < float(scale) < np.inf):
        raise ValueError(f"fd_gradient: scale (an entry's typical magnitude) must be a positive number; got {scale!r}")
    scale = None if scale is None else float(scale)
    spec = trainable_leaves(params) if trainable is None else trainable
    theta, rest = eqx.partition(params, spec)
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    f_flat = jax.jit(lambda ls: f(eqx.combine(jax.tree_util.tree_unflatten(treedef, ls), rest)))
    f0 = float(f_flat(leaves))
    if not np.isfinite(f0):
        raise ValueError(f"fd_gradient: f(params) = {f0}; central differences need a finite value at params")
    grads = []
    for i, leaf in enumerate(leaves):
        dtype = np.dtype(jnp.result_type(leaf))
        if not np.issubdtype(dtype, np.floating):
            raise ValueError(
                f"fd_gradient: a leaf marked for differentiation has dtype {dtype.name}; central differences "
                "need real floating-point leaves: mark only those in `trainable`"
            )
        x = np.asarray(leaf, dtype=dtype)
        g = np.zeros(x.shape, dtype=np.float64)
        rel = float(np.finfo(dtype).eps) ** (1 / 3) if h is None else float(h)
        for j in np.ndindex(x.shape):

            def value(u, j=j):
                trial = list(leaves)
                xp = x.copy()
                xp[j] = u
                trial[i] = jnp.asarray(xp, dtype=dtype)
                return float(f_flat(trial))

            g[j] = _central_difference(value, x[j], rel, scale, f0, strict=h is None)
        grads.append(jnp.asarray(g, dtype=dtype))
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, grads), jax.tree_util.tree_map(lambda _: None, rest))


_FD_GROWTH = 1e4  # the largest factor by which one trial lengthens the step (rounding)
_FD_TRIALS = 8  # trials of each kind: from eps^(1/3)·1e-12 to ~1 takes four lengthenings


def _central_difference(
    value: Callable[[Any], float], x: Any, rel: float, scale: Optional[float], f0: float, strict: bool
) -> float:
    """∂f/∂x for one entry x (a NumPy scalar of the leaf's dtype) by central differences with the
    step `fd_gradient` describes. `value(u)` is f with the entry set to u.

    The quotients' denominators are the differences of the arguments as rounded to the dtype, so
    they are exact. First the step is lengthened while rounding drowns the difference; then the
    quotient at s is compared with the one at s/2, whose truncation errors are c s² and c s²/4:
    they must agree to `h²` of their size plus what rounding (relative noise `h³` of f) can make
    of them, else the step is shortened for the truncation estimate to meet it."""
    dtype = np.asarray(x).dtype
    noise = rel**3  # the relative noise of f that the step `rel` is right for: eps for the default
    ax = abs(float(x))
    cap = np.inf if scale is None else rel * max(ax, scale)

    def quotient(s):
        xp, xm = dtype.type(x + dtype.type(s)), dtype.type(x - dtype.type(s))
        if xp == xm:
            return None
        fp, fm = value(xp), value(xm)
        if not (np.isfinite(fp) and np.isfinite(fm)):
            return None
        return (fp - fm) / (float(xp) - float(xm)), abs(fp - fm), max(abs(fp), abs(fm), abs(f0))

    # 1. rounding: lengthen the step until the difference is h of |f| (f varies on a scale L much
    # longer than |x|: the step grows towards h·L), unless it stops growing with the step
    s = rel * (ax if ax > 0 else (1.0 if scale is None else scale))
    last = None  # (s, quotient) of the last step whose difference rose above rounding
    for _ in range(_FD_TRIALS):
        out = quotient(s)
        if out is None:  # below the resolution of x, or f undefined at x ± s
            if last is not None or s >= cap:
                break
            s = min(s * _FD_GROWTH, cap)
            continue
        d, df, size = out
        floor = 64 * np.finfo(dtype).eps * size  # what rounding alone makes of the difference
        if last is not None and df < 0.5 * last[2] * s / last[0]:
            break  # the difference stopped growing in proportion: f is no longer close to linear
        last = (s, d, df) if df > floor or last is None else last
        if df >= rel * size or s >= cap:
            break
        s = min(s * (_FD_GROWTH if df <= floor else min(_FD_GROWTH, 2 * rel * size / df)), cap)
    if last is None:
        raise ValueError(
            f"fd_gradient: f is not finite at x ± s for every step tried around the entry x = {x!r}; "
            "check f there, or pass a smaller h"
        )
    s, d, _ = last
    # 2. truncation: D(s) against D(s/2); shorten the step until they agree
    best = None  # (gap, D(s/2)) with the smallest gap
    for _ in range(_FD_TRIALS):
        half = quotient(s / 2)
        if half is None:
            break
        d2, _, size = half
        gap = abs(d - d2)
        allowed = rel**2 * max(abs(d), abs(d2)) + 4 * noise * size / s
        if gap <= allowed:
            return d2  # its truncation error is about gap / 3
        best = (gap, d2) if best is None or gap < best[0] else best
        s = s * max(1e-3, 0.5 * np.sqrt(allowed / gap))
        out = quotient(s)
        if out is None:
            break
        d = out[0]
    if not strict and best is not None:
        return best[1]  # the caller's h: the steps it allows, the one whose quotients agree best
    raise ValueError(
        f"fd_gradient: central differences around the entry x = {x!r} do not settle as the step shortens "
        f"(last step {s:.3g}): f is noisier than h³ = {noise:.1e} of its size (a solve's tolerance), or not "
        f"differentiable there, or varies on a scale finer than x's resolution in {dtype.name}. Pass "
        "h ≈ (relative noise of f)^(1/3), e.g. h=1e-4 for a solve at rtol 1e-12, or params in float64."
    )
