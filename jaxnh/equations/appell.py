"""Appell's (Gibbs–Appell) equations (paper eqs. 17–18).

With the independent velocities v and qd = B v + β0 (eq. 17), the
accelerations are `qdd = B vd + β`, and Appell's equations are

    Bᵀ ∂S/∂qdd (q, qd, B vd + β, t) = Bᵀ Q           (eq. 18)

for the k = s − m independent accelerations vd only. S is the user's
acceleration energy when given (it must be quadratic in qdd, as every
mechanical S is, so one Newton step solves it exactly); otherwise its
acceleration-dependent part is built from T, `S = ½ qddᵀ M qdd + qddᵀ h`,
whose gradient is the Lagrange expression `M qdd + h`. The reduced system
matrix `Bᵀ M B` is symmetric positive definite. The state is (q, v): the
dependent velocities come from the constraints, so they cannot drift.
Multipliers are recovered from the accelerations only when recorded.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..linalg import mm, solve_spd
from .base import Formulation, multipliers_from_accelerations
from .split import VelocitySplit
from .terms import mass_and_velocity_terms


class Appell(Formulation):
    """Gibbs–Appell equations in the independent velocities; state (q, v)."""

    split: VelocitySplit

    def state(self, q, qd, t, params):
        return (q, self.split.independent_of(qd))

    def unpack(self, y, t, params):
        q, v = y
        return q, self.split.velocities(q, v, t, params)

    def _independent_accelerations(self, q, v, t, params):
        mech = self.mech
        qd, B, beta = self.split.velocities_and_rates(q, v, t, params)
        Q = mech.generalized_forces(q, qd, t, params)
        if mech.acceleration_energy is None:
            M, h = mass_and_velocity_terms(mech, q, qd, t, params)
            K = mm(B.T, mm(M, B))
            rhs = mm(B.T, Q - h - mm(M, beta))
        else:
            dS = jax.grad(mech.acceleration_energy, argnums=2)
            g0, H = jax.linearize(lambda a: dS(q, qd, a, t, params), beta)
            K = mm(B.T, jax.vmap(H, in_axes=1, out_axes=1)(B))
            rhs = mm(B.T, Q - g0)
        vd = solve_spd(K, rhs)
        return qd, mm(B, vd) + beta, vd

    def accelerations(self, q, qd, t, params, multipliers: bool = False):
        v = self.split.independent_of(qd)
        qd, qdd, _ = self._independent_accelerations(q, v, t, params)
        lam = multipliers_from_accelerations(self.mech, q, qd, qdd, t, params) if multipliers else None
        return qdd, lam

    def vector_field(self, t, y, params):
        q, v = y
        qd, _, vd = self._independent_accelerations(q, v, t, params)
        return (qd, vd)
