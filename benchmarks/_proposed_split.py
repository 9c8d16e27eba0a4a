"""Faster small solves and cheaper checks for the Appell split (proposed for
jaxnh/linalg.py and jaxnh/equations/split.py).

* `solve_square(A, b)` — Gaussian elimination with partial pivoting written out
  for static sizes up to `jaxnh.linalg.UNROLL_MAX` (row exchanges by selects,
  so it fuses, vmaps and differentiates), LAPACK beyond. `jnp.linalg.solve` on
  a 3×3 matrix is an LU factorisation and two triangular solves, three library
  calls of about 1 µs each on CPU.
* `velocities_and_rates_linear` — for constraints linear in the velocities,
  `A(q, t) qd + a(q, t) = 0`, the dependent velocities, `B = ∂qd/∂v` and β
  written out from one constraint Jacobian (as `jaxnh.linearize._LinearSplit`
  does), instead of differentiating a solve twice (jacfwd for B, jvp for β),
  which factorised the dependent block three times per evaluation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

import jaxnh.equations.split as _split
from jaxnh.linalg import UNROLL_MAX, mm

_orig_choose_independent = _split.choose_independent
_orig_check_split = _split.check_split


def solve_square(A, b):
    """Solve A x = b for a small square non-symmetric A (n, n); b (n,) or (n, k)."""
    n = A.shape[0]
    if n == 1:
        return b / A[0, 0]
    if n > UNROLL_MAX:
        return jnp.linalg.solve(A, b)
    rows = [A[i] for i in range(n)]
    rhs = [b[i] for i in range(n)]
    for k in range(n):
        # partial pivoting: bring the largest |A[i, k]|, i ≥ k, to row k by compare-and-swap
        for i in range(k + 1, n):
            swap = jnp.abs(rows[i][k]) > jnp.abs(rows[k][k])
            rows[k], rows[i] = jnp.where(swap, rows[i], rows[k]), jnp.where(swap, rows[k], rows[i])
            rhs[k], rhs[i] = jnp.where(swap, rhs[i], rhs[k]), jnp.where(swap, rhs[k], rhs[i])
        for i in range(k + 1, n):
            f = rows[i][k] / rows[k][k]
            rows[i] = rows[i] - f * rows[k]
            rhs[i] = rhs[i] - f * rhs[k]
    x = [None] * n
    for i in reversed(range(n)):
        acc = rhs[i]
        for j in range(i + 1, n):
            acc = acc - rows[i][j] * x[j]
        x[i] = acc / rows[i][i]
    return jnp.stack(x)


def velocities_and_rates_linear(split, q, v, t, params):
    """qd (s,), B = ∂qd/∂v (s, k) and β = dqd/dt at dv/dt = 0 (s,), for linear constraints."""
    mech, ind, dep = split.mech, split.independent, split.dependent
    s = len(ind) + len(dep)
    if not dep:
        return split.assemble(v, v[:0]), jnp.eye(s, dtype=v.dtype), jnp.zeros((s,), v.dtype)
    zero = jnp.zeros((s,), v.dtype)
    a = mech.constraint(q, zero, t, params)
    A = jax.jacfwd(lambda u: mech.constraint(q, u, t, params))(zero)
    AD = jnp.stack([A[:, i] for i in dep], axis=1)
    AI = jnp.stack([A[:, i] for i in ind], axis=1)
    # one elimination for the dependent velocities and the columns of B
    X = solve_square(AD, -jnp.concatenate([(mm(AI, v) + a)[:, None], AI], axis=1))
    qd = split.assemble(v, X[:, 0])
    eye = jnp.eye(len(ind), dtype=v.dtype)
    B = jnp.stack([split.assemble(eye[:, j], X[:, 1 + j]) for j in range(len(ind))], axis=1)
    _, b = jax.jvp(lambda q_, t_: mech.constraint(q_, qd, t_, params), (q, t), (qd, jnp.ones_like(t)))
    beta = split.assemble(jnp.zeros_like(v), solve_square(AD, -b))
    return qd, B, beta


# --- per-call cost of simulate: the constraint matrix at the initial state, compiled ---------


@eqx.filter_jit
def constraint_matrix(mech, q, qd, t, params):
    """A = ∂c/∂qd at one state, compiled once per mechanism and shapes.

    `choose_independent` and `check_split` evaluated it with an eager
    `jax.jacfwd`: about 40 operations dispatched one by one, each compiled on
    the first call (≈ 1–3 s of a first `simulate` call on a loaded 2-core
    machine) and ≈ 20 ms of Python on every later call.
    """
    return jax.jacfwd(lambda v: mech.constraint(q, v, t, params))(jnp.asarray(qd))


def choose_independent(mech, q, qd, t, params) -> tuple:
    leaves = [q, qd, t] + jax.tree_util.tree_leaves(params)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return _orig_choose_independent(mech, q, qd, t, params)  # raises the explanatory error
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
        return _orig_choose_independent(mech, q, qd, t, params)  # raises the explanatory error
    dependent = set(int(i) for i in piv[:m])
    return tuple(i for i in range(s) if i not in dependent)


def check_split(mech, independent: tuple, q, qd, t, params) -> None:
    leaves = [q, qd, t] + jax.tree_util.tree_leaves(params)
    if mech.constraints is None or any(isinstance(x, jax.core.Tracer) for x in leaves):
        return
    A = np.asarray(constraint_matrix(mech, jnp.asarray(q), jnp.asarray(qd), t, params))
    dep = [i for i in range(A.shape[1]) if i not in independent]
    if not dep:
        return
    sv = np.linalg.svd(A[:, dep], compute_uv=False)
    if sv[-1] <= 1e3 * np.finfo(A.dtype).eps * max(sv[0], np.finfo(A.dtype).tiny):
        _orig_check_split(mech, independent, q, qd, t, params)  # raises the explanatory error


# --- per-call cost of simulate: shape checks remembered -------------------------------------

_SHAPES_CHECKED: dict = {}


def _signature(x):
    if hasattr(x, "shape") and hasattr(x, "dtype"):
        return ("array", tuple(x.shape), str(x.dtype))
    return ("value", type(x).__name__, x)


def check_shapes_memoized(original):
    """`Mechanism.check_shapes` remembered per (mechanism, shapes and dtypes, params structure).

    The check traces every user function with `jax.eval_shape` (≈ 3 ms of
    Python per `simulate` call, twice: in `simulate` and in `formulation`); its
    answer depends only on that signature.
    """

    def check_shapes(self, q, qd, t, params):
        leaves, treedef = jax.tree_util.tree_flatten(params)
        try:
            key = (self, _signature(q), _signature(qd), _signature(t), treedef, tuple(_signature(x) for x in leaves))
            hash(key)
        except TypeError:
            return original(self, q, qd, t, params)
        if key not in _SHAPES_CHECKED:
            _SHAPES_CHECKED[key] = original(self, q, qd, t, params)
        return _SHAPES_CHECKED[key]

    return check_shapes
