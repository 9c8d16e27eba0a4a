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


def _momentum(mech, params):
    """p(q, qd, t) = ∂T/∂qd, the generalized momentum."""
    return lambda q_, qd_, t_: jax.grad(mech.kinetic, argnums=1)(q_, qd_, t_, params)


def _velocity_terms(mech, q, qd, t, params):
    """∂T/∂q and `(∂p/∂q) qd + ∂p/∂t = h + ∂T/∂q` (the momentum pushed forward along the motion)."""
    momentum = _momentum(mech, params)
    _, dp = jax.jvp(lambda q_, t_: momentum(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    return jax.grad(mech.kinetic, argnums=0)(q, qd, t, params), dp


def mass_and_velocity_terms(mech, q, qd, t, params):
    """Mass matrix M (s, s) and velocity terms h (s,) of the Lagrange expression."""
    dTdq, dp = _velocity_terms(mech, q, qd, t, params)
    return jax.jacfwd(_momentum(mech, params), argnums=1)(q, qd, t), dp - dTdq


def projected_terms(mech, q, qd, t, params, B, beta):
    """`K = Bᵀ M B` (k, k) and `r = Bᵀ (M β + h)` (k,) for the velocity map qd = B v + ...

    The derived Appell field's system matrix and right-hand side from the k + 1
    products `M [B, β]` (the momentum pushed forward along those velocity
    directions only), not from the whole mass matrix: no unused Jacobian column
    is formed (for the variator, k = 1 of s = 2).
    """
    k = B.shape[1]
    momentum = _momentum(mech, params)
    dTdq, dp = _velocity_terms(mech, q, qd, t, params)

    def along(d):
        return jax.jvp(lambda v: momentum(q, v, t), (qd,), (d,))[1]

    MD = jax.vmap(along, in_axes=1, out_axes=1)(jnp.concatenate([B, beta[:, None]], axis=1))
    return mm(B.T, MD[:, :k]), mm(B.T, dp - dTdq + MD[:, k])


def constraint_terms(mech, q, qd, t, params):
    """Constraint matrix A = ∂c/∂qd (m, s) and b (m,) with A qdd + b = 0."""

    def c(q_, qd_, t_):
        return mech.constraint(q_, qd_, t_, params)

    A = jax.jacfwd(c, argnums=1)(q, qd, t)
    _, b = jax.jvp(lambda q_, t_: c(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    return A, b
