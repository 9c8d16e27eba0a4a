"""The seed paper's friction variator: autodiff equations against eqs. (8), (9), (16),
and simulations against the closed form."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import variator as V
from jaxnh.profiles import Fourier


METHODS_WITH_S = [("lagrange", False), ("appell", False), ("appell", True)]


def random_params(key):
    k = jax.random.split(key, 6)
    u = jax.random.uniform
    return V.VariatorParams(
        J1=u(k[0], minval=0.005, maxval=0.2),
        J2=u(k[1], minval=0.005, maxval=0.2),
        U21=Fourier(u(k[2], minval=0.8, maxval=2.0), cos=[0.1], sin=u(k[3], (2,), minval=-0.3, maxval=0.3), period=1.7),
        M1=Fourier(u(k[4], minval=-1, maxval=1), sin=[0.2], period=3.0),
        M2=Fourier(u(k[5], minval=-1, maxval=1), cos=[0.1], period=2.3),
    )


@pytest.fixture(scope="module")
def samples():
    """60 random (params, phi1', t) triples."""
    keys = jax.random.split(jax.random.PRNGKey(0), 60)
    params = jax.vmap(random_params)(keys)
    w = jax.random.uniform(jax.random.PRNGKey(1), (60,), minval=-5, maxval=5)
    t = jax.random.uniform(jax.random.PRNGKey(2), (60,), minval=0, maxval=10)
    return params, w, t


def batched_accelerations(method, with_S, params, w, t):
    mech = V.mechanism(acceleration_energy_given=with_S)

    def one(p, w, t):
        qd = jnp.stack([w, p.U21(t) * w])
        return nh.accelerations(mech, jnp.array([0.3, -1.2]), qd, t, p, method=method)

    return jax.jit(jax.vmap(one))(params, w, t)


@pytest.mark.parametrize("method,with_S", METHODS_WITH_S)
def test_accelerations_equal_paper_eq9_and_multiplier(samples, method, with_S):
    params, w, t = samples
    qdd, lam = batched_accelerations(method, with_S, params, w, t)
    a9 = jax.vmap(V.paper_eq9)(w, t, params)
    U, dU = jax.vmap(lambda p, t: p.U21(t))(params, t), jax.vmap(lambda p, t: p.U21.derivative(t))(params, t)
    np.testing.assert_allclose(qdd[:, 0], a9, rtol=1e-12, atol=1e-12)
    # phi2'' from the differentiated constraint, eq. (25)
    np.testing.assert_allclose(qdd[:, 1], dU * w + U * a9, rtol=1e-12, atol=1e-12)
    lam_ref = jax.vmap(V.paper_multiplier)(w, a9, t, params)
    np.testing.assert_allclose(lam[:, 0], lam_ref, rtol=1e-12, atol=1e-12)
    # eq. (8): J1 phi1'' = M1 + lambda U21, J2 phi2'' = M2 - lambda
    M1 = jax.vmap(lambda p, t: p.M1(t))(params, t)
    np.testing.assert_allclose(params.J1 * qdd[:, 0], M1 + lam[:, 0] * U, rtol=1e-11, atol=1e-12)


def test_substituted_has_exactly_the_extra_velocity_term(samples):
    params, w, t = samples
    qdd_sub, _ = batched_accelerations("substituted", False, params, w, t)
    a9 = jax.vmap(V.paper_eq9)(w, t, params)
    U, dU = jax.vmap(lambda p, t: p.U21(t))(params, t), jax.vmap(lambda p, t: p.U21.derivative(t))(params, t)
    extra = params.J2 * U * dU * w / (params.J1 + params.J2 * U**2)
    np.testing.assert_allclose(qdd_sub[:, 0], a9 - extra, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(qdd_sub[:, 0], jax.vmap(V.paper_eq16)(w, t, params), rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(extra)) > 0.1  # the difference is not negligible in these samples


# --- simulation against the closed form ---------------------------------------

W0 = 2.0
TS = jnp.linspace(0.0, 10.0, 201)


@pytest.fixture(scope="module")
def driven():
    """Non-trivial U21(t) (two harmonics) and non-zero time-varying torques."""
    p = V.VariatorParams(
        J1=0.02,
        J2=0.05,
        U21=Fourier(1.1, cos=[0.2, 0.05], sin=[0.3], period=2.0),
        M1=Fourier(0.3, sin=[0.1], period=5.0),
        M2=-0.1,
    )
    return p, V.closed_form(p, TS, w0=W0)


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_simulation_matches_closed_form(driven, method):
    p, (q_ref, qd_ref) = driven
    qd0 = jnp.array([W0, p.U21(0.0) * W0])
    sol = nh.simulate(
        V.mechanism(),
        p,
        jnp.zeros(2),
        qd0,
        TS,
        method=method,
        rtol=1e-12,
        atol=1e-12,
        solver=__import__("diffrax").Dopri8(),
    )
    assert bool(sol.success)
    err = max(np.max(np.abs(sol.q - q_ref)), np.max(np.abs(sol.qd - qd_ref)))
    print(f"{method}: max error vs closed form {err:.2e}, steps {int(sol.stats['num_steps'])}")
    assert err <= 1e-9


def test_closed_form_quadrature_is_converged(driven):
    """The reference itself: halving the panel width changes nothing above 1e-12."""
    p, (q_ref, qd_ref) = driven
    q2, qd2 = V.closed_form(p, TS, w0=W0, max_panel=0.005)
    assert np.max(np.abs(q2 - q_ref)) < 1e-12 and np.max(np.abs(qd2 - qd_ref)) < 1e-12


# --- energy with M1 = M2 = 0 --------------------------------------------------

PERIOD = 2.0
N_PERIODS = 100


@pytest.fixture(scope="module")
def free_runs():
    p = V.VariatorParams(J1=0.02, J2=0.05, U21=Fourier(1.0, sin=[0.4], period=PERIOD))
    ts = jnp.linspace(0.0, N_PERIODS * PERIOD, 1001)
    qd0 = jnp.array([W0, p.U21(0.0) * W0])
    out = {}
    for method in ("lagrange", "appell", "substituted"):
        sol = nh.simulate(
            V.mechanism(),
            p,
            jnp.zeros(2),
            qd0,
            ts,
            method=method,
            rtol=1e-12,
            atol=1e-12,
            record=("energy",),
            solver=__import__("diffrax").Dopri8(),
        )
        out[method] = sol
    return out


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_energy_conserved_without_torques(free_runs, method):
    E = np.asarray(free_runs[method].energy)
    drift = np.max(np.abs(E - E[0])) / E[0]
    print(f"{method}: relative energy drift over {N_PERIODS} periods {drift:.2e}")
    assert drift <= 1e-9


def test_substituted_does_not_conserve_energy(free_runs):
    E = np.asarray(free_runs["substituted"].energy)
    drift = np.max(np.abs(E - E[0])) / E[0]
    print(f"substituted: relative energy change {drift:.2f}")
    assert drift > 0.05


def test_recorded_residual_and_multipliers(free_runs):
    """Records are absent unless asked for."""
    sol = free_runs["appell"]
    assert sol.multipliers is None and sol.residual is None and sol.energy is not None
