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


def mass_and_velocity_terms(mech, q, qd, t, params):
    """Mass matrix M (s, s) and velocity terms h (s,) of the Lagrange expression."""

    def momentum(q_, qd_, t_):
        return jax.grad(mech.kinetic, argnums=1)(q_, qd_, t_, params)

    _, dp = jax.jvp(lambda q_, t_: momentum(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    M = jax.jacfwd(momentum, argnums=1)(q, qd, t)
    dTdq = jax.grad(mech.kinetic, argnums=0)(q, qd, t, params)
    return M, dp - dTdq


def constraint_terms(mech, q, qd, t, params):
    """Constraint matrix A = ∂c/∂qd (m, s) and b (m,) with A qdd + b = 0."""

    def c(q_, qd_, t_):
        return mech.constraint(q_, qd_, t_, params)

    A = jax.jacfwd(c, argnums=1)(q, qd, t)
    _, b = jax.jvp(lambda q_, t_: c(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    return A, b
