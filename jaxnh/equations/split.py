"""Independent and dependent velocities (paper eq. 17).

The m constraints `c(q, qd, t) = 0` are solved for m dependent velocities
`qd_D` given the s − m independent ones `v = qd_I`:

    qd = B(q, t) v + β0(q, t)      (linear constraints),

with `B = ∂qd/∂v`, the matrix of the paper's coefficients b_ai. The split is a
static choice of indices, made by the user or by `choose_independent` from the
constraint matrix at the initial state (column-pivoted QR picks the best
conditioned dependent block).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from ..linalg import solve_square
from .._mechanism import Mechanism, check_independent

NEWTON_ITERATIONS = 8  # for constraints nonlinear in qd; linear ones need one


@eqx.filter_jit
def constraint_matrix(mech: Mechanism, q, qd, t, params):
    """A = ∂c/∂qd (m, s) at one state, compiled once per mechanism and shapes.

    (Evaluated eagerly, the Jacobian dispatched some forty operations one by
    one on every `simulate` call, each compiled on first use.)
    """
    return jax.jacfwd(lambda v: mech.constraint(q, v, t, params))(qd)


def choose_independent(mech: Mechanism, q, qd, t, params) -> tuple:
    """Indices of s − m independent velocities, chosen from A = ∂c/∂qd at a state.

    The dependent block A[:, D] is the best conditioned one that column
    pivoted QR finds. Needs concrete (not traced) values: under `jit` or `vmap`
    pass `independent=` to `simulate` instead (e.g. the result of this
    function called once outside the transformation).
    """
    leaves = [q, qd, t] + jax.tree_util.tree_leaves(params)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        raise ValueError(
            "independent=None: the automatic choice of independent velocities inspects the "
            "constraint matrix at the initial state, which is traced here (inside jit/vmap/grad). "
            "Pass independent=(...) to simulate/accelerations, or set Mechanism(independent=...); "
            "jaxnh.choose_independent(mech, q0, qd0, t0, params) computes it outside the transformation."
        )
    q, qd = jnp.asarray(q), jnp.asarray(qd)
    s = q.shape[0]
    if mech.constraints is None:
        return tuple(range(s))
    A = np.asarray(constraint_matrix(mech, q, qd, t, params))
    m = A.shape[0]
    if m == 0:
        return tuple(range(s))
    _, R, piv = scipy.linalg.qr(A, pivoting=True, mode="economic")
    diag = np.abs(np.diag(R))
    if diag[-1] <= 1e3 * np.finfo(A.dtype).eps * max(diag[0], np.finfo(A.dtype).tiny):
        raise ValueError(
            f"the {m} constraints are linearly dependent at the initial state (rank of ∂c/∂qd < {m}); "
            "the Appell and substituted formulations need independent constraints: "
            "remove the redundant ones or use method='lagrange'."
        )
    dependent = set(int(i) for i in piv[:m])
    return tuple(i for i in range(s) if i not in dependent)


def check_split(mech: Mechanism, independent: tuple, q, qd, t, params) -> None:
    """Raise if the dependent block ∂c/∂qd_D is singular at a concrete state."""
    leaves = [q, qd, t] + jax.tree_util.tree_leaves(params)
    if mech.constraints is None or any(isinstance(x, jax.core.Tracer) for x in leaves):
        return
    A = np.asarray(constraint_matrix(mech, jnp.asarray(q), jnp.asarray(qd), t, params))
    dep = [i for i in range(A.shape[1]) if i not in independent]
    if not dep:
        return
    sv = np.linalg.svd(A[:, dep], compute_uv=False)
    # relative to the whole constraint matrix: a 1×1 block compared with itself is never "singular"
    scale = np.linalg.norm(A, 2)
    if sv[-1] <= 1e3 * np.finfo(A.dtype).eps * max(scale, np.finfo(A.dtype).tiny):
        raise ValueError(
            f"independent={independent}: the dependent velocities {tuple(dep)} cannot be solved from the "
            f"constraints at this state (the block ∂c/∂qd_D is singular, singular values {sv}); "
            "choose other independent velocities or pass independent=None for an automatic choice."
        )


def pick(x, indices):
    """x[indices] for a static tuple of indices, without a gather."""
    return jnp.stack([x[i] for i in indices]) if indices else x[:0]


class VelocitySplit(eqx.Module):
    """Map from independent velocities v to all velocities qd."""

    mech: Mechanism
    independent: tuple = eqx.field(static=True)
    dependent: tuple = eqx.field(static=True)

    @classmethod
    def make(cls, mech: Mechanism, s: int, m: int, independent) -> "VelocitySplit":
        ind = check_independent(independent, s, m)
        dep = tuple(i for i in range(s) if i not in ind)
        return cls(mech, ind, dep)

    def independent_of(self, qd):
        """The independent velocities v (k,) picked out of qd (s,)."""
        return pick(qd, self.independent)

    def assemble(self, v, x):
        """qd (s,) from independent v (k,) and dependent x (m,) (static placement)."""
        parts = [None] * (len(self.independent) + len(self.dependent))
        for j, i in enumerate(self.independent):
            parts[i] = v[j]
        for j, i in enumerate(self.dependent):
            parts[i] = x[j]
        return jnp.stack(parts)

    def dependent_block_determinant(self, q, qd, t, params):
        """det of the dependent block A_D of A = ∂c/∂qd, each row scaled by its norm in A:
        a dimensionless, signed measure of how regular the split is (±1 at best, 0 when
        the dependent velocities cannot be solved for). 1 when nothing is dependent."""
        if not self.dependent:
            return jnp.ones((), q.dtype)
        A = jax.jacfwd(lambda u: self.mech.constraint(q, u, t, params))(qd)
        A = A / jnp.maximum(jnp.linalg.norm(A, axis=1, keepdims=True), jnp.finfo(A.dtype).tiny)
        AD = jnp.stack([A[:, i] for i in self.dependent], axis=1)
        return AD[0, 0] if AD.shape[0] == 1 else jnp.linalg.det(AD)

    def velocities(self, q, v, t, params):
        """All velocities qd (s,) satisfying the constraints, from independent v (k,)."""
        m = len(self.dependent)
        x = jnp.zeros((m,), v.dtype)
        if not m:
            return self.assemble(v, x)

        def c_dep(x):
            return self.mech.constraint(q, self.assemble(v, x), t, params)

        for _ in range(NEWTON_ITERATIONS if self.mech.nonlinear_constraints else 1):
            x = x - solve_square(jax.jacfwd(c_dep)(x), c_dep(x))
        return self.assemble(v, x)

    def velocities_and_rates(self, q, v, t, params):
        """qd, B = ∂qd/∂v (s, k) and β = dqd/dt at dv/dt = 0 (s,)."""
        if not self.mech.nonlinear_constraints and self.dependent:
            return self._linear_velocities_and_rates(q, v, t, params)
        qd = self.velocities(q, v, t, params)
        B = jax.jacfwd(self.velocities, argnums=1)(q, v, t, params)
        _, beta = jax.jvp(
            lambda q_, t_: self.velocities(q_, v, t_, params), (q, t), (qd, jnp.ones_like(t))
        )
        return qd, B, beta

    def _linear_velocities_and_rates(self, q, v, t, params):
        """For `A q̇ + a = 0`: `B = [I; −A_D⁻¹ A_I]` and `A_D β_D = −b` written out.

        No derivative passes through the solve, which keeps the nested
        derivatives of the Appell vector field small (Whipple bicycle:
        12.2k → 8.4k traced operations).
        """
        mech, ind, dep = self.mech, self.independent, self.dependent
        zero = jnp.zeros((len(ind) + len(dep),), q.dtype)
        a = mech.constraint(q, zero, t, params)
        A = jax.jacfwd(lambda u: mech.constraint(q, u, t, params))(zero)
        AD = jnp.stack([A[:, i] for i in dep], axis=1)
        AI = jnp.stack([A[:, i] for i in ind], axis=1)
        # one elimination gives the dependent velocities and the columns of B
        X = solve_square(AD, -jnp.concatenate([(jnp.sum(AI * v, axis=1) + a)[:, None], AI], axis=1))
        qd = self.assemble(v, X[:, 0])
        eye = jnp.eye(len(ind), dtype=q.dtype)
        B = jnp.stack([self.assemble(eye[:, j], X[:, 1 + j]) for j in range(len(ind))], axis=1)
        _, b = jax.jvp(lambda q_, t_: mech.constraint(q_, qd, t_, params), (q, t), (qd, jnp.ones_like(t)))
        return qd, B, self.assemble(jnp.zeros_like(v), solve_square(AD, -b))
