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
* `optimize`: an optax loop over the inexact-array leaves of a pytree.
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

from typing import Any, Callable, ClassVar, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from .profiles import Bounded, Profile, trainable as trainable_leaves  # noqa: F401  (Bounded re-exported)

__all__ = ["Chebyshev", "Bounded", "optimize", "fd_gradient"]


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

    def __init__(self, coef, t0=0.0, t1=1.0):
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
    params,
    *,
    optimizer: Optional[optax.GradientTransformation] = None,
    steps: int = 200,
    trainable: Any = None,
    callback: Optional[Callable[[int, float, Any], Any]] = None,
):
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

    Returns:
        `(best_params, history)`: the params with the lowest loss seen
        (evaluated before each update, and after the last) and the loss
        values as a NumPy array of length `steps + 1`.
    """
    if int(steps) != steps or steps < 0:
        raise ValueError(f"optimize: steps must be a non-negative integer; got {steps!r}")
    optimizer = optax.adam(0.05) if optimizer is None else optimizer
    spec = trainable_leaves(params) if trainable is None else trainable
    theta, rest = eqx.partition(params, spec)
    opt_state = optimizer.init(theta)

    @eqx.filter_jit
    def step(theta, opt_state):
        value, g = eqx.filter_value_and_grad(lambda th: loss(eqx.combine(th, rest)))(theta)
        updates, opt_state = optimizer.update(g, opt_state, theta)
        return eqx.apply_updates(theta, updates), opt_state, value

    @eqx.filter_jit
    def value_only(theta):
        return loss(eqx.combine(theta, rest))

    history = []
    best, best_value = theta, np.inf
    for k in range(int(steps)):
        new, opt_state, value = step(theta, opt_state)
        value = float(value)
        if not np.isfinite(value):
            raise FloatingPointError(f"optimize: loss is {value} at step {k}; lower the learning rate or check the model")
        history.append(value)
        if value < best_value:
            best, best_value = theta, value
        if callback is not None:
            callback(k, value, eqx.combine(theta, rest))
        theta = new
    value = float(value_only(theta))
    history.append(value)
    if value < best_value:
        best = theta
    return eqx.combine(best, rest), np.asarray(history)


def fd_gradient(f: Callable[[Any], Any], params, h: float = 1e-6, trainable: Any = None):
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
