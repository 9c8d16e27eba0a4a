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


def fd_gradient(f: Callable[[Any], Any], params: PyTree, h: float = 1e-6, trainable: Any = None) -> PyTree:
    """Central-difference gradient of the scalar `f` over the trainable leaves
    of `params` (default as in `optimize`, or those marked by `trainable`), with step `h` scaled
    by `max(1, |x|)` for each entry. Returns a pytree like `params` with None
    at the leaves not differentiated (as `equinox.filter_grad` does). Costs two evaluations per entry:
    meant for checking `jax.grad` on a handful of design variables.
    """
    spec = trainable_leaves(params) if trainable is None else trainable
    theta, rest = eqx.partition(params, spec)
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    f_flat = jax.jit(lambda ls: f(eqx.combine(jax.tree_util.tree_unflatten(treedef, ls), rest)))
    grads = []
    for i, x in enumerate(leaves):
        x = np.asarray(x, dtype=float)
        g = np.zeros_like(x)
        for j in np.ndindex(x.shape):
            step = h * max(1.0, abs(float(x[j])))
            vals = []
            for s in (step, -step):
                xp = x.copy()
                xp[j] += s
                trial = list(leaves)
                trial[i] = jnp.asarray(xp, dtype=leaves[i].dtype)
                vals.append(float(f_flat(trial)))
            g[j] = (vals[0] - vals[1]) / (2 * step)
        grads.append(jnp.asarray(g, dtype=leaves[i].dtype))
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, grads), jax.tree_util.tree_map(lambda _: None, rest))
