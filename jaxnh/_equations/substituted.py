"""The naive "substituted" method (paper eqs. 11–16) — wrong for nonholonomic constraints.

The dependent velocities are substituted into the kinetic energy,
`T*(q, v, t) = T(q, B v + β0, t)` (eq. 13), and Lagrange's equations of the
second kind are applied to the independent coordinates with the reduced
forces `Bᵀ Q` (eqs. 11–12):

    d/dt ∂T*/∂v − ∂T*/∂q_I = Bᵀ Q.

This is correct only when the constraints are integrable (holonomic). For a
nonholonomic constraint it is wrong: for the friction variator it doubles the
velocity term, `2 J2 U21 U21' phi1'` instead of `J2 U21 U21' phi1'`
(eq. 16 against the correct eq. 9), and does not conserve energy. It exists
to reproduce the paper's comparison and to show the error; do not use it
for anything else. The partition of the velocities is handled as for
`Appell` (the same state and the same re-choice during a run).
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp

from jaxnh._base.linalg import mm, solve_spd
from jaxnh._equations.appell import Appell


class Substituted(Appell):
    """Lagrange's second kind applied to T with the constraints substituted (wrong)."""

    has_multipliers = False
    name = "substituted"

    def bind(self, mech, s: int, m: int, nq: Optional[int] = None) -> "Substituted":
        if getattr(mech, "kinematics", None) is not None:
            raise ValueError(
                "method='substituted': the substituted form is Lagrange's second kind in q̇ and has no counterpart "
                "in speeds (a mechanism with `kinematics=`); use method='lagrange' or method='appell'"
            )
        return super().bind(mech, s, m, nq)  # pyright: ignore[reportReturnType]

    def _independent_accelerations(self, q, v, t, params, part, start=None):
        mech, split = self.bound_mech, self.split
        qd, B, beta = split.velocities_and_rates(q, v, t, params, part, start)

        def T_star(q_, v_, t_):
            return mech.kinetic(q_, split.velocities(q_, v_, t_, params, part, start), t_, params)

        def p_star(q_, v_, t_):
            return jax.grad(T_star, argnums=1)(q_, v_, t_)

        _, dp = jax.jvp(lambda q_, t_: p_star(q_, v, t_), (q, t), (qd, jnp.ones_like(t)))
        M_star = jax.jacfwd(p_star, argnums=1)(q, v, t)
        dTdq_I = split.independent_of(jax.grad(T_star, argnums=0)(q, v, t), part)
        Q = mech.generalized_forces(q, qd, t, params)
        vd = solve_spd(M_star, mm(B.T, Q) - dp + dTdq_I)
        return qd, mm(B, vd) + beta, vd

    def accelerations(
        self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object, multipliers: bool = False
    ) -> tuple[jax.Array, jax.Array | None]:
        if multipliers:
            raise ValueError(
                "method='substituted' has no multipliers: the constraint forces were "
                "eliminated by substitution (which is what makes the method wrong)."
            )
        return super().accelerations(q, qd, t, params, multipliers=False)
