"""Holonomic constraints `g(q, t, p) = 0` solved for dependent coordinates.

A wheel that must stay on the ground, a fork that closes a loop: h
constraints on the coordinates themselves, so h of the s coordinates (the
*dependent* ones, `q_D`) are functions of the others (`q_I`). A `Mechanism`
offers the two classical treatments:

* without `dependent`, all s coordinates are integrated and
  `ġ = (∂g/∂q) q̇ + ∂g/∂t = 0` joins the nonholonomic constraints. Lagrange's
  equations with multipliers differentiate it once more, so the motion
  satisfies `g̈ = 0` (index reduction): `g` itself holds only to the
  integration error and drifts slowly (`Mechanism.project` removes the drift);
* with `dependent`, only the s − h independent coordinates are integrated;
  the dependent ones are recovered at every evaluation by Newton's method on
  `g(q_I, q_D, t) = 0`, differentiated by the implicit function theorem
  (`∂q_D/∂q_I = −G_D⁻¹ G_I`, `G = ∂g/∂q`) to any order, so `g` cannot drift.
  Substituting a holonomic parametrisation into T is exact (unlike a
  nonholonomic one), so Lagrange's and Appell's equations both apply to the
  reduced mechanism.

`Elimination` is the Newton solve and its derivatives; `Mechanism.reduced`
builds the mechanism in q_I from it.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from jaxnh._base.host import as_float, as_time
from jaxnh._base.linalg import pick, solve_square


__all__ = ["Elimination", "check_dependent", "project"]


def check_dependent(dependent, holonomic, independent) -> None:
    """Refuse a `dependent` that cannot name the coordinates solved from `holonomic`."""
    if dependent is None:
        return
    dep = tuple(dependent)
    if holonomic is None:
        raise ValueError(
            f"Mechanism: `dependent={dep!r}` names coordinates solved from holonomic constraints, but no "
            "`holonomic=g(q, t, params)` was given"
        )
    if not dep or len(set(dep)) != len(dep) or not all(isinstance(i, int) and i >= 0 for i in dep):
        raise ValueError(f"Mechanism: `dependent` must be distinct coordinate indices ≥ 0; got {dependent!r}")
    if independent is not None and set(independent) & set(dep):
        raise ValueError(
            f"Mechanism: independent velocities {tuple(independent)} include dependent coordinates "
            f"{tuple(sorted(set(independent) & set(dep)))}; their rates follow from ġ = 0"
        )


class Elimination(eqx.Module):
    """Dependent coordinates `q_D(q_I, t, params)` from `g(q, t, params) = 0` by Newton's method.

    Attributes:
        holonomic: g(q, t, params) -> (h,).
        dependent: the h indices of q_D among the s coordinates.
        guess: `guess(q_I, t, params) -> (h,)`, Newton's start (None: zeros).
        iterations: Newton iterations (quadratic convergence: 8 reach rounding
            from any reasonable start).
        tol: largest accepted |g| after the iterations (None: √eps); a miss
            gives NaN, which a simulation reports as a failure.
    """

    holonomic: Callable = eqx.field(static=True)
    dependent: tuple = eqx.field(static=True)
    guess: Optional[Callable] = eqx.field(static=True, default=None)
    iterations: int = eqx.field(static=True, default=8)
    tol: Optional[float] = eqx.field(static=True, default=None)

    def free(self, s: int) -> tuple:
        """Indices of the s − h independent coordinates q_I."""
        return tuple(i for i in range(s) if i not in self.dependent)

    def assemble(self, q_ind, q_dep):
        """All s coordinates from q_I (s − h,) and q_D (h,)."""
        s = q_ind.shape[0] + q_dep.shape[0]
        if max(self.dependent) >= s:
            raise ValueError(f"Mechanism: dependent index {max(self.dependent)} ≥ s = {s} coordinates")
        parts = [None] * s
        for j, i in enumerate(self.free(s)):
            parts[i] = q_ind[j]
        for j, i in enumerate(self.dependent):
            parts[i] = q_dep[j]
        return jnp.stack(parts)

    def residual(self, q, t, p):
        """g(q, t, p) (h,), its shape checked against `dependent`."""
        g = jnp.asarray(self.holonomic(q, t, p))
        if g.shape != (len(self.dependent),):
            raise ValueError(
                f"Mechanism `holonomic` must return shape ({len(self.dependent)},), one value per dependent "
                f"coordinate {self.dependent}; got {g.shape}"
            )
        return g

    def coordinates(self, q_ind, t, params, start=None):
        """All coordinates q (s,) from q_I (s − h,): Newton from `start` (default `guess`, else zeros).

        Differentiable in q_I, t and the array leaves of params to any order
        (implicit function theorem); NaN if Newton missed `tol`.
        """
        q_ind = as_float(q_ind)
        t = as_time(t, q_ind)
        h = len(self.dependent)
        if start is None:
            start = self.guess(q_ind, t, params) if self.guess is not None else jnp.zeros((h,), q_ind.dtype)
        start = jax.lax.stop_gradient(jnp.asarray(start, dtype=q_ind.dtype))
        dyn, static = eqx.partition(params, eqx.is_inexact_array)

        def g_of(qi, x, t_, dyn_):
            return self.residual(self.assemble(qi, x), t_, eqx.combine(dyn_, static))

        tol = self.tol if self.tol is not None else float(jnp.finfo(q_ind.dtype).eps) ** 0.5
        iterations = self.iterations

        @jax.custom_jvp
        def solve(qi, t_, dyn_, x):
            def newton_step(_, x):
                G = jax.jacfwd(g_of, argnums=1)(qi, x, t_, dyn_)
                return x - solve_square(G, g_of(qi, x, t_, dyn_))

            # a loop, not unrolled: traced once, however often derivatives re-enter it
            x = jax.lax.fori_loop(0, iterations, newton_step, x)
            ok = jnp.all(jnp.abs(g_of(qi, x, t_, dyn_)) <= tol)
            return jnp.where(ok, x, jnp.nan)

        def solve_jvp(primals, tangents):
            qi, t_, dyn_, x0 = primals
            x = solve(qi, t_, dyn_, x0)  # the solution does not depend on the start x0
            G = jax.jacfwd(g_of, argnums=1)(qi, x, t_, dyn_)
            # ∂g/∂(qi, t, params) · tangents at fixed q_D, over the non-zero tangents only
            flat_p, tree = jax.tree_util.tree_flatten((qi, t_, dyn_))
            flat_t = jax.tree_util.tree_leaves(tangents[:3], is_leaf=lambda z: isinstance(z, SymbolicZero))
            live = [k for k, d in enumerate(flat_t) if not isinstance(d, SymbolicZero)]
            if not live:
                return x, jnp.zeros_like(x)

            def g_live(*vals):
                leaves = list(flat_p)
                for k, v in zip(live, vals):
                    leaves[k] = v
                qi_, tt_, dd_ = jax.tree_util.tree_unflatten(tree, leaves)
                return g_of(qi_, x, tt_, dd_)

            _, dg = jax.jvp(g_live, tuple(flat_p[k] for k in live), tuple(flat_t[k] for k in live))
            return x, -solve_square(G, dg)

        solve.defjvp(solve_jvp, symbolic_zeros=True)
        return self.assemble(q_ind, solve(q_ind, t, dyn, start))

    def jacobians(self, q, t, params):
        """G_D (h, h), G_I (h, s − h) and ∂g/∂t (h,) at q."""
        s = q.shape[0]
        G, gt = jax.jacfwd(self.residual, argnums=(0, 1))(q, t, params)
        GD = jnp.stack([G[:, i] for i in self.dependent], axis=1)
        GI = jnp.stack([G[:, i] for i in self.free(s)], axis=1)
        return GD, GI, gt

    def velocities(self, q, qd_ind, t, params):
        """All q̇ (s,) at q with g = 0 from q̇_I: `q̇_D = −G_D⁻¹ (G_I q̇_I + ∂g/∂t)` (ġ = 0)."""
        GD, GI, gt = self.jacobians(q, t, params)
        return self.assemble(qd_ind, solve_square(GD, -(GI @ qd_ind + gt)))

    def accelerations(self, q, qd, qdd_ind, t, params):
        """All q̈ (s,) at a consistent (q, q̇) from q̈_I: `q̈_D = −G_D⁻¹ (G_I q̈_I + γ)` (g̈ = 0),
        with `γ = (∂ġ/∂q) q̇ + ∂ġ/∂t`."""

        def gdot(q_, t_):
            return jax.jvp(lambda x, tt: self.residual(x, tt, params), (q_, t_), (qd, jnp.ones_like(t_)))[1]

        _, gamma = jax.jvp(gdot, (q, t), (qd, jnp.ones_like(t)))
        GD, GI, _ = self.jacobians(q, t, params)
        return self.assemble(qdd_ind, solve_square(GD, -(GI @ qdd_ind + gamma)))

    def state(self, q_ind, qd_ind, t, params, start=None):
        """q (s,) and q̇ (s,) from q_I and q̇_I (g = 0, ġ = 0); Newton from `start` as in `coordinates`.

        The velocities are written out from the Jacobian of g (not by
        differentiating the Newton solve), which keeps nested derivatives of
        the reduced mechanism small.
        """
        q_ind = as_float(q_ind)
        t = as_time(t, q_ind)
        q = self.coordinates(q_ind, t, params, start)
        return q, self.velocities(q, jnp.asarray(qd_ind, q_ind.dtype), t, params)

    def restore(self, q, t, params):
        """q with q_D re-solved from q_I, Newton started at q's own q_D."""
        q = as_float(q)
        return self.coordinates(pick(q, self.free(q.shape[0])), t, params, start=pick(q, self.dependent))

    def generalized_forces(self, Q, q, t, params):
        """The reduced forces `Jᵀ Q` (s − h,), `J = ∂q/∂q_I = [I; −G_D⁻¹ G_I]` (virtual work Q · δq)."""
        GD, GI, _ = self.jacobians(q, t, params)
        return pick(Q, self.free(q.shape[0])) + solve_square(GD, -GI).T @ pick(Q, self.dependent)


def project(holonomic: Callable, q, t, params, iterations: int = 4):
    """The coordinates nearest to q (Euclidean) with g = 0, by Gauss–Newton."""
    q = as_float(q)
    t = as_time(t, q)
    for _ in range(iterations):
        g = jnp.asarray(holonomic(q, t, params))
        G = jax.jacfwd(lambda x: jnp.asarray(holonomic(x, t, params)))(q)
        q = q - G.T @ solve_square(G @ G.T, g)
    return q
