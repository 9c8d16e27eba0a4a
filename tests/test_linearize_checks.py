"""`linearize` makes the checks `simulate` makes of its initial state, by the same functions, at
the operating state: a given acceleration energy S must agree with T (`acceleration_energy_agrees`)
and the configuration must lie on the holonomic constraints (`holonomic_consistent`). A failure is
refused eagerly with a ValueError naming it and the fix, and gives NaN under jit and vmap; a
mechanism that passes is linearised as before.

Tolerance of the comparisons between Appell's and Lagrange's state matrices: both are exact
derivatives of the same equations, evaluated by different automatic-differentiation paths (∂S/∂q̈
and Lagrange's expression from T), so they differ by rounding only: a few operations per entry of
the projected equations and one solve with the k×k mass (k ≤ 2 here, condition number κ), each
rounding to eps of its terms. The allowance is 64 κ eps of the largest entry of A (measured: at
most 0.7 eps, and 0 for the variator and the point mass).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import variator as V


EPS = float(np.finfo(np.float64).eps)


def _agree(a, b, mass):
    kappa = float(np.linalg.cond(np.asarray(mass)))
    np.testing.assert_allclose(a, b, rtol=0, atol=64 * kappa * EPS * float(np.max(np.abs(b))))


# --- the variator: S given with and without a term ----------------------------------------------------

P = V.default_params()
Q = jnp.zeros(2)
T0 = 0.3
QD = jnp.array([2.0, 2.0 * float(P.U21(T0))])


def _variator(S):
    return nh.Mechanism(
        V.kinetic, constraints=V.constraint, forces=V.torques, acceleration_energy=S, names=("phi1", "phi2")
    )


def _S_without_J2(q, qd, qdd, t, p):
    """The paper's S with the output shaft's term ½ J2 φ2''² left out."""
    return 0.5 * p.J1 * qdd[0] ** 2


@pytest.mark.parametrize("method", ["appell", "lagrange"])
def test_an_acceleration_energy_that_disagrees_with_T_is_refused(method):
    bad = _variator(_S_without_J2)
    with pytest.raises(ValueError, match="acceleration_energy.*disagrees") as info:
        nh.linearize(bad, P, Q, QD, T0, speeds=(0,), method=method)
    assert "Correct `acceleration_energy`, or leave it out" in str(info.value)
    # simulate refuses the same mechanism at the same state, with its status
    with pytest.raises(nh.InvalidInitialState, match="acceleration_energy"):
        nh.simulate(bad, P, Q, QD, jnp.array([T0, T0 + 0.1]), method="appell")
    # traced: NaN, never the finite matrices of S's equations
    lin = jax.jit(lambda qd: nh.linearize(bad, P, Q, qd, T0, speeds=(0,), method=method))(QD)
    assert all(np.all(np.isnan(np.asarray(x))) for x in (lin.A, lin.mass, lin.damping, lin.stiffness, lin.rates))
    batch = jax.vmap(lambda w: nh.linearize(bad, P, Q, w * QD, T0, speeds=(0,), method=method).A)(jnp.array([1.0, 2.0]))
    assert np.all(np.isnan(np.asarray(batch)))


def test_an_acceleration_energy_that_agrees_with_T_gives_lagranges_state_matrix():
    good = _variator(V.acceleration_energy)
    ref = nh.linearize(good, P, Q, QD, T0, speeds=(0,), method="lagrange")
    lin = nh.linearize(good, P, Q, QD, T0, speeds=(0,), method="appell")
    assert np.all(np.isfinite(np.asarray(lin.A))) and float(jnp.max(jnp.abs(lin.A))) > 0.1
    _agree(lin.A, ref.A, ref.mass)
    jitted = jax.jit(lambda qd: nh.linearize(good, P, Q, qd, T0, speeds=(0,), method="appell"))(QD)
    _agree(jitted.A, ref.A, ref.mass)
    # and the same as the mechanism without S (jaxnh builds it from T)
    _agree(lin.A, nh.linearize(V.mechanism(), P, Q, QD, T0, speeds=(0,), method="appell").A, ref.mass)


# --- velocity terms: a point mass on a spring in polar coordinates, in motion ----------------------------


def _polar_T(q, qd, t, p):
    return 0.5 * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)


def _polar_S(q, qd, a, t, p):  # ½ |acceleration|²: radial r'' − r θ'², transverse r θ'' + 2 r' θ'
    return 0.5 * ((a[0] - q[0] * qd[1] ** 2) ** 2 + (q[0] * a[1] + 2 * qd[0] * qd[1]) ** 2)


def _polar_S_no_centripetal(q, qd, a, t, p):
    return 0.5 * (a[0] ** 2 + (q[0] * a[1] + 2 * qd[0] * qd[1]) ** 2)


def _spring(q, t, p):
    return 0.5 * 40.0 * (q[0] - 1.0) ** 2


def test_velocity_terms_of_S_are_checked_in_motion_and_at_rest():
    q, qd = jnp.array([1.2, 0.4]), jnp.array([0.3, 0.7])
    good = nh.Mechanism(_polar_T, potential=_spring, acceleration_energy=_polar_S)
    ref = nh.linearize(good, {}, q, qd, method="lagrange")
    lin = nh.linearize(good, {}, q, qd, method="appell")
    _agree(lin.A, ref.A, ref.mass)
    bad = nh.Mechanism(_polar_T, potential=_spring, acceleration_energy=_polar_S_no_centripetal)
    for v in (qd, jnp.zeros(2)):  # at rest the missing term vanishes: the second velocity finds it
        with pytest.raises(ValueError, match="acceleration_energy"):
            nh.linearize(bad, {}, q, v, method="appell")


# --- holonomic constraints: the operating configuration must lie on them ------------------------------

G, L = 9.81, 0.8

PENDULUM = nh.Mechanism(
    lambda q, qd, t, p: 0.5 * (qd[0] ** 2 + qd[1] ** 2),  # unit mass, Cartesian bob
    potential=lambda q, t, p: G * q[1],
    holonomic=lambda q, t, p: jnp.stack([q[0] ** 2 + q[1] ** 2 - L**2]),
    dependent=(1,),
    names=("x", "y"),
)


def test_a_configuration_off_the_holonomic_constraints_is_refused():
    """The bob hanging at rest: for the state (x, ẋ), A = [[0, 1], [−g/L, 0]]. At y = −1.1 L it is off
    the rod: refused (eagerly a ValueError naming the constraints and the fix, traced NaN), and
    accepted with complete=mech.restore, which puts it back on the rod."""
    on, off, qd = jnp.array([0.0, -L]), jnp.array([0.0, -1.1 * L]), jnp.zeros(2)
    exact = np.array([[0.0, 1.0], [-G / L, 0.0]])
    lin = nh.linearize(PENDULUM, {}, on, qd, coordinates=(0,), speeds=(0,))
    _agree(lin.A, exact, lin.mass)
    with pytest.raises(ValueError, match="holonomic constraints.*complete=mech.restore"):
        nh.linearize(PENDULUM, {}, off, qd, coordinates=(0,), speeds=(0,))
    traced = jax.jit(lambda q: nh.linearize(PENDULUM, {}, q, qd, coordinates=(0,), speeds=(0,)).A)(off)
    assert np.all(np.isnan(np.asarray(traced)))
    restored = nh.linearize(PENDULUM, {}, off, qd, coordinates=(0,), speeds=(0,), complete=PENDULUM.restore)
    _agree(restored.A, exact, restored.mass)
