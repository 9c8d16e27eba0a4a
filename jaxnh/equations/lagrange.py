"""Lagrange's equations with undetermined multipliers (paper eq. 3).

    M qdd + h = Q + Aᵀ λ,        A qdd + b = 0,

s + m equations for the s accelerations and m multipliers. With the
Cholesky factor M = L Lᵀ, W = L⁻¹ Aᵀ and u = L⁻¹ (Q − h):

    (Wᵀ W) λ = −b − Wᵀ u,        qdd = L⁻ᵀ (u + W λ).

`Wᵀ W = A M⁻¹ Aᵀ` is positive definite for independent constraints and only
semidefinite for redundant ones, where the minimum-norm multipliers are
returned (`jaxnh.linalg.solve_psd_min_norm`); the accelerations are unique
either way. The integrated state is (q, qd): the velocity constraint itself
is only kept through its derivative and drifts at the level of the solver
tolerance, unless stabilised: with `baumgarte` set to a rate α (1/s) the
acceleration constraint becomes `A qdd + b = −α c`, so a violation decays like
exp(−α t) instead of accumulating (Baumgarte's method, first-order form as
suits velocity constraints).
"""

from __future__ import annotations

from ..linalg import cholesky, mm, solve_lower, solve_psd_min_norm, solve_upper_t
from .base import Formulation
from .terms import constraint_terms, mass_and_velocity_terms


class Lagrange(Formulation):
    """Lagrange's equations of the first kind with multipliers; state (q, qd).

    `baumgarte`: optional constraint stabilisation rate α, 1/s (a traced array
    is fine, so it may be differentiated or batched).
    """

    baumgarte: object = None

    def state(self, q, qd, t, params):
        return (q, qd)

    def unpack(self, y, t, params):
        return y

    def accelerations(self, q, qd, t, params, multipliers: bool = False):
        mech = self.mech
        M, h = mass_and_velocity_terms(mech, q, qd, t, params)
        L = cholesky(M)
        u = solve_lower(L, mech.generalized_forces(q, qd, t, params) - h)
        if mech.constraints is None:
            qdd = solve_upper_t(L, u)
            return qdd, (qdd[:0] if multipliers else None)
        A, b = constraint_terms(mech, q, qd, t, params)
        if self.baumgarte is not None:
            b = b + self.baumgarte * mech.constraint(q, qd, t, params)
        if A.shape[0] == 0:
            qdd = solve_upper_t(L, u)
            return qdd, (b if multipliers else None)
        W = solve_lower(L, A.T)
        lam = solve_psd_min_norm(mm(W.T, W), -b - mm(W.T, u))
        qdd = solve_upper_t(L, u + mm(W, lam))
        return qdd, (lam if multipliers else None)

    def vector_field(self, t, y, params):
        q, qd = y
        qdd, _ = self.accelerations(q, qd, t, params)
        return (qd, qdd)
