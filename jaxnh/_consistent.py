"""Consistent initial velocities."""

from __future__ import annotations

import jax.numpy as jnp

from .equations.base import as_float, as_time
from .equations.terms import constraint_terms, mass_and_velocity_terms
from .linalg import cholesky, mm, solve_lower, solve_psd_min_norm, solve_upper_t
from ._mechanism import Mechanism

__all__ = ["consistent_velocities"]


def consistent_velocities(mech: Mechanism, q, qd, t, params, iterations: int = 3):
    """The velocities nearest to `qd` that satisfy the constraints.

    "Nearest" is in the kinetic-energy metric: the correction `δ` minimises
    `½ δᵀ M δ` subject to `c(q, qd + δ, t) = 0`, i.e. it is the velocity jump
    an impulsive constraint force would cause. Linear constraints are met in
    one step; nonlinear ones by `iterations` Gauss–Newton steps.

    Returns:
        velocities (s,) in the units of qd.
    """
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    if mech.constraints is None:
        return qd
    mech.check_values(q, qd, t, params, constraint_rtol=float("inf"))  # concrete input only
    M, _ = mass_and_velocity_terms(mech, q, qd, t, params)
    L = cholesky(M)
    for _ in range(iterations if mech.nonlinear_constraints else 1):
        A, _ = constraint_terms(mech, q, qd, t, params)
        c = mech.constraint(q, qd, t, params)
        W = solve_lower(L, A.T)
        mu = solve_psd_min_norm(mm(W.T, W), c)
        qd = qd - solve_upper_t(L, mm(W, mu))
    return qd
