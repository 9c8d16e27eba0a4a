"""The Whipple bicycle built from rigid bodies and contact constraints against the benchmark
of Meijaard, Papadopoulos, Ruina & Schwab (2007), Proc. R. Soc. A 463:1955–1982.

Tolerances: the published matrices and eigenvalues are printed to 14 decimals (rounding
≤ 5e-15) and were themselves computed in float64; our autodiff values agree to ~1e-14, so
1e-12 (entries of size 1–80) leaves two orders of margin and still fails on any wrong
term. Speeds found by Brent's method on the characteristic polynomial are good to
rounding; we ask for 1e-10 m/s (> 10 significant digits; the issue asks for 8).

Nonlinear runs use diffrax's Dopri8, which is what `simulate`'s default picks at these
tolerances (rtol 1e-10): its stages are a loop, so the large vector field of the bicycle is
compiled once rather than once per unrolled stage (an unrolled 8th-order step compiled
about 5× longer for the same accuracy).
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jaxnh as nh
from jaxnh.models import bicycle as B


P = B.default_params()
PUB = B.PUBLISHED
SPEEDS = np.array([0.0, 1.0, 2.0, 3.0, 4.0, PUB["weave_speed"], 5.0, 6.0, PUB["capsize_speed"], 8.0, 10.0])
LS = np.array(B.LEAN_STEER)


def published_state_matrix(v, g=9.81):
    M, C1, K0, K2 = (np.array(PUB[k]) for k in ("M", "C1", "K0", "K2"))
    Minv = np.linalg.inv(M)
    return np.block([[np.zeros((2, 2)), np.eye(2)], [-Minv @ (g * K0 + v**2 * K2), -v * Minv @ C1]])


@pytest.fixture(scope="module")
def lagrange():
    """Linearisations of the 8-coordinate model (front contact as ġ = 0), all speeds, one compile."""
    return B.linearized_speeds(SPEEDS, P, "lagrange")


@pytest.fixture(scope="module")
def appell():
    """The 7-coordinate model (pitch by Newton), Appell's equations from S."""
    return B.linearized_speeds(SPEEDS[[0, 1, 6]], P, "appell")


def test_canonical_matrices_match_published(lagrange):
    mats = B.canonical_from(lagrange, P["g"])
    for k in ("M", "C1", "K0", "K2"):
        np.testing.assert_allclose(mats[k], PUB[k], rtol=0, atol=1e-12, err_msg=k)


def test_eigenvalues_match_published(lagrange):
    for i, key in ((0, "eigenvalues_v0"), (6, "eigenvalues_v5")):
        ev = np.sort_complex(np.linalg.eigvals(np.asarray(lagrange.A[i])[LS][:, LS]))
        np.testing.assert_allclose(ev, np.sort_complex(np.array(PUB[key], dtype=complex)), rtol=0, atol=1e-11)


def test_state_matrix_at_every_speed_matches_published_equations(lagrange):
    for i, v in enumerate(SPEEDS):
        A = np.asarray(lagrange.A[i])[LS][:, LS]
        np.testing.assert_allclose(A, published_state_matrix(v), rtol=1e-12, atol=1e-11, err_msg=f"v = {v}")


def test_weave_and_capsize_speeds(lagrange):
    mats = B.canonical_from(lagrange, P["g"])
    assert abs(B.weave_speed(P, matrices=mats) - PUB["weave_speed"]) < 1e-10
    assert abs(B.capsize_speed(P, matrices=mats) - PUB["capsize_speed"]) < 1e-10
    # the stable speed range between them, seen directly in the eigenvalues
    max_re = np.array([np.linalg.eigvals(np.asarray(A)[LS][:, LS]).real.max() for A in lagrange.A])
    stable = max_re < -1e-9
    assert list(stable) == [False, False, False, False, False, False, True, True, False, False, False]
    assert abs(max_re[5]) < 1e-9 and abs(max_re[8]) < 1e-9  # on the boundaries


def test_upright_running_is_steady_and_the_rear_wheel_decouples(lagrange):
    np.testing.assert_allclose(lagrange.rates, 0.0, atol=1e-12)
    A = np.asarray(lagrange.A)
    np.testing.assert_allclose(A[:, 3, :], 0.0, atol=1e-12)  # d(rear wheel rate)/dt is unaffected
    np.testing.assert_allclose(A[:, :, 3], 0.0, atol=1e-12)  # ... and affects nothing


@pytest.mark.extended
def test_appell_with_newton_pitch_equals_lagrange(lagrange, appell):
    np.testing.assert_allclose(appell.A, np.asarray(lagrange.A)[[0, 1, 6]], rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(appell.mass, np.asarray(lagrange.mass)[[0, 1, 6]], rtol=1e-12, atol=1e-12)


# --- the nonlinear bicycle --------------------------------------------------------------

TS = jnp.linspace(0.0, 5.0, 101)
SOLVER = diffrax.Dopri8()


def run(v, kick, ts=TS):
    """Lagrange with multipliers, all 8 coordinates, from upright running at v with a roll-rate kick.

    By symmetry a roll rate at upright moves neither contact nor the pitch, so this state
    is consistent as it stands (the recorded residual at t = 0 checks it).
    """
    q, qd = B.upright(v, P)
    return nh.simulate(
        B.mechanism("lagrange"),
        P,
        q,
        qd.at[B.ROLL].set(kick),
        ts,
        method="lagrange",
        rtol=1e-10,
        atol=1e-12,
        solver=SOLVER,
        record=("residual", "energy"),
    )


@pytest.fixture(scope="module")
def runs():
    return {"small": run(5.0, 0.01), "kick5": run(5.0, 0.5), "kick2": run(2.0, 0.5, jnp.linspace(0.0, 1.5, 101))}


@pytest.mark.slow
def test_small_kick_follows_the_linear_model(runs):
    """Left-right symmetry makes the error cubic in the amplitude: relative error O(kick²) = 1e-4."""
    sol = runs["small"]
    A = published_state_matrix(5.0)
    lin = np.array([scipy.linalg.expm(A * t) @ np.array([0.0, 0.0, 0.01, 0.0]) for t in np.asarray(TS)])
    amp = np.abs(lin[:, :2]).max()
    np.testing.assert_allclose(np.asarray(sol.q)[:, [B.ROLL, B.STEER]], lin[:, :2], atol=1e-3 * amp)
    np.testing.assert_allclose(
        np.asarray(sol.qd)[:, [B.ROLL, B.STEER]], lin[:, 2:], atol=1e-3 * np.abs(lin[:, 2:]).max()
    )


@pytest.mark.slow
def test_self_stable_at_5_and_falls_at_2(runs):
    roll5 = np.abs(np.asarray(runs["kick5"].q[:, B.ROLL]))
    assert roll5[-20:].max() < 0.2 * roll5[:20].max()  # decays (slowest mode: the capsize root −0.32/s)
    roll2 = np.asarray(runs["kick2"].q[:, B.ROLL])
    assert roll2[-1] > 0.5 > roll2[:20].max()  # the weave grows (+2.7/s) and the bicycle falls over


@pytest.mark.slow
def test_constraints_and_energy_hold(runs):
    for sol in runs.values():
        assert sol.message == "success"
        assert np.abs(sol.residual).max() < 1e-9
        g = jax.jit(jax.vmap(lambda q: B.front_contact(q, 0.0, P)))(sol.q)
        assert np.abs(g).max() < 1e-9  # drift of the twice-differentiated front contact
        E = np.asarray(sol.energy)
        assert np.ptp(E) < 1e-9 * abs(E[0])  # no dissipation in the Whipple model


@pytest.mark.extended
def test_nonlinear_appell_with_newton_pitch_equals_lagrange(runs):
    """The 7-coordinate Appell model (pitch by Newton) along the kicked run: ~50 s to compile."""
    q, qd = B.upright(5.0, P)
    sol = nh.simulate(
        B.system(), P, q, qd.at[B.ROLL].set(0.5), TS, method="appell", rtol=1e-10, atol=1e-12, solver=SOLVER
    )
    np.testing.assert_allclose(sol.q, runs["kick5"].q, atol=1e-7)
