"""Small dense linear algebra specialised for mechanisms.

A mechanism has a handful of coordinates, and on a CPU a call to
`jnp.linalg.solve` on a 2×2 matrix costs about as much as the whole
right-hand side of the equations of motion (about 1 µs per call, measured once
on a 2-core CPU by a benchmark since removed). The factorisations
here are written out element by element for static sizes up to
`UNROLL_MAX`, so XLA fuses them into the vector field; larger systems fall
back to LAPACK through `jax.scipy.linalg`.

All functions are differentiable, work under `vmap`, and keep the dtype of
their inputs. `value_and_jacfwd` gives a small map's value and Jacobian in one
forward-mode pass (the constraint matrix, a linearisation).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float


__all__ = [
    "UNROLL_MAX",
    "mm",
    "cholesky",
    "solve_lower",
    "solve_upper_t",
    "solve_spd",
    "pivot_rtol",
    "solve_psd_min_norm",
    "solve_square",
    "value_and_jacfwd",
    "pick",
]

UNROLL_MAX = 8


def mm(a: Any, b: Any) -> Any:
    """Matrix product for small matrices/vectors as a fusible multiply-and-sum.

    XLA on CPU turns `a @ b` into a library call whose fixed cost dominates
    for 2×2 operands; a broadcast product and a sum fuse with the rest of
    the right-hand side. Falls back to `@` for large operands.
    """
    if max(a.size, b.size) > UNROLL_MAX * UNROLL_MAX:
        return a @ b
    if b.ndim == 1:
        return jnp.sum(a * b, axis=-1)
    if a.ndim == 1:
        return jnp.sum(a[:, None] * b, axis=0)
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def cholesky(M: Float[Array, "s s"]) -> Float[Array, "s s"]:
    """Lower Cholesky factor L of a symmetric positive definite M = L Lᵀ.

    A matrix that is not positive definite gives NaN entries (which a
    diffrax step controller rejects), never a silently wrong factor.
    """
    s = M.shape[0]
    if s > UNROLL_MAX:
        return jnp.linalg.cholesky(M)
    L: list[list[Any]] = [[None] * s for _ in range(s)]  # entries filled in below
    for j in range(s):
        d = M[j, j] - sum(L[j][k] * L[j][k] for k in range(j))
        L[j][j] = jnp.sqrt(d)
        for i in range(j + 1, s):
            L[i][j] = (M[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    zero = jnp.zeros((), M.dtype)
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(s)]) for i in range(s)])


def solve_lower(L: Float[Array, "s s"], b: Float[Array, " s *k"]) -> Float[Array, " s *k"]:
    """Solve L x = b for lower-triangular L (forward substitution)."""
    s = L.shape[0]
    if s > UNROLL_MAX:
        return jsl.solve_triangular(L, b, lower=True)
    x = []
    for i in range(s):
        acc = b[i]
        for k in range(i):
            acc = acc - L[i, k] * x[k]
        x.append(acc / L[i, i])
    return jnp.stack(x)


def solve_upper_t(L: Float[Array, "s s"], b: Float[Array, " s *k"]) -> Float[Array, " s *k"]:
    """Solve Lᵀ x = b for lower-triangular L (back substitution)."""
    s = L.shape[0]
    if s > UNROLL_MAX:
        return jsl.solve_triangular(L, b, lower=True, trans="T")
    x: list[Any] = [None] * s  # filled in below
    for i in reversed(range(s)):
        acc = b[i]
        for k in range(i + 1, s):
            acc = acc - L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return jnp.stack(x)


def solve_spd(M: Float[Array, "s s"], b: Float[Array, " s *k"]) -> Float[Array, " s *k"]:
    """Solve M x = b for symmetric positive definite M by Cholesky."""
    L = cholesky(M)
    return solve_upper_t(L, solve_lower(L, b))


def pivot_rtol(dtype: jax.typing.DTypeLike) -> float:
    """Relative pivot below which a constraint counts as redundant."""
    return float(1e4 * jnp.finfo(dtype).eps)


def solve_psd_min_norm(G: Float[Array, "m m"], r: Float[Array, " m"]) -> Float[Array, " m"]:
    """Minimum-norm solution of G x = r for symmetric positive semidefinite G.

    G = A M⁻¹ Aᵀ is the constraint "compliance" matrix of the multipliers.
    When the constraints are independent it is positive definite and this is
    an ordinary LDLᵀ solve. When some constraints repeat others (a rank
    deficient A), the LDLᵀ pivot of each redundant row is (up to rounding)
    zero: such rows are dropped (pivot below `pivot_rtol` times the original
    diagonal), which gives a particular solution; its component along the
    null space of G, spanned by L⁻ᵀ e_k for the dropped k, is then removed by
    a masked Gram–Schmidt projection, which leaves the minimum-norm solution.
    Differentiable wherever the rank is locally constant.

    Written out element by element up to `UNROLL_MAX` constraints; beyond, the
    same factorisation runs as a loop over columns with array operations
    (`_solve_psd_min_norm_looped`): element by element it takes O(m³) scalar
    operations (the null-space basis alone m³), each compiled separately, so its
    compile time grew faster than cubically (m = 9: 1 792 operations; m = 17:
    9 436, minutes of XLA compilation, and a Lagrange `simulate` holds several
    copies: the solver's stages, the first step, the stiffness estimate's jvp).
    """
    m = G.shape[0]
    if m == 0:
        return r
    if m > UNROLL_MAX:
        return _solve_psd_min_norm_looped(G, r)
    rtol = pivot_rtol(G.dtype)
    one = jnp.ones((), G.dtype)
    zero = jnp.zeros((), G.dtype)
    # LDLᵀ without pivoting, redundant rows dropped.
    L = [[zero] * m for _ in range(m)]
    d, dinv, dropped = [], [], []
    for j in range(m):
        dj = G[j, j] - sum(L[j][k] * L[j][k] * d[k] for k in range(j))
        keep = dj > rtol * jnp.abs(G[j, j]) + jnp.finfo(G.dtype).tiny
        dj_safe = jnp.where(keep, dj, one)
        inv = jnp.where(keep, 1 / dj_safe, zero)
        d.append(jnp.where(keep, dj, zero))
        dinv.append(inv)
        dropped.append(~keep)
        L[j][j] = one
        for i in range(j + 1, m):
            lij = (G[i, j] - sum(L[i][k] * L[j][k] * d[k] for k in range(j))) * inv
            L[i][j] = lij
    # forward, diagonal, back substitution
    y = []
    for i in range(m):
        y.append(r[i] - sum(L[i][k] * y[k] for k in range(i)))
    z = [y[i] * dinv[i] for i in range(m)]
    xs: list[Any] = [None] * m  # filled in below
    for i in reversed(range(m)):
        xs[i] = z[i] - sum(L[k][i] * xs[k] for k in range(i + 1, m))
    x = jnp.stack(xs)
    if m == 1:
        return x  # a dropped single constraint already gives x = 0
    # Null space of G: columns L⁻ᵀ e_k for dropped k; project them out of x.
    basis = []
    for k in range(m):
        n: list[Any] = [None] * m  # filled in below
        for i in reversed(range(m)):
            n[i] = (one if i == k else zero) - sum(L[j][i] * n[j] for j in range(i + 1, m))
        v = jnp.stack(n)
        for b in basis:
            v = v - b * jnp.dot(b, v)
        norm = jnp.sqrt(jnp.dot(v, v))
        v = jnp.where(dropped[k], v / jnp.where(dropped[k], norm, one), zero)
        basis.append(v)
    for b in basis:
        x = x - b * jnp.dot(b, x)
    return x


def _solve_psd_min_norm_looped(G: Float[Array, "m m"], r: Float[Array, " m"]) -> Float[Array, " m"]:
    """`solve_psd_min_norm` for large m: the same LDLᵀ with redundant rows dropped, right-looking
    (one rank-one update of the Schur complement per column) in a `fori_loop`, so the program's
    size does not grow with m; substitutions and the null-space projection by LAPACK."""
    m = G.shape[0]
    dtype = G.dtype
    rtol = pivot_rtol(dtype)
    one = jnp.ones((), dtype)
    idx = jnp.arange(m)
    floor = rtol * jnp.abs(jnp.diagonal(G)) + jnp.finfo(dtype).tiny

    def column(j, carry):
        S, L, dinv, kept = carry  # S: the Schur complement G − Σ_{k<j} d_k l_k l_kᵀ
        dj = S[j, j]
        keep = dj > floor[j]
        inv = jnp.where(keep, 1 / jnp.where(keep, dj, one), 0.0)
        lj = jnp.where(idx > j, S[:, j] * inv, (idx == j).astype(dtype))
        S = S - jnp.where(keep, dj, 0.0) * lj[:, None] * lj[None, :]
        return S, L.at[:, j].set(lj), dinv.at[j].set(inv), kept.at[j].set(keep)

    init = (G, jnp.zeros_like(G), jnp.zeros((m,), dtype), jnp.zeros((m,), bool))
    _, L, dinv, kept = jax.lax.fori_loop(0, m, column, init)
    # forward, diagonal, back substitution (L has a unit diagonal)
    y = jsl.solve_triangular(L, r, lower=True, unit_diagonal=True)
    x = jsl.solve_triangular(L, y * dinv, lower=True, trans="T", unit_diagonal=True)
    # null space of G: the columns L⁻ᵀ e_k of the dropped k (zero columns for the kept ones);
    # x minus its orthogonal projection onto them (the kept block of the Gram matrix set to 1)
    N = jsl.solve_triangular(L, jnp.diag((~kept).astype(dtype)), lower=True, trans="T", unit_diagonal=True)
    C = N.T @ N + jnp.diag(kept.astype(dtype))
    return x - N @ jnp.linalg.solve(C, N.T @ x)


def solve_square(A: Float[Array, "n n"], b: Float[Array, " n *k"]) -> Float[Array, " n *k"]:
    """Solve A x = b for a small square, non-symmetric A (e.g. the dependent block of
    the constraint matrix) by Gaussian elimination with partial pivoting.

    Written out element by element for static sizes up to `UNROLL_MAX`, row
    exchanges done by selects, so it fuses into the vector field, vmaps and
    differentiates; `jnp.linalg.solve` there is three library calls (LU and two
    triangular solves) of about 1 µs each on CPU. LAPACK beyond `UNROLL_MAX`.
    A singular A gives inf/NaN entries, as LAPACK does.
    """
    n = A.shape[0]
    if n == 1:
        return b / A[0, 0]
    if n > UNROLL_MAX:
        return jnp.linalg.solve(A, b)
    rows = [A[i] for i in range(n)]
    rhs = [b[i] for i in range(n)]
    for k in range(n):
        # bring the largest |A[i, k]|, i ≥ k, to row k (compare-and-swap down the column)
        for i in range(k + 1, n):
            swap = jnp.abs(rows[i][k]) > jnp.abs(rows[k][k])
            rows[k], rows[i] = jnp.where(swap, rows[i], rows[k]), jnp.where(swap, rows[k], rows[i])
            rhs[k], rhs[i] = jnp.where(swap, rhs[i], rhs[k]), jnp.where(swap, rhs[k], rhs[i])
        for i in range(k + 1, n):
            f = rows[i][k] / rows[k][k]
            rows[i] = rows[i] - f * rows[k]
            rhs[i] = rhs[i] - f * rhs[k]
    x: list[Any] = [None] * n  # filled in below
    for i in reversed(range(n)):
        acc = rhs[i]
        for j in range(i + 1, n):
            acc = acc - rows[i][j] * x[j]
        x[i] = acc / rows[i][i]
    return jnp.stack(x)


def value_and_jacfwd(f: Any, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """f(x) and its Jacobian ∂f/∂x (shape `f(x).shape + (n,)`) for a vector x (n,), by forward mode
    in one pass: a `jvp` batched over the n unit tangents, whose primal is not batched and so is
    traced and evaluated once (`jax.jacfwd` drops it, so a caller needing both would trace f
    twice; `jax.linearize` also gives both, at half as much tracing time again). Units: those of
    f, and of f per unit of each x. Works under `jit`, `vmap` and `grad`."""
    jac = jax.vmap(lambda dx: jax.jvp(f, (x,), (dx,)), in_axes=1, out_axes=(None, 1))
    return jac(jnp.eye(x.shape[0], dtype=x.dtype))


def pick(x: jax.Array, indices: tuple[int, ...] | None) -> jax.Array:
    """x[indices] for a static tuple of indices, without a gather."""
    return jnp.stack([x[i] for i in indices]) if indices else x[:0]
