"""Independent and dependent velocities (paper eq. 17), the one split used everywhere.

The m constraints `c(q, qd, t) = 0` are solved for m dependent velocities
`qd_D` given the k = s − m independent ones `v = qd_I`:

    qd = B(q, t) v + β0(q, t)      (linear constraints),

with `B = ∂qd/∂v`, the matrix of the paper's coefficients b_ai.

Which velocities are independent is a *partition* of the s velocity indices.
It is either

* a static tuple of independent indices (given by the user), or
* data: an integer permutation `perm` (s,) whose first k entries are the
  independent indices and whose last m are the dependent ones. Data can be
  chosen inside a compiled program from the constraint matrix at the current
  state, per batch member under `vmap`, and changed during a run.

The choice (`best_partition`) is generalized coordinate partitioning
(Wehage & Haug, J. Mech. Des. 104 (1982) 247–255) in the kinetic-energy
metric: with the columns of A = ∂c/∂qd divided by √M_jj (M the mass matrix,
`mass_scaled_matrix`) and the rows then scaled to unit length,
column-pivoted Gram–Schmidt picks the m dependent columns greedily by largest
remaining norm, which approximately maximises the volume |det A_D| — the
best-conditioned dependent block. `partition_quality` compares the volume of
the block in use with that of the best one: a ratio of 1 is the best choice,
0 a singular block.

Why the mass scaling: the dependent velocities are not integrated, they are
rebuilt from (q, v) at every stage, so they carry the error of everything
they are rebuilt from, and the step-size control, which sees (q, v) only,
never sees it. On the raw A the choice compared columns in the units of
their velocities, so it changed with the units of the coordinates. A ball of
radius r on a turntable, coordinates (x, y, quaternion): the column of ẋ (1)
beat the quaternion rates' (≈ 2r = 0.2 for r = 0.1 m), so the centre's
velocity was rebuilt from the quaternion and its rates, ẋ = r ω_y(e, ė) − Ω y,
and carried |ω| × the quaternion's orientation error: 1.3e-6 m after 50 s at
rtol 1e-8 against 2.2e-14 m with ẋ, ẏ independent (the partition chosen on
A M^-1/2, or on the raw A when r = 1 m): re-choosing the partition (237
times in that run) costs nothing, the choice does
(benchmarks/mechanisms/ball.py, ball_wp.py).
"""

from __future__ import annotations

from typing import Optional, Union

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxnh._base.linalg import pick, solve_square, value_and_jacfwd
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._model.mechanism import check_independent, Mechanism


NEWTON_ITERATIONS = 8  # for constraints nonlinear in qd; linear ones need one

SWITCH_BELOW = 0.9
"""A run re-chooses the partition when the dependent block's volume falls below
this fraction of the best available block's. The error of the dependent
velocities grows like the inverse of that volume, and so do the derivatives of
the reduced vector field near a singular block, which shrink the steps and get
them rejected (at 0.25 the knife edge's steps before every switch were cut by
up to 2.5×). Switching early costs one re-evaluation of the field's first
stage per switch and keeps the block near its best: from 0.5 to 0.9 the
knife edge (20 s, rtol 1e-10) took 242 steps instead of 293 (42 rejected
instead of 70), and the rolling ball on a turntable (20 s, rtol 1e-6 … 1e-12)
355–1392 instead of 518–1687, at the same errors. A switch lands on a block
with ratio 1, so the band [0.9, 1] keeps two nearly equal blocks from
alternating at every step; a switch maps the state exactly."""

Partition = Union[tuple, jax.Array]


def constraint_matrix(mech: Mechanism, q, qd, t, params):
    """A = ∂c/∂qd (m, s) at one state."""
    return jax.jacfwd(lambda v: mech.constraint(q, v, t, params))(qd)


def mass_scaled_matrix(mech: Mechanism, q, qd, t, params, A=None, inertias=None):
    """A = ∂c/∂qd (m, s) with column j divided by √M_jj (M = ∂²T/∂qd², the mass matrix).

    The partition is chosen on this matrix, not on A: a column of A is in the
    units of its velocity (∂c/∂ẋ per m/s, ∂c/∂φ̇ per rad/s, a quaternion rate per
    1/s), so comparing columns of A compares numbers whose ratio changes with
    the units of the coordinates (metres against millimetres, or the radius of a
    ball against its quaternion). Divided by √M_jj every column is per √(kinetic
    energy), and the choice no longer depends on how any coordinate is scaled:
    heavy velocities (large M_jj) are kept independent and light ones, which can
    follow from them without amplifying their error in the kinetic-energy
    norm, become dependent. `A` and `inertias` (the mass matrix's diagonal): their values at the
    state, when the caller has them already.
    """
    A = constraint_matrix(mech, q, qd, t, params) if A is None else A
    if A.shape[0] == 0:
        return A
    d = jnp.diagonal(jax.hessian(lambda v: mech.kinetic(q, v, t, params))(qd)) if inertias is None else inertias
    d = jnp.where(d > 0, d, 1.0)  # (a mass matrix that is not positive definite is reported by the checks)
    return A / jnp.sqrt(d).astype(A.dtype)[None, :]


def unit_rows(A):
    """A with each row scaled to unit Euclidean norm (rows of zeros stay zero)."""
    n = jnp.linalg.norm(A, axis=1, keepdims=True)
    return A / jnp.where(n > 0, n, 1.0)


def best_dependent(A) -> tuple[jax.Array, jax.Array]:
    """Greedy column-pivoted Gram–Schmidt on the row-normalised A (m, s) (mass-scaled by the callers).

    Returns the m dependent column indices (int32, in pivot order) and the
    volume they span (the product of the pivots: |det| of the chosen block of
    the row-normalised matrix, up to the Gram–Schmidt orthogonalisation).
    """
    A = unit_rows(A)
    m, s = A.shape
    R = A
    taken = jnp.zeros((s,), bool)
    idx, vol = [], jnp.ones((), A.dtype)
    for _ in range(m):
        norms = jnp.where(taken, -1.0, jnp.sum(R * R, axis=0))
        p = jnp.argmax(norms)
        col = R[:, p]
        nrm = jnp.sqrt(jnp.maximum(norms[p], 0.0))
        u = col / jnp.where(nrm > 0, nrm, 1.0)
        R = R - u[:, None] * (u @ R)[None, :]
        taken = taken.at[p].set(True)
        idx.append(p)
        vol = vol * nrm
    return jnp.stack(idx).astype(jnp.int32), vol


def best_block_margin(mech: Mechanism, q, qd, t, params, m: int, A=None, inertias=None):
    """The smallest singular value of the best dependent block (the one `best_partition` picks) of
    the row-normalised, mass-scaled A: how far the automatic split is from a singular block.

    The block's volume (|det|, the product of its singular values) is no such measure: it falls
    geometrically with m on well-conditioned blocks (a car pulling N trailers: 3e-3, 1e-7 and
    1e-18 at N = 8, 16 and 32, every block well conditioned), while the smallest singular value
    does not depend on m. It equals the volume for m = 1 (dimensionless, at most 1). `A`,
    `inertias`: as for `mass_scaled_matrix`."""
    A = mass_scaled_matrix(mech, q, qd, t, params, A, inertias)
    if m == 0:
        return jnp.ones((), q.dtype)
    dep, _ = best_dependent(A)
    D = unit_rows(A)[:, dep]
    return jnp.linalg.svd(jax.lax.stop_gradient(D), compute_uv=False)[-1]


def partition_from_dependent(dep, s: int):
    """The permutation (s,) int32: independent indices ascending, then the dependent ones
    ascending, from the m dependent indices `dep` (in any order).

    Written with comparisons and running sums, not a sort, so that it fuses with the
    arithmetic around it (the vector field decodes the partition at every evaluation)."""
    dep = jnp.asarray(dep, jnp.int32)
    m = dep.shape[0]
    cols = jnp.arange(s, dtype=jnp.int32)
    is_dep = jnp.any(dep[:, None] == cols[None, :], axis=0) if m else jnp.zeros((s,), bool)
    indep = ~is_dep
    out = []
    for mask, count in ((indep, s - m), (is_dep, m)):
        # rank[j]: how many entries of the group come before j
        ranks, acc = [], jnp.zeros((), jnp.int32)
        for j in range(s):
            ranks.append(acc)
            acc = acc + mask[j].astype(jnp.int32)
        rank = jnp.stack(ranks)
        hit = mask[None, :] & (rank[None, :] == jnp.arange(count, dtype=jnp.int32)[:, None])
        out.append(jnp.sum(jnp.where(hit, cols[None, :], 0), axis=1).astype(jnp.int32))
    return jnp.concatenate(out)


def best_partition(mech: Mechanism, q, qd, t, params, s: int, m: int, A=None, inertias=None):
    """The best-conditioned partition at a state, as data: (perm (s,) int32, volume). `A`,
    `inertias`: as for `mass_scaled_matrix`."""
    if m == 0:
        return jnp.arange(s, dtype=jnp.int32), jnp.ones((), q.dtype)
    dep, vol = best_dependent(mass_scaled_matrix(mech, q, qd, t, params, A, inertias))
    return partition_from_dependent(dep, s), vol


def permutation(part: Partition, s: int):
    """The permutation (s,) int32 of a partition (static tuples included)."""
    if isinstance(part, tuple):
        dep = tuple(i for i in range(s) if i not in part)
        return jnp.asarray(part + dep, dtype=jnp.int32)
    return part


def block_determinant(A, part: Partition, k: int):
    """Signed det of the dependent block of the row-normalised A (1 when m = 0)."""
    m, s = A.shape
    if m == 0:
        return jnp.ones((), A.dtype)
    _, AD = _columns(unit_rows(A), part, k)
    return _det(AD)


def _det(D):
    """det of a square matrix: written out for m ≤ 3 (arithmetic that fuses with what is around it,
    where an LU factorisation is a kernel of its own at every step), LU above."""
    m = D.shape[0]
    if m == 1:
        return D[0, 0]
    if m == 2:
        return D[0, 0] * D[1, 1] - D[0, 1] * D[1, 0]
    if m == 3:
        return (
            D[0, 0] * (D[1, 1] * D[2, 2] - D[1, 2] * D[2, 1])
            - D[0, 1] * (D[1, 0] * D[2, 2] - D[1, 2] * D[2, 0])
            + D[0, 2] * (D[1, 0] * D[2, 1] - D[1, 1] * D[2, 0])
        )
    return jnp.linalg.det(D)


def partition_quality(mech: Mechanism, q, qd, t, params, part: Partition, k: int, A=None, inertias=None):
    """(|det A_D| / best volume, signed det A_D, best perm): how good the block in use is.

    The ratio is 1 for the best block greedy pivoting finds and 0 for a
    singular block (both on the row-normalised, mass-scaled A of
    `mass_scaled_matrix`). `A`, `inertias`: as for `mass_scaled_matrix`.
    """
    s = jnp.shape(qd)[0]
    A = mass_scaled_matrix(mech, q, qd, t, params, A, inertias)
    if A.shape[0] == 0:
        one = jnp.ones((), q.dtype)
        return one, one, jnp.arange(s, dtype=jnp.int32)
    det = block_determinant(A, part, k)
    dep, best = best_dependent(A)
    ratio = jnp.abs(det) / jnp.where(best > 0, best, 1.0)
    ratio = jnp.where(best > 0, ratio, 0.0)
    return ratio, det, partition_from_dependent(dep, s)


def split_regular(mech: Mechanism, q, qd, t, params, s: int, m: int, independent=None, A=None, inertias=None):
    """Whether Appell's split at a state is usable, the one test of every solve's initial checks:
    for the automatic split (`independent` None), the best dependent block's smallest singular
    value (`best_block_margin`) is above 1e3 eps; for fixed `independent` velocities, their
    block's |det| is above 1e3 eps of the best block's (`partition_quality`). Both judge the
    row-normalised, mass-scaled A, so neither depends on units or, for the automatic split,
    on m. `A`, `inertias`: as for `mass_scaled_matrix`."""
    tiny = 1e3 * jnp.finfo(q.dtype).eps
    if m == 0:
        return jnp.asarray(True)
    if independent is None:
        return best_block_margin(mech, q, qd, t, params, m, A, inertias) > tiny
    return partition_quality(mech, q, qd, t, params, independent, s - m, A, inertias)[0] > tiny


def _one_hot(perm, s, dtype):
    return jax.nn.one_hot(perm, s, dtype=dtype)  # P[j, perm[j]] = 1


def _columns(A, part: Partition, k: int):
    """(A_I, A_D): the independent and dependent columns of A (m, s)."""
    s = A.shape[1]
    if isinstance(part, tuple):
        dep = tuple(i for i in range(s) if i not in part)
        return _stack_cols(A, part), _stack_cols(A, dep)
    Ap = A @ _one_hot(part, s, A.dtype).T
    return Ap[:, :k], Ap[:, k:]


def _stack_cols(A, idx):
    return jnp.stack([A[:, i] for i in idx], axis=1) if idx else A[:, :0]


def select(x, part: Partition, k: int):
    """(x_I (k, ...), x_D (m, ...)): entries of x (s, ...) split by the partition."""
    s = x.shape[0]
    if isinstance(part, tuple):
        dep = tuple(i for i in range(s) if i not in part)
        return pick(x, part), pick(x, dep)
    xp = jnp.tensordot(_one_hot(part, s, x.dtype), x, axes=1)
    return xp[:k], xp[k:]


def place(top, bottom, part: Partition):
    """x (s, ...) with x_I = top (k, ...) and x_D = bottom (m, ...)."""
    k, m = top.shape[0], bottom.shape[0]
    s = k + m
    if isinstance(part, tuple):
        dep = tuple(i for i in range(s) if i not in part)
        parts = [None] * s
        for j, i in enumerate(part):
            parts[i] = top[j]
        for j, i in enumerate(dep):
            parts[i] = bottom[j]
        return jnp.stack(parts)
    xp = jnp.concatenate([top, bottom], axis=0)
    return jnp.tensordot(_one_hot(part, s, xp.dtype).T, xp, axes=1)


def _converged(c_dep, x, jacobian):
    """x where Newton's method has converged (|c| ≤ √eps of the constraint's scale
    |∂c/∂x| |x| + |c(0)|, in every row), else NaN: a velocity that does not satisfy the
    constraints is never returned (a solve reports `STATUS.nonlinear_constraints_unsolved`).

    √eps: the iteration converges quadratically, so a converged x leaves a residual at the
    rounding level (a few eps of the scale), while a diverging or stalled one leaves a
    residual of the order of the scale itself."""
    value = c_dep(x)
    scale = jnp.sum(jnp.abs(jax.lax.stop_gradient(jacobian) * x), axis=1) + jnp.abs(c_dep(jnp.zeros_like(x)))
    scale = jax.lax.stop_gradient(scale) + jnp.finfo(x.dtype).tiny
    ok = jnp.all(jnp.abs(jax.lax.stop_gradient(value)) <= jnp.sqrt(jnp.finfo(x.dtype).eps) * scale)
    return jnp.where(ok, x, jnp.nan)


class VelocitySplit(eqx.Module):
    """Map from independent velocities v to all velocities qd, for one mechanism.

    Every method takes the partition `part` (a static tuple of independent
    indices, or a permutation array, see the module docstring).
    """

    mech: Mechanism
    s: int = eqx.field(static=True)
    m: int = eqx.field(static=True)

    @property
    def k(self) -> int:
        """Number of independent velocities (degrees of freedom), s − m."""
        return self.s - self.m

    def independent_of(self, qd: jax.Array, part: Partition) -> jax.Array:
        """The independent velocities v (k,) picked out of qd (s,)."""
        return select(qd, part, self.k)[0]

    def dependent_of(self, qd: jax.Array, part: Partition) -> jax.Array:
        """The dependent velocities (m,) picked out of qd (s,)."""
        return select(qd, part, self.k)[1]

    def velocities(
        self,
        q: jax.Array,
        v: jax.Array,
        t: jax.typing.ArrayLike,
        params: PyTree,
        part: Partition,
        start: Optional[jax.Array] = None,
    ) -> jax.Array:
        """All velocities qd (s,) satisfying the constraints, from independent v (k,).

        For constraints nonlinear in the velocities, Newton's method starts at `start` (the
        dependent velocities (m,) of a known nearby state: it then stays on that state's root)
        or, without one, at zero."""
        if self.m == 0:
            return place(v, v[:0], part)
        if not self.mech.nonlinear_constraints:
            return self.linear_velocities(q, v, t, params, part)[0]

        def c_dep(x):
            return self.mech.constraint(q, place(v, x, part), t, params)

        x = jnp.zeros((self.m,), v.dtype) if start is None else jax.lax.stop_gradient(start).astype(v.dtype)
        for _ in range(NEWTON_ITERATIONS):
            value, jacobian = value_and_jacfwd(c_dep, x)
            x = x - solve_square(jacobian, value)
        return place(v, _converged(c_dep, x, jacobian), part)

    def velocities_and_rates(
        self,
        q: jax.Array,
        v: jax.Array,
        t: jax.typing.ArrayLike,
        params: PyTree,
        part: Partition,
        start: Optional[jax.Array] = None,
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """qd (s,), B = ∂qd/∂v (s, k) and β = dqd/dt at dv/dt = 0 (s,) (`start`: as for
        `velocities`)."""
        if self.m == 0:
            B = place(jnp.eye(self.k, dtype=q.dtype), jnp.zeros((0, self.k), q.dtype), part)
            return place(v, v[:0], part), B, jnp.zeros((self.s,), q.dtype)
        if not self.mech.nonlinear_constraints:
            return self._linear(q, v, t, params, part)
        qd = self.velocities(q, v, t, params, part, start)
        B = jax.jacfwd(self.velocities, argnums=1)(q, v, t, params, part, start)
        _, beta = jax.jvp(
            lambda q_, t_: self.velocities(q_, v, t_, params, part, start),
            (q, t),
            (self.mech.rate(q, qd, t, params), jnp.ones_like(t)),
        )
        return qd, B, beta

    def linear_velocities(self, q, v, t, params, part: Partition) -> tuple[jax.Array, jax.Array]:
        """For constraints linear in the velocities: (qd (s,) from v (k,), A = ∂c/∂qd (m, s)), the
        matrix the solve for qd used (it does not depend on qd), for a caller that needs both.
        qd comes from `A_D q̇_D = −(A_I v + a)` alone (no B or β to trace)."""
        a, A, AI, AD = self._linear_terms(q, t, params, part)
        return place(v, solve_square(AD, -(jnp.sum(AI * v, axis=1) + a)), part), A

    def _linear_terms(self, q, t, params, part: Partition):
        """a = c(q, 0, t), A = ∂c/∂q̇ and its columns A_I, A_D (one pass over c)."""
        mech = self.mech
        a, A = value_and_jacfwd(lambda u: mech.constraint(q, u, t, params), jnp.zeros((self.s,), q.dtype))
        AI, AD = _columns(A, part, self.k)
        return a, A, AI, AD

    def _linear(self, q, v, t, params, part: Partition):
        """For `A q̇ + a = 0`: `B = [I; −A_D⁻¹ A_I]` and `A_D β_D = −b` written out.

        No derivative passes through the solve, which keeps the nested
        derivatives of the Appell vector field small (Whipple bicycle:
        12.2k → 8.4k traced operations).
        """
        mech, k = self.mech, self.k
        a, _, AI, AD = self._linear_terms(q, t, params, part)
        # one elimination gives the dependent velocities and the columns of B
        X = solve_square(AD, -jnp.concatenate([(jnp.sum(AI * v, axis=1) + a)[:, None], AI], axis=1))
        qd = place(v, X[:, 0], part)
        B = place(jnp.eye(k, dtype=q.dtype), X[:, 1:], part)
        rate = mech.rate(q, qd, t, params)
        _, b = jax.jvp(lambda q_, t_: mech.constraint(q_, qd, t_, params), (q, t), (rate, jnp.ones_like(t)))
        return qd, B, place(jnp.zeros_like(v), solve_square(AD, -b), part)


def resolve_independent(mech: Mechanism, independent, s: int, m: int) -> Optional[tuple]:
    """The one resolution of `independent`: the argument, else `mech.independent`,
    else None (the partition is then chosen as data at the state)."""
    if independent is None:
        independent = mech.independent
    if independent is None:
        return None
    return check_independent(independent, s, m)


def choose_independent(
    mech: Mechanism, q: ArrayInput, qd: ArrayInput, t: ArrayInput, params: PyTree
) -> tuple[int, ...]:
    """Indices of the s − m independent velocities that the automatic choice would
    take at a concrete state (for display, or to fix a partition by hand).

    `simulate` and `linearize` do not need it: they choose the partition inside
    the compiled program, also under `jit`/`vmap`/`grad`.
    """
    q = jnp.asarray(q)
    s = jnp.asarray(qd).shape[0]
    m = mech.check_shapes(q, qd, t, params)
    perm, vol = _best_partition_jit(mech, q, jnp.asarray(qd, q.dtype), t, params, s, m)
    if m and not float(vol) > 1e3 * float(jnp.finfo(q.dtype).eps):
        raise ValueError(
            f"the {m} constraints are linearly dependent at this state (rank of ∂c/∂qd < {m}); the Appell "
            "and substituted formulations need independent constraints: remove the redundant ones or use "
            "method='lagrange'."
        )
    return tuple(sorted(int(i) for i in perm[: s - m]))


@eqx.filter_jit
def _best_partition_jit(mech, q, qd, t, params, s, m):
    return best_partition(mech, q, qd, t, params, s, m)
