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

from ..linalg import mm


def kinetic_pushforward(mech, q, qd, t, params, dq, dqd, dt):
    """∂T/∂q, and the derivatives of (∂T/∂q, ∂T/∂qd) along n directions at once.

    One reverse pass over T gives both gradients; a `jvp` of that pass batched
    over the directions (rows of `dq` (n, s), `dqd` (n, s), `dt` (n,)) pushes them
    forward, its primal traced and evaluated once. Returns `(∂T/∂q (s,), d∂T/∂q
    (n, s), d∂T/∂qd (n, s))`; along (qd, a, 1) the last is `M a + h + ∂T/∂q`, along
    (0, e, 0) it is `M e`. Units: those of T per unit of q, and per unit of q and
    of each direction.
    """

    def gradients(q_, qd_, t_):
        return jax.grad(mech.kinetic, argnums=(0, 1))(q_, qd_, t_, params)

    push = jax.vmap(lambda a, b, c: jax.jvp(gradients, (q, qd, t), (a, b, c)), out_axes=(None, 0))
    (dTdq, _), (ddq, ddqd) = push(dq, dqd, dt)
    return dTdq, ddq, ddqd


def mass_and_velocity_terms(mech, q, qd, t, params):
    """Mass matrix M (s, s) and velocity terms h (s,) of the Lagrange expression."""
    s = q.shape[0]
    dq = jnp.concatenate([qd[None], jnp.zeros((s, s), qd.dtype)])
    dqd = jnp.concatenate([jnp.zeros((1, s), qd.dtype), jnp.eye(s, dtype=qd.dtype)])
    dt = jnp.zeros((s + 1,), jnp.result_type(t)).at[0].set(1)
    dTdq, _, dp = kinetic_pushforward(mech, q, qd, t, params, dq, dqd, dt)
    # M is symmetric: its rows are the pushed-forward momenta along the unit directions
    return dp[1:], dp[0] - dTdq


def projected_terms(mech, q, qd, t, params, B, beta):
    """`K = Bᵀ M B` (k, k) and `r = Bᵀ (M β + h)` (k,) for the velocity map qd = B v + ...

    The k + 1 directions (qd, β, 1) and (0, B e_j, 0) alone are pushed forward,
    so neither the full mass matrix nor unused Jacobian columns are formed (the
    derived Appell field's system matrix and right-hand side).
    """
    s, k = B.shape
    dq = jnp.concatenate([qd[None], jnp.zeros((k, s), qd.dtype)])
    dqd = jnp.concatenate([beta[None], B.T])
    dt = jnp.zeros((k + 1,), jnp.result_type(t)).at[0].set(1)
    dTdq, _, dp = kinetic_pushforward(mech, q, qd, t, params, dq, dqd, dt)
    return mm(dp[1:], B), mm(B.T, dp[0] - dTdq)


def constraint_terms(mech, q, qd, t, params):
    """Constraint matrix A = ∂c/∂qd (m, s) and b (m,) with A qdd + b = 0."""

    def c(q_, qd_, t_):
        return mech.constraint(q_, qd_, t_, params)

    A = jax.jacfwd(c, argnums=1)(q, qd, t)
    _, b = jax.jvp(lambda q_, t_: c(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    return A, b
