"""The terms of the equations of motion, each by automatic differentiation.

For kinetic energy T(q, qd, t) the Lagrange expression is

    d/dt ∂T/∂qd − ∂T/∂q = M(q, t) qdd + h(q, qd, t),

with the mass matrix `M = ∂²T/∂qd²` and the velocity terms
`h = (∂p/∂q) qd + ∂p/∂t − ∂T/∂q`, where `p = ∂T/∂qd` is the generalized
momentum (the ∂p/∂t term is the explicit time dependence of a rheonomic T).

A constraint `c(q, qd, t) = 0` differentiated along the motion gives the
acceleration-level constraint `A qdd + b = 0` with `A = ∂c/∂qd` and
`b = (∂c/∂q) qd + ∂c/∂t`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnh._base.linalg import mm


def _along(f, q, qd, t, dqd):
    """`f(q, qd, t)` and its derivatives along the k velocity directions `dqd` (s, k) and along the
    motion (q, t) → (q + qd dt, t + dt), in one forward pass over one evaluation of f.

    Returns (f, (k,) + f's shape, f's shape): f's value, its derivatives ∂f/∂qd · dqd_j, and
    (∂f/∂q) qd + ∂f/∂t. The k + 1 tangents are batched (`vmap` of `jvp`): f and, for a gradient f,
    its reverse pass, are traced and evaluated once, not once per quantity."""
    k = dqd.shape[1]
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.inexact):  # (an integer time has no tangent)
        t = t.astype(q.dtype)
    tq = jnp.concatenate([jnp.zeros((k, q.shape[0]), q.dtype), qd[None, :].astype(q.dtype)])
    tqd = jnp.concatenate([dqd.T.astype(qd.dtype), jnp.zeros((1, qd.shape[0]), qd.dtype)])
    tt = jnp.concatenate([jnp.zeros((k,), t.dtype), jnp.ones((1,), t.dtype)])

    def push(a, b, c):
        return jax.jvp(f, (q, qd, t), (a, b, c))

    value, d = jax.vmap(push, out_axes=(None, 0))(tq, tqd, tt)
    return value, jax.tree_util.tree_map(lambda x: x[:k], d), jax.tree_util.tree_map(lambda x: x[k], d)


def _gradients(mech, params):
    """(q, qd, t) → (∂T/∂q, ∂T/∂qd): the second is the generalized momentum p."""
    return lambda q_, qd_, t_: jax.grad(mech.kinetic, argnums=(0, 1))(q_, qd_, t_, params)


def mass_and_velocity_terms(mech, q, qd, t, params):
    """Mass matrix M (s, s) and velocity terms h (s,) of the Lagrange expression, from one
    forward pass (s + 1 tangents) over one reverse pass of T."""
    (dTdq, _), (_, Mt), (_, dp) = _along(_gradients(mech, params), q, qd, t, jnp.eye(qd.shape[0], dtype=qd.dtype))
    return Mt.T, dp - dTdq


def projected_terms(mech, q, qd, t, params, B, beta):
    """`K = Bᵀ M B` (k, k) and `r = Bᵀ (M β + h)` (k,) for the velocity map qd = B v + ...

    The derived Appell field's system matrix and right-hand side from the k + 1
    products `M [B, β]` (the momentum pushed forward along those velocity
    directions only), not from the whole mass matrix: no unused Jacobian column
    is formed (for the variator, k = 1 of s = 2). (Not through `_along`: for the variator's
    flattened Appell field the k + 2 tangents of both gradients made a step 1.5× slower.)
    """
    k = B.shape[1]

    def momentum(q_, qd_, t_):
        return jax.grad(mech.kinetic, argnums=1)(q_, qd_, t_, params)

    _, dp = jax.jvp(lambda q_, t_: momentum(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    dTdq = jax.grad(mech.kinetic, argnums=0)(q, qd, t, params)

    def along(d):
        return jax.jvp(lambda v: momentum(q, v, t), (qd,), (d,))[1]

    MD = jax.vmap(along, in_axes=1, out_axes=1)(jnp.concatenate([B, beta[:, None]], axis=1))
    return mm(B.T, MD[:, :k]), mm(B.T, dp - dTdq + MD[:, k])


def constraint_terms(mech, q, qd, t, params):
    """Constraint matrix A = ∂c/∂qd (m, s) and b (m,) with A qdd + b = 0."""

    def c(q_, qd_, t_):
        return mech.constraint(q_, qd_, t_, params)

    _, At, b = _along(c, q, qd, t, jnp.eye(qd.shape[0], dtype=qd.dtype))
    return At.T, b
