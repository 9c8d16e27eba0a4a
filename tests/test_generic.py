"""A generic mechanism (s = 4, m = 2): configuration-dependent mass matrix, rheonomic
kinetic energy and constraints with free terms. "appell" must equal "lagrange", and
the constraints must hold along the motion."""

from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh._equations.split import best_partition
from jaxnh._equations.terms import mass_and_velocity_terms


P = {"m": 1.3, "I": 0.4, "J": 0.2, "r": 0.3, "k": 0.8, "c": 0.05}


def mass_matrix(q, p):
    """Positive definite, configuration dependent."""
    C = jnp.array(
        [
            [1.0, 0.2 * jnp.sin(q[2]), 0.0, 0.1 * jnp.cos(q[3])],
            [0.0, 1.0, 0.3 * jnp.cos(q[2]), 0.0],
            [0.1 * jnp.sin(q[3]), 0.0, 1.0, 0.2 * jnp.sin(q[2] - q[3])],
            [0.0, 0.1, 0.0, 1.0],
        ]
    )
    return C.T @ jnp.diag(jnp.array([p["m"], p["m"], p["I"], p["J"]])) @ C


def kinetic(q, qd, t, p):
    """½ qdᵀ M(q) qd plus a rheonomic term (a frame moving with speed u(t))."""
    u = jnp.array([0.2 * jnp.sin(1.3 * t), 0.1 * t, 0.0, 0.0])
    return 0.5 * qd @ mass_matrix(q, p) @ qd + p["m"] * jnp.dot(u, qd) * jnp.cos(q[2]) + 0.5 * p["m"] * jnp.dot(u, u)


def constraints(q, qd, t, p):
    """A knife edge on a moving surface and a rolling wheel with a varying ratio."""
    x, y, th, ph = q
    return jnp.stack(
        [
            qd[0] * jnp.sin(th) - qd[1] * jnp.cos(th) - 0.1 * jnp.sin(t),
            p["r"] * (1 + 0.2 * jnp.sin(t)) * qd[3] - (qd[0] * jnp.cos(th) + qd[1] * jnp.sin(th)),
        ]
    )


def forces(q, qd, t, p):
    return -p["c"] * qd + jnp.array([0.0, 0.0, 0.1 * jnp.cos(t), 0.0])


def potential(q, t, p):
    return 0.5 * p["k"] * (q[0] ** 2 + 0.5 * q[1] ** 2) + 0.3 * jnp.cos(q[2])


MECH = nh.Mechanism(
    kinetic, constraints=constraints, forces=forces, potential=potential, names=("x", "y", "theta", "phi")
)


def random_state(key):
    k1, k2, k3 = jax.random.split(key, 3)
    q = jax.random.normal(k1, (4,))
    t = jax.random.uniform(k3, minval=0, maxval=5)
    qd = nh.consistent_velocities(MECH, q, jax.random.normal(k2, (4,)), t, P)
    return q, qd, t


@pytest.fixture(scope="module")
def states():
    return jax.vmap(random_state)(jax.random.split(jax.random.PRNGKey(3), 40))


def test_consistent_velocities_satisfy_constraints(states):
    q, qd, t = states
    c = jax.vmap(lambda a, b, s: constraints(a, b, s, P))(q, qd, t)
    assert np.max(np.abs(c)) < 1e-12


@pytest.mark.parametrize("independent", [(2, 3), (0, 2)])
def test_appell_equals_lagrange_accelerations(states, independent):
    q, qd, t = states

    def both(q, qd, t):
        a_l, lam_l = nh.accelerations(MECH, q, qd, t, P, method="lagrange")
        a_a, lam_a = nh.accelerations(MECH, q, qd, t, P, method="appell", independent=independent)
        return a_l, lam_l, a_a, lam_a

    a_l, lam_l, a_a, lam_a = jax.jit(jax.vmap(both))(q, qd, t)
    np.testing.assert_allclose(a_a, a_l, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(lam_a, lam_l, rtol=1e-10, atol=1e-10)

    # accelerations satisfy the differentiated constraints
    def cdot(q, qd, qdd, t):
        return jax.jvp(lambda a, b, s: constraints(a, b, s, P), (q, qd, t), (qd, qdd, jnp.ones_like(t)))[1]

    assert np.max(np.abs(jax.vmap(cdot)(q, qd, a_l, t))) < 1e-10


@pytest.fixture(scope="module")
def trajectories():
    q0 = jnp.array([0.2, -0.1, 0.4, 0.0])
    qd0 = nh.consistent_velocities(MECH, q0, jnp.array([0.5, 0.3, -0.4, 0.1]), 0.0, P)
    ts = jnp.linspace(0.0, 8.0, 81)
    kw: dict[str, Any] = dict(rtol=1e-12, atol=1e-12, solver=diffrax.Dopri8(), record=("residual", "energy"))
    return {
        "lagrange": nh.simulate(MECH, P, q0, qd0, ts, method="lagrange", **kw),
        "appell": nh.simulate(MECH, P, q0, qd0, ts, method="appell", **kw),  # automatic split
    }


def test_appell_equals_lagrange_trajectories(trajectories):
    a, l = trajectories["appell"], trajectories["lagrange"]
    assert bool(a.success) and bool(l.success)
    err = max(np.max(np.abs(a.q - l.q)), np.max(np.abs(a.qd - l.qd)))
    print(f"appell vs lagrange trajectory difference {err:.2e}")
    assert err < 1e-9


def test_constraints_hold_along_the_motion(trajectories):
    # Appell integrates only independent velocities: exact to rounding.
    assert np.max(np.abs(trajectories["appell"].residual)) < 1e-12
    # Lagrange keeps the derivative of the constraint: drift at the tolerance level.
    assert np.max(np.abs(trajectories["lagrange"].residual)) < 1e-9


def test_redundant_constraints_give_minimum_norm_multipliers():
    """The same knife-edge constraint twice (and a multiple of it): accelerations unchanged,
    multipliers finite and of minimum norm (split equally)."""

    def c_red(q, qd, t, p):
        c = constraints(q, qd, t, p)
        return jnp.stack([c[0], c[1], c[0], 2.0 * c[1]])

    red = nh.Mechanism(kinetic, constraints=c_red, forces=forces, potential=potential)
    q, qd, t = random_state(jax.random.PRNGKey(7))
    a, lam = nh.accelerations(MECH, q, qd, t, P, method="lagrange")
    assert lam is not None  # Lagrange's form has multipliers
    a_r, lam_r = jax.jit(lambda q, qd, t: nh.accelerations(red, q, qd, t, P, method="lagrange"))(q, qd, t)
    assert np.all(np.isfinite(a_r)) and np.all(np.isfinite(lam_r))
    np.testing.assert_allclose(a_r, a, rtol=1e-9, atol=1e-9)
    # min-norm: lam0 = lam_r0 + lam_r2 split evenly; lam1 = lam_r1 + 2 lam_r3 with lam_r3 = 2 lam_r1
    np.testing.assert_allclose(lam_r, [lam[0] / 2, lam[1] / 5, lam[0] / 2, 2 * lam[1] / 5], rtol=1e-8, atol=1e-9)


def test_appell_with_user_acceleration_energy_matches():
    """S supplied by the user (½ qddᵀ M qdd + qddᵀ h from the known M) gives the same."""

    def S(q, qd, qdd, t, p):
        M = mass_matrix(q, p)
        h = mass_and_velocity_terms(MECH, q, qd, t, p)[1]
        return 0.5 * qdd @ M @ qdd + qdd @ h

    mech_S = nh.Mechanism(kinetic, constraints=constraints, forces=forces, potential=potential, acceleration_energy=S)
    q, qd, t = random_state(jax.random.PRNGKey(11))
    a_S, _ = nh.accelerations(mech_S, q, qd, t, P, method="appell", independent=(2, 3))
    a_l, _ = nh.accelerations(MECH, q, qd, t, P, method="lagrange")
    np.testing.assert_allclose(a_S, a_l, rtol=1e-10, atol=1e-10)


def test_singular_split_is_refused():
    """theta' appears in no constraint, so it cannot be a dependent velocity."""
    q, qd, t = random_state(jax.random.PRNGKey(5))
    with pytest.raises(ValueError, match=r"independent=\(1, 3\).*singular"):
        nh.accelerations(MECH, q, qd, t, P, method="appell", independent=(1, 3))


def test_automatic_split_of_many_constraints_is_not_refused():
    """A chain of m = 90 equal speeds (qd_k+1 = qd_k, unit masses): every block of m columns of its
    row-normalised A is well conditioned (smallest singular value 0.012), but the block's volume
    (its determinant, 2^(−m/2) = 2.8e-14) is below any fixed threshold that also catches a block
    singular to rounding (1e3 eps = 2.2e-13). The check judges the smallest singular value."""
    m = 90

    def T(q, qd, t, p):
        return 0.5 * jnp.sum(qd**2)

    def c(q, qd, t, p):
        return qd[1:] - qd[:-1]

    mech = nh.Mechanism(T, constraints=c)
    q, qd = jnp.zeros(m + 1), jnp.ones(m + 1)
    _, volume = best_partition(mech, q, qd, 0.0, None, m + 1, m)
    assert float(volume) < 1e3 * np.finfo(np.float64).eps  # the case a volume test would refuse
    ok, status = jax.jit(lambda q, qd: nh.Appell().bind(mech, m + 1, m).check(q, qd, 0.0, None))(q, qd)
    assert bool(ok) and status == nh.STATUS.successful
    # a block singular to rounding still is refused: one of the m equalities written twice
    twice = nh.Mechanism(
        T, constraints=lambda q, qd, t, p: jnp.concatenate([c(q, qd, t, p)[:-1], c(q, qd, t, p)[-2:-1]])
    )
    ok, status = nh.Appell().bind(twice, m + 1, m).check(q, qd, 0.0, None)
    assert not bool(ok) and status == nh.STATUS.singular_split


def test_check_given_agrees_with_check_and_keeps_a_subclass_check():
    """`check_given` (what simulate calls, with ∂c/∂qd and the inertias its own checks evaluated)
    gives `check`'s verdict, for a regular and a singular fixed split and the automatic one; a
    subclass that overrides `check` has its own check run by simulate."""
    from jaxnh._model.checks import mass_matrix_check

    q, qd, t = random_state(jax.random.PRNGKey(5))
    A = jax.jacfwd(lambda v: MECH.constraint(q, v, t, P))(qd)
    inertias = mass_matrix_check(MECH, q, qd, t, P)[1]
    s, m = q.shape[0], A.shape[0]
    for independent, good in ((None, True), ((2, 3), True), ((1, 3), False)):
        form = nh.Appell(independent=independent).bind(MECH, s, m)
        ok, status = form.check(q, qd, t, P)
        ok_given, status_given = form.check_given(q, qd, t, P, A, inertias)
        assert bool(ok) == bool(ok_given) == good and bool(status == status_given)

    class Refusing(nh.Appell):
        def check(self, q, qd, t, params):
            ok, _ = super().check(q, qd, t, params)
            return ok & False, nh.STATUS.singular_split

    sol = nh.simulate(MECH, P, q, qd, jnp.linspace(0.0, 0.1, 3), method=Refusing(), throw=False)
    assert sol.status == nh.STATUS.singular_split


def test_appell_leaving_the_root_of_a_nonlinear_constraint_fails_clearly():
    """ż² + (x + a) ż − 1 = 0 with a free ẋ = −1: the motion follows the root
    ż = (−u + √(u² + 4))/2, u = x + a, through u = 0 (Lagrange's run, checked against it). Appell's
    equations solve for ż by Newton's method from zero, which reaches that root only while u > 0
    (the other one beyond): the run must stop there with `nonlinear_root_left`, eagerly and under
    jit, not go on along the other root. Tolerance of Lagrange's answer: rtol 1e-8 over 3 s, a
    smooth motion of size 1: 1e-6."""

    def T(q, qd, t, p):
        return 0.5 * (qd[0] ** 2 + qd[1] ** 2)

    def c(q, qd, t, p):
        return jnp.stack([qd[1] ** 2 + (q[0] + p) * qd[1] - 1.0])

    mech = nh.Mechanism(T, constraints=c, nonlinear_constraints=True, independent=(0,))
    a = 0.3
    root = lambda u: (-u + np.sqrt(u * u + 4.0)) / 2  # noqa: E731
    q0, qd0 = jnp.array([1.0, 0.0]), jnp.array([-1.0, root(1.0 + a)])
    ts = jnp.linspace(0.0, 3.0, 31)
    lag = nh.simulate(mech, a, q0, qd0, ts, method="lagrange")
    x = 1.0 - np.asarray(ts)
    np.testing.assert_allclose(lag.q[:, 0], x, atol=1e-6)
    np.testing.assert_allclose(lag.qd[:, 1], root(x + a), atol=1e-6)
    sol = nh.simulate(mech, a, q0, qd0, ts, method="appell", throw=False)
    assert sol.status == nh.STATUS.nonlinear_root_left, sol.message
    jitted = jax.jit(lambda p: nh.simulate(mech, p, q0, qd0, ts, method="appell", throw=False).status)(a)
    assert jitted == nh.STATUS.nonlinear_root_left
    with pytest.raises(nh.SimulationError, match="method='lagrange'"):
        nh.simulate(mech, a, q0, qd0, ts, method="appell")


@pytest.mark.slow
def test_nonlinear_constraint_by_chetaev_conserves_energy_and_formulations_agree():
    """A point whose speed in the plane is tied to a rotor: qd2 = sqrt(qd0² + qd1²).

    The constraint is homogeneous of degree one in qd, so by Chetaev's rule
    the constraint force Aᵀλ does power λ A qd = λ c = 0: with conservative
    forces only, T + V is conserved.
    """

    def T(q, qd, t, p):
        return 0.5 * (1.2 * qd[0] ** 2 + 1.2 * qd[1] ** 2 + 0.3 * qd[2] ** 2)

    def c(q, qd, t, p):
        return jnp.stack([qd[2] - jnp.sqrt(qd[0] ** 2 + qd[1] ** 2)])

    def V(q, t, p):
        return 0.5 * (q[0] ** 2 + 2.0 * q[1] ** 2) + 0.2 * jnp.cos(q[2])

    mech = nh.Mechanism(T, constraints=c, potential=V, nonlinear_constraints=True, independent=(0, 1))
    q0 = jnp.array([1.0, 0.0, 0.0])
    qd0 = jnp.array([0.3, 0.8, jnp.sqrt(0.73)])
    ts = jnp.linspace(0.0, 6.0, 61)
    kw: dict[str, Any] = dict(rtol=1e-12, atol=1e-12, solver=diffrax.Dopri8(), record=("energy", "residual"))
    a = nh.simulate(mech, None, q0, qd0, ts, method="appell", **kw)
    l = nh.simulate(mech, None, q0, qd0, ts, method="lagrange", **kw)
    assert np.max(np.abs(a.q - l.q)) < 1e-9 and np.max(np.abs(a.qd - l.qd)) < 1e-9
    for sol in (a, l):
        E = np.asarray(sol.energy)
        # global error of a rtol=1e-12 solve over 6 s is a few 1e-10; a wrong
        # constraint force (not along ∂c/∂qd) would change E at order one
        assert np.max(np.abs(E - E[0])) < 1e-9 * abs(E[0])
        assert sol.residual is not None and np.max(np.abs(sol.residual)) < 1e-9
    # the flag is required: the same constraint without it is refused
    with pytest.raises(ValueError, match="nonlinear_constraints=True"):
        nh.simulate(nh.Mechanism(T, constraints=c, potential=V), None, q0, qd0, ts)


def _unit_speed(method_independent):
    """A point mass in the plane moving at unit speed: c = qd0² + qd1² − 1, nonlinear in the velocities."""

    def T(q, qd, t, p):
        return 0.5 * (qd[0] ** 2 + qd[1] ** 2)

    def c(q, qd, t, p):
        return jnp.stack([qd[0] ** 2 + qd[1] ** 2 - 1.0])

    return nh.Mechanism(T, constraints=c, nonlinear_constraints=True, independent=method_independent)


def test_nonlinear_constraint_newton_that_cannot_converge_is_refused():
    """Newton's method for the dependent velocity qd1 of qd1² = 1 − qd0² starts at qd1 = 0, where
    ∂c/∂qd1 = 0: it cannot converge. The solve is refused with the status that names the cause
    (before: a fixed number of iterations, unchecked, gave NaN reported as a step limit), eagerly,
    under jit and under vmap; consistent_velocities refuses too."""
    mech = _unit_speed((0,))
    q0, qd0, ts = jnp.zeros(2), jnp.array([0.6, 0.8]), jnp.linspace(0.0, 1.0, 5)
    with pytest.raises(nh.InvalidInitialState, match="could not be solved"):
        nh.simulate(mech, None, q0, qd0, ts, method="appell")
    jitted = jax.jit(lambda x: nh.simulate(mech, None, q0, x, ts, method="appell", throw=False).status)
    assert jitted(qd0) == nh.STATUS.nonlinear_constraints_unsolved
    batched = jax.vmap(lambda x: nh.simulate(mech, None, q0, x, ts, method="appell", throw=False).status)(
        jnp.stack([qd0, qd0])
    )
    assert bool(jnp.all(batched == nh.STATUS.nonlinear_constraints_unsolved))
    # Lagrange needs no such solve: the same motion (straight line at unit speed) is right
    sol = nh.simulate(mech, None, q0, qd0, ts, method="lagrange", rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sol.q[-1], qd0 * ts[-1], rtol=1e-8)
    with pytest.raises(ValueError, match="did not satisfy the constraints"):
        nh.consistent_velocities(mech, q0, jnp.zeros(2), 0.0, None)  # ∂c/∂qd = 0 at qd = 0
