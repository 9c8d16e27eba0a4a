"""Consistent initial velocities."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp

from jaxnh._base.host import as_data, as_float, as_time
from jaxnh._base.linalg import cholesky, mm, solve_lower, solve_psd_min_norm, solve_upper_t
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._equations.terms import constraint_terms, mass_and_velocity_terms
from jaxnh._model.mechanism import Mechanism


__all__ = ["consistent_velocities", "project_velocities"]


def project_velocities(mech: Mechanism, q, qd, t, params, iterations: int = 8):
    """The velocities nearest to `qd` in the kinetic-energy metric that satisfy the
    constraints (no argument checks: the building block of `consistent_velocities`
    and of the "projection" stabilisation).

    For constraints nonlinear in the velocities the Gauss–Newton iteration must bring
    |c| to √eps of the constraint's scale `|A| |qd| + |c(q, 0, t)|` in every row;
    otherwise the result is NaN, never velocities that violate the constraints."""
    if mech.n_constraints(q, qd, t, params) == 0:
        return qd
    M, _ = mass_and_velocity_terms(mech, q, qd, t, params)
    L = cholesky(M)
    if not mech.nonlinear_constraints:  # one step: c is affine in the velocities
        A, _ = constraint_terms(mech, q, qd, t, params)
        W = solve_lower(L, A.T)
        mu = solve_psd_min_norm(mm(W.T, W), mech.constraint(q, qd, t, params))
        return qd - solve_upper_t(L, mm(W, mu))
    # Newton's method on the optimality conditions of min ½ (x − qd)ᵀ M (x − qd) s.t. c(x) = 0:
    # M (x − qd) + Aᵀ μ = 0 and c(x) = 0, with the Hessian of the Lagrangian H = M + Σ μ_i ∇²c_i.
    # Each step solves [H Aᵀ; A 0] [Δ; μ'] = −[M (x − qd); c(x)] by H = L_H L_Hᵀ:
    # (A H⁻¹ Aᵀ) μ' = c − A H⁻¹ M (x − qd), Δ = −H⁻¹ (M (x − qd) + Aᵀ μ'). The first step (μ = 0,
    # x = qd) is the projection of the linearised constraint; then convergence is quadratic to the
    # point of c = 0 nearest qd (a Gauss–Newton step from each iterate alone would stop at *a*
    # point of c = 0, off the nearest by the constraint's curvature times the move squared).
    x = qd
    mu = jnp.zeros((mech.n_constraints(q, qd, t, params),), qd.dtype)
    for _ in range(iterations):
        A, _ = constraint_terms(mech, q, x, t, params)
        c = mech.constraint(q, x, t, params)
        curvature = jax.hessian(lambda u: jnp.dot(mu, mech.constraint(q, u, t, params)))(x)
        LH = cholesky(M + curvature)
        W = solve_lower(LH, A.T)
        g = solve_lower(LH, mm(M, x - qd))
        mu = solve_psd_min_norm(mm(W.T, W), c - mm(W.T, g))
        x = x - solve_upper_t(LH, g + mm(W, mu))
    qd = x
    # (constraints nonlinear in qd here: the affine case returned above) Newton's method must have
    # converged: each residual within √eps of its scale, else NaN
    A, _ = constraint_terms(mech, q, qd, t, params)
    c = jax.lax.stop_gradient(mech.constraint(q, qd, t, params))
    scale = jnp.abs(A) @ jnp.abs(qd) + jnp.abs(mech.constraint(q, jnp.zeros_like(qd), t, params))
    scale = jax.lax.stop_gradient(scale) + jnp.finfo(qd.dtype).tiny
    ok = jnp.all(jnp.abs(c) <= jnp.sqrt(jnp.finfo(qd.dtype).eps) * scale)
    return jnp.where(ok, qd, jnp.nan)


def consistent_velocities(
    mech: Mechanism, q: ArrayInput, qd: ArrayInput, t: ArrayInput, params: PyTree, iterations: int = 8
) -> jax.Array:
    """The velocities nearest to `qd` that satisfy the constraints.

    "Nearest" is in the kinetic-energy metric: the correction `δ` minimises
    `½ δᵀ M δ` subject to `c(q, qd + δ, t) = 0`, i.e. it is the velocity jump
    an impulsive constraint force would cause. Linear constraints are met in
    one step; nonlinear ones by `iterations` Gauss–Newton steps, which must
    converge (|c| ≤ √eps of its scale): eagerly a `ValueError` says when they do
    not, under `jit`/`vmap`/`grad` the result is NaN. Runs compiled
    (once per mechanism and shapes); works under `jit`, `vmap` and `grad`.

    Arguments:
        mech: the `Mechanism`.
        q: coordinates (s,).
        qd: velocities (s,), in the units of q per second.
        t: time, s.
        params: the parameter pytree.

    Returns:
        velocities (s,) in the units of qd.
    """
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    params = as_data(params, q)
    mech.check_shapes(q, qd, t, params)
    mech.check_values(q, qd, t, params, constraint_rtol=float("inf"))  # concrete input only
    out = _project_jit(mech, q, qd, t, params, iterations)
    if mech.nonlinear_constraints and not isinstance(out, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(out))):
        raise ValueError(
            f"consistent_velocities: {iterations} Gauss–Newton steps from qd did not satisfy the constraints "
            "nonlinear in the velocities (|c| above √eps of its scale). Start from velocities closer to the "
            "constraint, pass more `iterations`, or write the constraints so that they are closer to linear "
            "in the velocities."
        )
    return out


@eqx.filter_jit
def _project_jit(mech, q, qd, t, params, iterations):
    return project_velocities(mech, q, qd, t, params, iterations)
