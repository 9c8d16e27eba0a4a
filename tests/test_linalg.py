"""The minimum-norm multiplier solve of Lagrange's form (`solve_psd_min_norm`): its written-out form
(m ≤ UNROLL_MAX) and its loop (m > UNROLL_MAX, so large constraint sets compile in bounded size),
against NumPy's pseudo-inverse, for independent and redundant constraints, with derivatives.

Tolerances: both solves are backward stable LDLᵀ factorisations, so the relative error of x is at
most a small multiple of κ(G)·eps on the range of G (κ over the nonzero eigenvalues); the test
allows 100·m·κ·eps, and builds G so that κ stays below 1e3.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnh._base.linalg import _solve_psd_min_norm_looped, solve_psd_min_norm, UNROLL_MAX


EPS = float(np.finfo(np.float64).eps)


def compliance(m: int, rank: int, seed: int) -> np.ndarray:
    """G = A M⁻¹ Aᵀ of m constraint rows of which only `rank` are independent (the others are
    combinations of them, as redundant constraints give), with a well-conditioned range."""
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((rank, 2 * rank + 2))
    A = np.vstack([B, rng.standard_normal((m - rank, rank)) @ B]) if rank < m else B
    return A @ A.T


def bound(G: np.ndarray) -> float:
    w = np.linalg.eigvalsh(G)
    w = w[w > 1e-9 * w[-1]]
    kappa = w[-1] / w[0]
    assert kappa < 1e4, kappa  # the construction keeps the range well conditioned
    return 100 * G.shape[0] * kappa * EPS


@pytest.mark.parametrize("m,rank", [(5, 5), (5, 3), (12, 12), (12, 9), (17, 10)])
def test_min_norm_solution_against_pseudo_inverse(m, rank):
    G = compliance(m, rank, seed=m + rank)
    r = G @ np.random.default_rng(1).standard_normal(m)  # consistent right-hand side, as Lagrange's are
    ref = np.linalg.pinv(G, rcond=1e-10) @ r
    tol = bound(G)
    for solve in (solve_psd_min_norm, _solve_psd_min_norm_looped):
        x = np.asarray(jax.jit(solve)(jnp.asarray(G), jnp.asarray(r)))
        assert np.linalg.norm(x - ref) <= tol * np.linalg.norm(ref), (solve.__name__, m, rank)


def test_large_m_takes_the_loop_and_small_m_is_written_out():
    """The loop's program does not grow with m: its jaxpr has the same number of equations at 12 and 24
    constraints; the written-out form's grows (cubically)."""

    def eqns(f, m):
        return len(jax.make_jaxpr(f)(jnp.eye(m), jnp.ones(m)).jaxpr.eqns)

    assert eqns(solve_psd_min_norm, 2 * UNROLL_MAX + 8) == eqns(solve_psd_min_norm, UNROLL_MAX + 4)
    assert eqns(solve_psd_min_norm, UNROLL_MAX) > 4 * eqns(solve_psd_min_norm, UNROLL_MAX // 2)


@pytest.mark.parametrize("rank", [6, 4])
def test_loop_derivatives_equal_the_written_out_ones(rank):
    """Where the rank is locally constant both forms are the same function; their forward and reverse
    derivatives agree to the error bound (perturbations keep G's null space, as a change of
    parameters does for redundant constraints)."""
    m = 6
    G = jnp.asarray(compliance(m, rank, seed=3))
    r = G @ jnp.linspace(-1.0, 1.0, m)

    def loss(solve, a):
        Ga = G * (1 + a) + a**2 * G @ G  # a polynomial in G: same null space, so the same rank
        return jnp.sum(jnp.sin(solve(Ga, r * (1 - a))))

    tol = bound(np.asarray(G))
    for a in (0.0, 0.3):
        d_ref = jax.grad(lambda a: loss(solve_psd_min_norm, a))(a)
        d_rev = jax.grad(lambda a: loss(_solve_psd_min_norm_looped, a))(a)
        d_fwd = jax.jacfwd(lambda a: loss(_solve_psd_min_norm_looped, a))(a)
        for d in (d_rev, d_fwd):
            assert abs(float(d) - float(d_ref)) <= 10 * tol * (1 + abs(float(d_ref))), (a, d, d_ref)
    # and under vmap
    xs = jax.vmap(lambda s: _solve_psd_min_norm_looped(G * s, r))(jnp.array([1.0, 2.0]))
    np.testing.assert_allclose(np.asarray(xs[1]), np.asarray(xs[0]) / 2, rtol=tol, atol=tol * float(jnp.max(xs[0])))
