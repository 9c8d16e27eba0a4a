"""Appell's (Gibbs–Appell) equations (paper eqs. 17–18).

With the independent velocities v and qd = B v + β0 (eq. 17), the
accelerations are `qdd = B vd + β`, and Appell's equations are

    Bᵀ ∂S/∂qdd (q, qd, B vd + β, t) = Bᵀ Q           (eq. 18)

for the k = s − m independent accelerations vd only. S is the user's
acceleration energy when given (it must be quadratic in qdd, as every
mechanical S is, so one Newton step solves it exactly); otherwise its
acceleration-dependent part is built from T, `S = ½ qddᵀ M qdd + qddᵀ h`,
whose gradient is the Lagrange expression `M qdd + h`. The reduced system
matrix `Bᵀ M B` is symmetric positive definite. The dependent velocities come
from the constraints, so they cannot drift. Multipliers are recovered from the
accelerations only when recorded.

Which velocities are independent (the partition, `jaxnh._equations.split`):

* `Appell(independent=(0,))` fixes it; the state is y = [q, v] (one flat
  vector: diffrax's stages and error norm then cost one operation per
  step, not one per part). A run in which the
  dependent block becomes singular fails with `STATUS.singular_split`.
* `Appell()` (the default) chooses it inside the compiled program from the
  constraint matrix, its columns scaled by the mass matrix
  (`split.mass_scaled_matrix`: a choice that does not depend on the units of
  the coordinates), at the initial state (per batch member under `vmap`) and
  re-chooses it before any step at which the dependent block has become
  ill-conditioned (its volume below `SWITCH_BELOW` of the best block's);
  a step during which the block's determinant changes sign is rejected and
  retried shorter. The state is y = [q, v, dependent], the partition
  carried as the m dependent indices (ascending, as floats), which the
  step-size control ignores: m entries rather than a permutation of s, as
  every entry of the state costs work in each stage of a step.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from jaxnh._base.linalg import mm, solve_spd
from jaxnh._base.status import STATUS
from jaxnh._equations.base import Formulation, multipliers_from_accelerations
from jaxnh._equations.scalarize import scalarized
from jaxnh._equations.split import (
    best_partition,
    block_determinant,
    constraint_matrix,
    partition_from_dependent,
    partition_quality,
    resolve_independent,
    select,
    split_regular,
    SWITCH_BELOW,
    VelocitySplit,
)
from jaxnh._equations.step_maps import normalize_quaternions, StepMaps
from jaxnh._equations.terms import projected_terms


class Appell(Formulation):
    """Gibbs–Appell equations in the independent velocities.

    Arguments:
        independent: indices of the independent velocities, fixed for the whole
            run; default None: chosen at the initial state and re-chosen during
            the run (see the module docstring).
        repartition: with `independent=None`, whether the choice may change
            during the run (default True).
    """

    independent: Optional[tuple] = eqx.field(static=True, default=None)
    repartition: bool = eqx.field(static=True, default=True)

    name = "appell"

    def bind(self, mech: eqx.Module, s: int, m: int, nq: Optional[int] = None) -> Appell:
        if m >= s:
            raise ValueError(
                f"method={self.name!r}: the mechanism has m={m} constraints for s={s} coordinates: no independent "
                "velocity is left for Appell's equations, or some constraints are linearly dependent (which they "
                "cannot use either); use method='lagrange'"
            )
        ind = resolve_independent(mech, self.independent, s, m)  # pyright: ignore[reportArgumentType]
        return dataclasses.replace(super().bind(mech, s, m, nq), independent=ind)  # pyright: ignore[reportReturnType, reportArgumentType]

    @property
    def split(self) -> VelocitySplit:
        return VelocitySplit(self.bound_mech, self.s, self.m)

    @property
    def traced(self) -> bool:
        """Whether the partition is data carried in the state."""
        return self.independent is None and self.m > 0

    def parts(self, y: jax.Array) -> tuple[jax.Array, jax.Array, Optional[jax.Array]]:
        """(q (nq,), v (k,), partition code (m,) or None) of a state y = [q, v, dependent indices]."""
        n, k = self.nq, self.s - self.m
        return y[:n], y[n : n + k], (y[n + k :] if self.traced else None)

    def partition(self, y: Optional[jax.Array]) -> tuple | jax.Array:
        """The partition in use for the state y."""
        if not self.traced:
            return self.independent if self.independent is not None else tuple(range(self.s))
        return partition_from_dependent(jnp.round(y[self.nq + self.s - self.m :]).astype(jnp.int32), self.s)  # pyright: ignore[reportOptionalSubscript]

    def state(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        if not self.traced:
            return jnp.concatenate([q, self.split.independent_of(qd, self.partition(None))])
        perm, _ = best_partition(self.bound_mech, q, qd, t, params, self.s, self.m)
        k = self.s - self.m
        return jnp.concatenate([q, select(qd, perm, k)[0], perm[k:].astype(q.dtype)])

    def unpack(self, y: jax.Array, t: jax.typing.ArrayLike, params: object) -> tuple[jax.Array, jax.Array]:
        q, v, _ = self.parts(y)
        q = normalize_quaternions(q, self.bound_mech.quaternions)  # (a report between steps: interpolated)
        return q, self.split.velocities(q, v, t, params, self.partition(y))

    def error_mask(self) -> Optional[tuple[float, ...]]:
        n = self.nq + self.s - self.m
        return (1.0,) * n + (0.0,) * self.m if self.traced else None

    def _independent_accelerations(self, q, v, t, params, part, start=None):
        mech = self.bound_mech
        qd, B, beta = self.split.velocities_and_rates(q, v, t, params, part, start)
        Q = mech.generalized_forces(q, qd, t, params)
        if mech.acceleration_energy is None:
            K, r = projected_terms(mech, q, qd, t, params, B, beta)
            rhs = mm(B.T, Q) - r
        else:
            dS = jax.grad(mech.acceleration_energy, argnums=2)
            g0, H = jax.linearize(lambda a: dS(q, qd, a, t, params), beta)
            K = mm(B.T, jax.vmap(H, in_axes=1, out_axes=1)(B))
            rhs = mm(B.T, Q - g0)
        vd = solve_spd(K, rhs)
        return qd, mm(B, vd) + beta, vd

    def _state_partition(self, q, qd, t, params, A=None, inertias=None):
        if not self.traced:
            return self.partition(None)
        return best_partition(self.bound_mech, q, qd, t, params, self.s, self.m, A, inertias)[0]

    def accelerations(
        self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object, multipliers: bool = False
    ) -> tuple[jax.Array, Optional[jax.Array]]:
        part = self._state_partition(q, qd, t, params)
        v = self.split.independent_of(qd, part)
        start = self.split.dependent_of(qd, part) if self.bound_mech.nonlinear_constraints else None
        qd, qdd, _ = self._independent_accelerations(q, v, t, params, part, start)
        lam = multipliers_from_accelerations(self.bound_mech, q, qd, qdd, t, params) if multipliers else None
        return qdd, lam

    def vector_field(self, t: jax.typing.ArrayLike, y: jax.Array, params: object) -> jax.Array:
        q, v, code = self.parts(y)
        qd, _, vd = self._independent_accelerations(q, v, t, params, self.partition(y))
        rate = self.rate(q, qd, t, params)
        return jnp.concatenate([rate, vd] + ([jnp.zeros_like(code)] if code is not None else [])).astype(y.dtype)

    def step_maps(self) -> Optional[StepMaps]:
        if self.m == 0:
            return None
        return _Partitioning(self.traced and self.repartition)

    def check(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object) -> tuple[jax.Array, STATUS]:
        return self._checked(q, qd, t, params, None, None)

    def check_given(
        self,
        q: jax.Array,
        qd: jax.Array,
        t: jax.typing.ArrayLike,
        params: object,
        A: Optional[jax.Array],
        inertias: Optional[jax.Array],
    ) -> tuple[jax.Array, STATUS]:
        if type(self).check is not Appell.check:  # a subclass's own check is the one to run
            return self.check(q, qd, t, params)
        return self._checked(q, qd, t, params, A, inertias)

    def _checked(self, q, qd, t, params, A, inertias) -> tuple[jax.Array, STATUS]:
        """`check` with A = ∂c/∂qd and the inertias at the state when given (None: evaluated here)."""
        if self.m == 0:
            return jnp.asarray(True), STATUS.successful  # pyright: ignore[reportReturnType]
        mech = self.bound_mech
        fixed = None if self.traced else self.partition(None)
        ok = split_regular(mech, q, qd, t, params, self.s, self.m, fixed, A, inertias)
        # (equinox types Enumerations as enum.Enum: an item STATUS inherits from diffrax looks like diffrax's)
        status = STATUS.where(ok, STATUS.successful, STATUS.singular_split)  # pyright: ignore[reportArgumentType]
        if self.bound_mech.nonlinear_constraints:  # the dependent velocities must be solvable at the start
            part = self._state_partition(q, qd, t, params, A, inertias)
            v = self.split.independent_of(qd, part)
            solved = self.split.velocities(q, v, t, params, part)  # from zero, as the vector field does
            unsolved = ok & ~jnp.all(jnp.isfinite(solved))
            status = STATUS.where(unsolved, STATUS.nonlinear_constraints_unsolved, status)
            ok = ok & ~unsolved
            # ... and on qd0's own root: Newton's method started at qd0's dependent velocities. Two
            # converged roots agree to rounding (eps times the Jacobian's condition) if they are the
            # same root, and differ by the distance between roots if not: √eps of the velocity scale
            own = self.split.velocities(q, v, t, params, part, self.split.dependent_of(qd, part))
            other = ok & jnp.all(jnp.isfinite(own)) & ~same_root(solved, own, qd)
            status = STATUS.where(other, STATUS.nonlinear_branch, status)
            ok = ok & ~other
        return ok, status


LEFT_ROOT = diffrax.RESULTS.breakdown
"""The step maps' failure (a diffrax result) for a run whose dependent velocities left the root
of constraints nonlinear in the velocities that the motion follows; `simulate` reports it as
`STATUS.nonlinear_root_left`. (No diffrax solve of these equations gives `breakdown` itself: it
comes from lineax's iterative linear solvers, which diffrax's solvers do not use here.)"""


def same_root(a: jax.Array, b: jax.Array, ref: jax.Array) -> jax.Array:
    """Whether two converged solutions a, b of constraints nonlinear in the velocities are the same
    root: they agree to √eps of the velocity scale max|ref| (m/s, rad/s). Two Newton solutions of
    one root agree to rounding (eps times the Jacobian's condition); distinct roots differ by the
    distance between them."""
    scale = jnp.max(jnp.abs(ref)) + jnp.finfo(ref.dtype).tiny
    return jnp.all(jnp.abs(a - b) <= jnp.sqrt(jnp.finfo(ref.dtype).eps) * scale)


class _Partitioning(StepMaps):
    """Watch (and, with `switch`, re-choose) the partition around every step.

    The solve's args are `(formulation, params, ok)`.
    """

    switch: bool = eqx.field(static=True)

    # Both maps are flattened to scalar operations for small mechanisms, as the vector field is
    # (`jaxnh._equations.scalarize`): they run at every step, and unflattened each of their tiny
    # array operations is a kernel of its own (variator: a step of simulate launched 60 kernels
    # with them unflattened, 51 flattened, against 29 for a step of the hand-written eq. (9)).

    def pre(self, t, y, args):
        if not self.switch:
            return y, False
        f, params, ok = args
        return scalarized(functools.partial(self._pre, f))(t, y, params, ok)

    @staticmethod
    def _pre(f, t, y, params, ok):
        q, v, _ = f.parts(y)
        perm = f.partition(y)
        if f.mech.nonlinear_constraints:
            qd, A = f.split.velocities(q, v, t, params, perm), None
        else:  # A = ∂c/∂qd does not depend on qd: the one the velocities were solved with
            qd, A = f.split.linear_velocities(q, v, t, params, perm)
        ratio, _, best = partition_quality(f.mech, q, qd, t, params, perm, f.s - f.m, A)
        switch = (ratio < SWITCH_BELOW) & ok  # a failed initial check: the (zero) state stays as it is
        k = f.s - f.m
        if f.mech.nonlinear_constraints:
            # the new dependent velocities are solved from zero at every evaluation: switch only to a
            # partition whose solution is the motion's root (qd), not another root of the constraints
            qd_best = f.split.velocities(q, select(qd, best, k)[0], t, params, best)
            switch = switch & same_root(qd_best, qd, qd)
        new = jnp.where(switch, best, perm)
        v_new = jnp.where(switch, select(qd, new, k)[0], v)
        return jnp.concatenate([q, v_new, new[k:].astype(y.dtype)]), switch

    def post(self, t0, y0, t1, y1, args):
        f, params, ok = args
        crossed, left = scalarized(functools.partial(self._watch, f))(t0, y0, t1, y1, params, ok)
        # a fixed partition cannot be changed: passing through a singular block fails the solve
        reject, singular = (crossed, False) if self.switch else (False, crossed)
        if not f.mech.nonlinear_constraints:
            return y1, None, reject, singular
        # (equinox types Enumerations as enum.Enum: RESULTS, inheriting from optimistix, looks like its)
        fail = diffrax.RESULTS.where(singular, diffrax.RESULTS.singular, diffrax.RESULTS.successful)  # pyright: ignore[reportArgumentType]
        fail = diffrax.RESULTS.where(left, LEFT_ROOT, fail)  # pyright: ignore[reportArgumentType]
        return y1, None, reject, fail

    @staticmethod
    def _watch(f, t0, y0, t1, y1, params, ok):
        """(crossed, left) for a step from (t0, y0) to (t1, y1); after a failed initial check (`ok`
        False: simulate's solve then has zero length, and a user's own diffeqsolve of `ode` gets a
        zero stand-in) nothing is watched.

        crossed: the dependent block's determinant changed sign (or became non-finite) in the step.
        left (constraints nonlinear in the velocities only, else False): at the end of the step the
        dependent velocities the equations solve for (Newton's method from zero, at every
        evaluation) are no longer the continuation of those at its start (Newton's method at the
        end state started from them): the motion's root has been left for another one, or for none.
        """
        part = f.partition(y1)
        nonlinear = f.mech.nonlinear_constraints
        qds, det = [], []
        for y, t in ((y0, t0), (y1, t1)):
            q = f.parts(y)[0]
            # A = ∂c/∂qd does not depend on qd for linear constraints: no velocity solve
            qd = f.unpack(y, t, params)[1] if nonlinear else jnp.zeros_like(q)
            qds.append(qd)
            det.append(block_determinant(constraint_matrix(f.mech, q, qd, t, params), part, f.s - f.m))
        crossed = ((jnp.sign(det[0]) != jnp.sign(det[1])) | ~jnp.isfinite(det[1])) & ok
        if not nonlinear:
            return crossed, jnp.asarray(False)
        q1, v1, _ = f.parts(y1)
        followed = f.split.velocities(q1, v1, t1, params, part, f.split.dependent_of(qds[0], part))
        left = ~same_root(qds[1], followed, followed) & jnp.all(jnp.isfinite(followed)) & ok
        return crossed, left
