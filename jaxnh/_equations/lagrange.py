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
tolerance, unless stabilised:

* `baumgarte=α` (1/s): the acceleration constraint becomes `A qdd + b = −α c`,
  so a violation decays like exp(−α t) instead of accumulating (Baumgarte's
  method, in the first-order form that suits velocity constraints). Cheap,
  but a large α makes the system stiff.
* `projection=True`: after every step the velocities are projected back onto
  the constraints, minimum-norm in the kinetic-energy metric (the velocity
  jump an impulsive constraint force would cause; `jaxnh.consistent_velocities`).
  The size of the correction is added to the step's error estimate, so a step
  that left the constraints by more than the tolerance is rejected rather than
  silently pulled back.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from jaxnh._base.linalg import cholesky, mm, solve_lower, solve_psd_min_norm, solve_upper_t
from jaxnh._equations.base import Formulation
from jaxnh._equations.consistent import project_velocities
from jaxnh._equations.step_maps import normalize_quaternions, StepMaps
from jaxnh._equations.terms import constraint_terms, mass_and_velocity_terms


class Lagrange(Formulation):
    """Lagrange's equations of the first kind with multipliers; state y = [q, qd] (one flat vector).

    Arguments:
        baumgarte: optional constraint stabilisation rate α, 1/s (a traced array
            is fine, so it may be differentiated or batched). `"auto"` in
            `simulate` means one over the median report interval.
        projection: project the velocities onto the constraints after every
            step (see the module docstring).
    """

    baumgarte: Any = None  # a float or array (α, 1/s), "auto" before `simulate` resolves it, or None
    projection: bool = False

    name = "lagrange"

    def state(self, q: jnp.ndarray, qd: jnp.ndarray, t: Any, params: Any) -> jnp.ndarray:
        return jnp.concatenate([q, qd])

    def unpack(self, y: jnp.ndarray, t: Any, params: Any) -> tuple[jnp.ndarray, jnp.ndarray]:
        q, qd = y[: self.nq], y[self.nq :]
        q = normalize_quaternions(q, self.bound_mech.quaternions)  # (a report between steps: interpolated)
        if self.projection and self.m:
            # reports between steps come from the dense output, which is not projected
            return q, project_velocities(self.bound_mech, q, qd, t, params)
        return q, qd

    def accelerations(
        self, q: jnp.ndarray, qd: jnp.ndarray, t: Any, params: Any, multipliers: bool = False
    ) -> tuple[jnp.ndarray, jnp.ndarray | None]:
        mech = self.bound_mech
        M, h = mass_and_velocity_terms(mech, q, qd, t, params)
        L = cholesky(M)
        u = solve_lower(L, mech.generalized_forces(q, qd, t, params) - h)
        if self.m == 0:
            qdd = solve_upper_t(L, u)
            return qdd, (qdd[:0] if multipliers else None)
        A, b = constraint_terms(mech, q, qd, t, params)
        if self.baumgarte is not None:
            b = b + self.baumgarte * mech.constraint(q, qd, t, params)
        W = solve_lower(L, A.T)
        lam = solve_psd_min_norm(mm(W.T, W), -b - mm(W.T, u))
        qdd = solve_upper_t(L, u + mm(W, lam))
        return qdd, (lam if multipliers else None)

    def vector_field(self, t: Any, y: jnp.ndarray, params: Any) -> jnp.ndarray:
        q, qd = y[: self.nq], y[self.nq :]
        qdd, _ = self.accelerations(q, qd, t, params)
        return jnp.concatenate([self.rate(q, qd, t, params), qdd]).astype(y.dtype)

    def step_maps(self) -> StepMaps | None:
        return _Projection() if self.projection and self.m else None


class _Projection(StepMaps):
    """(q, qd) → (q, consistent qd) after every step, the correction counted as error.
    The solve's args are `(formulation, params, ok)`."""

    def post(self, t0, y0, t1, y1, args):
        s = args[0].nq
        q, qd = y1[:s], y1[s:]
        qd_new = project_velocities(args[0].mech, q, qd, t1, args[1])
        y_new = jnp.concatenate([q, qd_new])
        return y_new, y_new - y1, False, False
