"""Holonomic constraints `g(q, t, p) = 0` alongside the nonholonomic ones.

A wheel that must stay on the ground, a fork that closes a loop: h
constraints on the coordinates themselves, so h of the s coordinates (the
*dependent* ones, `q_D`) are functions of the others (`q_I`). jaxnh offers
the two classical treatments, each as an ordinary `jaxnh.Mechanism`:

* `differentiated()` — all s coordinates are kept and `ġ = (∂g/∂q) q̇ + ∂g/∂t = 0`
  joins the nonholonomic constraints. Lagrange's equations with multipliers
  differentiate it once more, so the motion satisfies `g̈ = 0` ("index
  reduction"): `g` itself is kept only up to the integration error and drifts
  slowly; `project` brings coordinates back onto `g = 0`.
* `reduced()` — only the s − h independent coordinates are integrated; the
  dependent ones are recovered at every evaluation by a Newton solve of
  `g(q_I, q_D, t) = 0`, differentiated by the implicit function theorem
  (`∂q_D/∂q_I = −G_D⁻¹ G_I`), to any order. `g` cannot drift. Substituting a
  holonomic parametrisation into T is exact (unlike for nonholonomic
  constraints), so both Lagrange's and Appell's equations apply to it.

`HolonomicMechanism.simulate(method=...)` uses the first for "lagrange" and the
second for "appell" and reports full coordinates either way. `initial_state`
completes dependent coordinates and velocities from independent ones.
"""

from __future__ import annotations

import functools
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from jaxnh._base.linalg import solve_square
from jaxnh._equations.base import as_data, as_float, as_time
from jaxnh._equations.split import choose_independent, pick, VelocitySplit
from jaxnh._model.mechanism import check_independent, Mechanism
from jaxnh._solve.simulate import simulate


__all__ = ["HolonomicMechanism"]


class HolonomicMechanism(eqx.Module):
    """A mechanism with holonomic constraints `g(q, t, params) = 0`.

    Arguments (as for `jaxnh.Mechanism`, plus):
        kinetic: `T(q, qd, t, params)`, J, in all s coordinates.
        holonomic: `g(q, t, params) -> (h,)`, the holonomic constraints (in
            the units of their own, e.g. m for a contact height).
        dependent: indices of the h dependent coordinates, solved from g; the
            block `∂g/∂q_D` must be invertible along the motion.
        constraints, forces, potential, acceleration_energy, names,
        nonlinear_constraints: as in `jaxnh.Mechanism`, in all s coordinates.
        independent: indices (in all s coordinates) of the independent
            velocities, s − h − m of them; none of them dependent
            coordinates. Default: chosen at the initial state.
        guess: `guess(q_I, t, params) -> (h,)`, the start of the Newton
            solve for `q_D` (default zeros — the reference configuration).
        iterations: Newton iterations (static; quadratic convergence, so
            8 reach rounding from any reasonable guess).
        tol: largest accepted |g| after the Newton solve (default
            √eps); a solve that misses it returns NaN, which a simulation
            reports as a failed solve instead of a wrong answer.
    """

    kinetic: Callable = eqx.field(static=True)
    holonomic: Callable = eqx.field(static=True)
    dependent: tuple = eqx.field(static=True)
    constraints: Optional[Callable] = eqx.field(static=True, default=None)
    forces: Optional[Callable] = eqx.field(static=True, default=None)
    potential: Optional[Callable] = eqx.field(static=True, default=None)
    acceleration_energy: Optional[Callable] = eqx.field(static=True, default=None)
    names: Optional[tuple] = eqx.field(static=True, default=None)
    independent: Optional[tuple] = eqx.field(static=True, default=None)
    nonlinear_constraints: bool = eqx.field(static=True, default=False)
    guess: Optional[Callable] = eqx.field(static=True, default=None)
    iterations: int = eqx.field(static=True, default=8)
    tol: Optional[float] = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not callable(self.kinetic) or not callable(self.holonomic):
            raise TypeError("HolonomicMechanism: `kinetic` and `holonomic` must be functions")
        dep = tuple(self.dependent)
        if not dep or len(set(dep)) != len(dep) or not all(isinstance(i, int) and i >= 0 for i in dep):
            raise ValueError(
                f"HolonomicMechanism: `dependent` must be distinct coordinate indices ≥ 0; got {self.dependent!r}"
            )
        if self.independent is not None and set(self.independent) & set(dep):
            raise ValueError(
                f"HolonomicMechanism: independent velocities {tuple(self.independent)} include dependent "
                f"coordinates {tuple(sorted(set(self.independent) & set(dep)))}; their rates follow from ġ = 0"
            )
        if self.iterations < 1:
            raise ValueError(f"HolonomicMechanism: `iterations` must be ≥ 1; got {self.iterations}")

    # --- coordinates ------------------------------------------------------------

    def free(self, s: int) -> tuple:
        """Indices of the s − h independent coordinates q_I."""
        return tuple(i for i in range(s) if i not in self.dependent)

    def _assemble(self, q_ind, q_dep):
        s = q_ind.shape[0] + q_dep.shape[0]
        if max(self.dependent) >= s:
            raise ValueError(f"HolonomicMechanism: dependent index {max(self.dependent)} ≥ s = {s} coordinates")
        parts = [None] * s
        for j, i in enumerate(self.free(s)):
            parts[i] = q_ind[j]
        for j, i in enumerate(self.dependent):
            parts[i] = q_dep[j]
        return jnp.stack(parts)

    def _residual(self, q, t, p):
        g = jnp.asarray(self.holonomic(q, t, p))
        if g.shape != (len(self.dependent),):
            raise ValueError(
                f"HolonomicMechanism `holonomic` must return shape ({len(self.dependent)},) — one value per "
                f"dependent coordinate {self.dependent}; got {g.shape}"
            )
        return g

    def coordinates(self, q_ind, t, params, start=None):
        """All coordinates q (s,) from the independent ones q_I (s − h,).

        The dependent coordinates solve `g(q, t) = 0` by Newton's method from
        `start` (default `guess`, else zeros); the result is differentiable
        in q_I, t and the array leaves of params, to any order, by the
        implicit function theorem. NaN if Newton missed `tol`.
        """
        q_ind = as_float(q_ind)
        t = as_time(t, q_ind)
        h = len(self.dependent)
        if start is None:
            start = self.guess(q_ind, t, params) if self.guess is not None else jnp.zeros((h,), q_ind.dtype)
        start = jax.lax.stop_gradient(jnp.asarray(start, dtype=q_ind.dtype))
        dyn, static = eqx.partition(params, eqx.is_inexact_array)

        def g_of(qi, x, t_, dyn_):
            return self._residual(self._assemble(qi, x), t_, eqx.combine(dyn_, static))

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
        return self._assemble(q_ind, solve(q_ind, t, dyn, start))

    def _jacobians(self, q, t, params):
        """G_D (h, h), G_I (h, s − h) and ∂g/∂t (h,) at q."""
        s = q.shape[0]
        G, gt = jax.jacfwd(self._residual, argnums=(0, 1))(q, t, params)
        GD = jnp.stack([G[:, i] for i in self.dependent], axis=1)
        GI = jnp.stack([G[:, i] for i in self.free(s)], axis=1)
        return GD, GI, gt

    def velocities(self, q, qd_ind, t, params):
        """All q̇ (s,) at coordinates q with g = 0, from the independent rates q̇_I.

        `q̇_D = −G_D⁻¹ (G_I q̇_I + ∂g/∂t)` (ġ = 0), with `G = ∂g/∂q`.
        """
        GD, GI, gt = self._jacobians(q, t, params)
        return self._assemble(qd_ind, solve_square(GD, -(GI @ qd_ind + gt)))

    def accelerations(self, q, qd, qdd_ind, t, params):
        """All q̈ (s,) at a consistent (q, q̇), from the independent accelerations q̈_I.

        `q̈_D = −G_D⁻¹ (G_I q̈_I + γ)` (g̈ = 0), with `γ = (∂ġ/∂q) q̇ + ∂ġ/∂t`.
        """

        def gdot(q_, t_):
            return jax.jvp(lambda x, tt: self._residual(x, tt, params), (q_, t_), (qd, jnp.ones_like(t_)))[1]

        _, gamma = jax.jvp(gdot, (q, t), (qd, jnp.ones_like(t)))
        GD, GI, _ = self._jacobians(q, t, params)
        return self._assemble(qdd_ind, solve_square(GD, -(GI @ qdd_ind + gamma)))

    def coordinates_and_velocities(self, q_ind, qd_ind, t, params):
        """q (s,) and q̇ (s,) from independent coordinates and their rates (g = 0, ġ = 0).

        The velocities are written out from the Jacobian of g (not by
        differentiating the Newton solve), which keeps nested derivatives
        of the reduced mechanism small.
        """
        q_ind = as_float(q_ind)
        t = as_time(t, q_ind)
        q = self.coordinates(q_ind, t, params)
        return q, self.velocities(q, jnp.asarray(qd_ind, q_ind.dtype), t, params)

    def restore(self, q, t, params):
        """q with its dependent coordinates re-solved from its independent ones (Newton from q_D)."""
        q = as_float(q)
        return self.coordinates(pick(q, self.free(q.shape[0])), t, params, start=pick(q, self.dependent))

    def project(self, q, t, params, iterations: int = 4):
        """The coordinates nearest to q (Euclidean) with g = 0, by Gauss–Newton.

        Use it to remove the drift of `g` in a "lagrange" simulation of the
        differentiated mechanism (coordinates of mixed units are weighted
        equally).
        """
        q = as_float(q)
        t = as_time(t, q)
        for _ in range(iterations):
            g = self._residual(q, t, params)
            G = jax.jacfwd(lambda x: self._residual(x, t, params))(q)
            q = q - G.T @ solve_square(G @ G.T, g)
        return q

    def residuals(self, q, qd, t, params):
        """Constraint values at a state: `g` (h,), `ġ` (h,) and the nonholonomic `c` (m,)."""
        q = as_float(q)
        t = as_time(t, q)
        g, gd = jax.jvp(
            lambda x, t_: self._residual(x, t_, params), (q, t), (jnp.asarray(qd, q.dtype), jnp.ones_like(t))
        )
        c = self.constraints(q, qd, t, params) if self.constraints is not None else jnp.zeros((0,), q.dtype)
        return {"holonomic": g, "holonomic_rate": gd, "nonholonomic": jnp.asarray(c)}

    # --- the two representations as ordinary mechanisms ----------------------------

    def differentiated(self) -> Mechanism:
        """All s coordinates; constraints `[c(q, q̇, t), ġ(q, q̇, t)]` (the nonholonomic first).

        With method "lagrange" the holonomic constraint is thus imposed as
        `g̈ = 0`: the multipliers of the last h constraints are the holonomic
        constraint forces. (Cached: the same object for the same mechanism.)
        """
        return _differentiated(self)

    def _build_differentiated(self) -> Mechanism:
        c, g = self.constraints, self._residual

        def constraints(q, qd, t, p):
            _, gd = jax.jvp(lambda x, t_: g(x, t_, p), (q, t), (qd, jnp.ones_like(t)))
            return gd if c is None else jnp.concatenate([jnp.asarray(c(q, qd, t, p)), gd])

        return Mechanism(
            self.kinetic,
            constraints=constraints,
            forces=self.forces,
            potential=self.potential,
            acceleration_energy=self.acceleration_energy,
            names=self.names,
            independent=self.independent,
            nonlinear_constraints=self.nonlinear_constraints,
        )

    def reduced_names(self, s: int) -> Optional[tuple]:
        """Names of the independent coordinates (None if no names were given)."""
        return None if self.names is None else tuple(self.names[i] for i in self.free(s))

    def reduced_independent(self, s: int) -> Optional[tuple]:
        """`independent` translated to positions among the independent coordinates."""
        if self.independent is None:
            return None
        free = self.free(s)
        return tuple(free.index(i) for i in self.independent)

    def reduced(self, s: Optional[int] = None) -> Mechanism:
        """The mechanism in the s − h independent coordinates q_I.

        T, V, Q, S and c are those of the full mechanism evaluated at
        `q = coordinates(q_I)`, `q̇ = (∂q/∂q_I) q̇_I + ∂q/∂t` (and q̈ likewise);
        the generalized forces are `(∂q/∂q_I)ᵀ Q`. `s` (the number of all
        coordinates) is needed for `names` and `independent` only. (Cached.)
        """
        return _reduced(self, s)

    def _build_reduced(self, s: Optional[int] = None) -> Mechanism:
        full = self.coordinates_and_velocities

        def kinetic(qi, qdi, t, p):
            q, qd = full(qi, qdi, t, p)
            return self.kinetic(q, qd, t, p)

        # The optional functions below are passed on only when the full mechanism has them.
        def acceleration_energy(qi, qdi, qddi, t, p):
            assert self.acceleration_energy is not None
            q, qd = full(qi, qdi, t, p)
            return self.acceleration_energy(q, qd, self.accelerations(q, qd, qddi, t, p), t, p)

        def potential(qi, t, p):
            assert self.potential is not None
            return self.potential(self.coordinates(qi, t, p), t, p)

        def forces(qi, qdi, t, p):
            # virtual work Q · δq with δq = J δq_I, J = [I; −G_D⁻¹ G_I]
            assert self.forces is not None
            q, qd = full(qi, qdi, t, p)
            Q = jnp.asarray(self.forces(q, qd, t, p), qi.dtype)
            GD, GI, _ = self._jacobians(q, t, p)
            s = q.shape[0]
            return pick(Q, self.free(s)) + solve_square(GD, -GI).T @ pick(Q, self.dependent)

        def constraints(qi, qdi, t, p):
            assert self.constraints is not None
            q, qd = full(qi, qdi, t, p)
            return self.constraints(q, qd, t, p)

        return Mechanism(
            kinetic,
            constraints=constraints if self.constraints is not None else None,
            forces=forces if self.forces is not None else None,
            potential=potential if self.potential is not None else None,
            acceleration_energy=acceleration_energy if self.acceleration_energy is not None else None,
            names=self.reduced_names(s) if s is not None else None,
            independent=self.reduced_independent(s) if s is not None else None,
            nonlinear_constraints=self.nonlinear_constraints,
        )

    # --- consistent initial conditions and simulation --------------------------------

    def initial_state(self, q, qd, t, params, independent=None):
        """Consistent (q, q̇) from the independent coordinates and velocities in (q, qd).

        The dependent coordinates are re-solved from g = 0 (Newton started
        at the given q_D); the dependent velocities are solved from
        `c(q, q̇, t) = 0` and `ġ = 0` with the independent velocities
        (indices `independent`, default `self.independent`, else chosen at
        this state) kept as given.

        Returns:
            q (s,), q̇ (s,).
        """
        q = as_float(q)
        qd = jnp.asarray(qd, q.dtype)
        t = as_time(t, q)
        params = as_data(params, q)
        s = q.shape[0]
        q = _restore(self, q, t, params)
        if not isinstance(q, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(q))):
            raise ValueError(
                f"HolonomicMechanism.initial_state: Newton's method found no dependent coordinates "
                f"{self.dependent} with g = 0 from the given q (|g| > tol after {self.iterations} "
                "iterations, or ∂g/∂q_D singular there); start from dependent coordinates closer to a solution"
            )
        mech = self.differentiated()
        m = mech.check_shapes(q, qd, t, params)
        ind = independent if independent is not None else self.independent
        if ind is None:
            ind = choose_independent(mech, q, qd, t, params)
        return q, _complete_velocities(mech, check_independent(ind, s, m), q, qd, t, params)

    def expand(self, sol, params):
        """A `Solution` of `reduced()` rewritten in all s coordinates."""
        s = sol.q.shape[-1] + len(self.dependent)
        q, qd = _expand(self, sol.q, sol.qd, sol.ts, as_data(params, sol.q))
        names = tuple(self.names) if self.names is not None else tuple(f"q{i}" for i in range(s))
        return type(sol)(
            ts=sol.ts,
            q=q,
            qd=qd,
            multipliers=sol.multipliers,
            energy=sol.energy,
            residual=sol.residual,
            stats=sol.stats,
            status=sol.status,
            names=names,
        )

    def simulate(self, params, q0, qd0, ts, method: str = "appell", **kwargs):
        """Integrate from the consistent completion of (q0, qd0); full coordinates out.

        "lagrange": `differentiated()` with multipliers (g̈ = 0; g drifts at
        the level of the tolerances). "appell": `reduced()` with Appell's
        equations (g = 0 to Newton accuracy at every step). Other keyword
        arguments go to `jaxnh.simulate`; `independent` is given in all s
        coordinates. The recorded "residual" and "multipliers" are those of
        the mechanism integrated (for "lagrange" the last h entries belong
        to ġ = 0).
        """
        independent = kwargs.pop("independent", None)
        q0, qd0 = self.initial_state(q0, qd0, ts[0], params, independent)
        s = q0.shape[0]
        ind = independent if independent is not None else self.independent
        if method == "lagrange":
            return simulate(self.differentiated(), params, q0, qd0, ts, method="lagrange", **kwargs)
        if method != "appell":
            raise ValueError(f"HolonomicMechanism.simulate: method must be 'lagrange' or 'appell'; got {method!r}")
        free = self.free(s)
        red_ind = None if ind is None else tuple(free.index(i) for i in ind)
        mech = self.reduced(s)
        sol = simulate(
            mech, params, pick(q0, free), pick(qd0, free), ts, method="appell", independent=red_ind, **kwargs
        )
        return self.expand(sol, params)


# cached builders: the same HolonomicMechanism always gives the same Mechanism
# object, so compiled simulations are reused instead of retraced


@functools.lru_cache(maxsize=64)
def _differentiated(hm: HolonomicMechanism) -> Mechanism:
    return hm._build_differentiated()


@functools.lru_cache(maxsize=64)
def _reduced(hm: HolonomicMechanism, s) -> Mechanism:
    return hm._build_reduced(s)


# compiled helpers (the Newton loop would otherwise be compiled anew at every eager call)


@eqx.filter_jit
def _restore(hm: HolonomicMechanism, q, t, params):
    return hm.restore(q, t, params)


@eqx.filter_jit
def _complete_velocities(mech: Mechanism, independent: tuple, q, qd, t, params):
    s = q.shape[0]
    split = VelocitySplit(mech, s, s - len(independent))
    return split.velocities(q, split.independent_of(qd, independent), t, params, independent)


@eqx.filter_jit
def _expand(hm: HolonomicMechanism, q, qd, ts, params):
    return jax.vmap(lambda a, b, t: hm.coordinates_and_velocities(a, b, t, params))(q, qd, ts)
