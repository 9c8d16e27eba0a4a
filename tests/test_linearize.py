"""`linearize` on small systems whose linearisation is known by hand: a damped pendulum,
and a wheel rolling on a spring written with a velocity constraint, in both choices of
independent speed. Also jit, vmap and grad through it, and its argument checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh._analysis.linearize import linearize


G, L = 9.81, 0.7

PENDULUM = nh.Mechanism(
    lambda q, qd, t, p: 0.5 * p["m"] * L**2 * qd[0] ** 2,
    potential=lambda q, t, p: -p["m"] * G * L * jnp.cos(q[0]),
    forces=lambda q, qd, t, p: -p["c"] * qd,
    names=("theta",),
)
PP = {"m": jnp.asarray(1.5), "c": jnp.asarray(0.2)}


def test_damped_pendulum_about_a_non_equilibrium_state():
    th = 0.3
    lin = linearize(PENDULUM, PP, jnp.array([th]), jnp.array([0.0]))
    mL2 = 1.5 * L**2
    np.testing.assert_allclose(lin.A, [[0.0, 1.0], [-G / L * np.cos(th), -0.2 / mL2]], rtol=1e-14)
    np.testing.assert_allclose(lin.mass, [[mL2]], rtol=1e-14)
    np.testing.assert_allclose(lin.damping, [[0.2]], rtol=1e-14)
    np.testing.assert_allclose(lin.stiffness, [[1.5 * G * L * np.cos(th)]], rtol=1e-14)
    np.testing.assert_allclose(lin.rates, [0.0, -G / L * np.sin(th)], rtol=1e-14)  # not an equilibrium
    assert lin.states == ("theta", "dtheta")
    # declared accelerations are checked: a wrong guess does not hide the true ones
    lin2 = linearize(PENDULUM, PP, jnp.array([th]), jnp.array([0.0]), accelerations=jnp.zeros(1))
    np.testing.assert_allclose(lin2.rates, lin.rates, rtol=1e-14)


# a wheel (mass m, inertia J about its axle, radius r) rolling on a spring of stiffness k:
# q = (x, θ), rolling ẋ − r θ̇ = 0 as a (integrable) velocity constraint
WHEEL = nh.Mechanism(
    lambda q, qd, t, p: 0.5 * p["m"] * qd[0] ** 2 + 0.5 * p["J"] * qd[1] ** 2,
    constraints=lambda q, qd, t, p: jnp.stack([qd[0] - p["r"] * qd[1]]),
    potential=lambda q, t, p: 0.5 * p["k"] * q[0] ** 2,
    names=("x", "theta"),
)
WP = {"m": jnp.asarray(2.0), "J": jnp.asarray(0.05), "r": jnp.asarray(0.25), "k": jnp.asarray(30.0)}


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_constrained_linearisation_in_either_speed(method):
    m, J, r, k = 2.0, 0.05, 0.25, 30.0
    q, qd = jnp.zeros(2), jnp.zeros(2)
    lin = linearize(WHEEL, WP, q, qd, coordinates=(0,), speeds=(0,), method=method)
    M = m + J / r**2  # effective mass for ẋ
    np.testing.assert_allclose(lin.A, [[0.0, 1.0], [-k / M, 0.0]], rtol=1e-14)
    np.testing.assert_allclose(lin.mass, [[M]], rtol=1e-14)
    lin = linearize(WHEEL, WP, q, qd, coordinates=(0,), speeds=(1,), method=method)
    np.testing.assert_allclose(lin.A, [[0.0, r], [-k * r / (m * r**2 + J), 0.0]], rtol=1e-14)
    np.testing.assert_allclose(lin.mass, [[m * r**2 + J]], rtol=1e-14)
    np.testing.assert_allclose(lin.stiffness, [[k * r]], rtol=1e-14)
    assert lin.states == ("x", "dtheta")


def test_jit_vmap_grad():
    def omega2(k):
        p = dict(WP, k=k)
        return -linearize(WHEEL, p, jnp.zeros(2), jnp.zeros(2), coordinates=(0,), speeds=(0,)).A[1, 0]

    M = 2.0 + 0.05 / 0.25**2
    ks = jnp.array([10.0, 20.0, 40.0])
    np.testing.assert_allclose(jax.jit(jax.vmap(omega2))(ks), ks / M, rtol=1e-14)
    np.testing.assert_allclose(jax.grad(omega2)(30.0), 1 / M, rtol=1e-14)
    # eigenvalues ±i√(k/M)
    ev = linearize(WHEEL, WP, jnp.zeros(2), jnp.zeros(2), coordinates=(0,), speeds=(0,)).eigenvalues()
    np.testing.assert_allclose(np.sort(ev.imag), [-np.sqrt(30 / M), np.sqrt(30 / M)], rtol=1e-14)


def test_argument_errors():
    q, qd = jnp.zeros(2), jnp.zeros(2)
    with pytest.raises(ValueError, match="method"):
        linearize(WHEEL, WP, q, qd, method="substituted")
    with pytest.raises(ValueError, match="coordinates"):
        linearize(WHEEL, WP, q, qd, coordinates=(2,))
    with pytest.raises(ValueError, match="independent"):
        linearize(WHEEL, WP, q, qd, speeds=(0, 1))
    with pytest.raises(ValueError, match="accelerations"):
        linearize(WHEEL, WP, q, qd, speeds=(0,), accelerations=jnp.zeros(2))
    # the automatic choice of speeds works on traced values too (made inside the program)
    np.testing.assert_allclose(
        jax.jit(lambda a: linearize(WHEEL, WP, a, qd).A)(q), linearize(WHEEL, WP, q, qd).A, rtol=1e-12, atol=1e-12
    )


def test_refusals_eagerly_and_under_transformations():
    """Eagerly, a singular dependent block for the given speeds and constraints declared linear that
    are not raise ValueErrors naming the fix (checked in the program's own outputs and by
    `check_values`); under jit/vmap the same inputs give NaN matrices, never finite wrong ones."""
    q, qd = jnp.zeros(2), jnp.zeros(2)
    rigid_axle = dict(WP, r=jnp.asarray(0.0))  # ẋ = 0·θ̇: θ̇ cannot be solved from the constraint
    with pytest.raises(ValueError, match="cannot be solved from the constraints"):
        linearize(WHEEL, rigid_axle, q, qd, coordinates=(0,), speeds=(0,))
    # the other speed is fine: ẋ = 0, θ free (no restoring force on it)
    lin = linearize(WHEEL, rigid_axle, q, qd, coordinates=(0,), speeds=(1,))
    np.testing.assert_allclose(lin.A, [[0.0, 0.0], [0.0, 0.0]], atol=1e-14)

    bent = nh.Mechanism(
        WHEEL.kinetic,
        constraints=lambda q, qd, t, p: jnp.stack([qd[0] - p["r"] * qd[1] + 0.3 * qd[1] ** 2]),
        potential=WHEEL.potential,
    )
    with pytest.raises(ValueError, match="nonlinear_constraints=True"):
        linearize(bent, WP, q, jnp.array([0.25, 1.0]), coordinates=(0,), speeds=(1,))
    traced = jax.jit(lambda v: linearize(bent, WP, q, v, coordinates=(0,), speeds=(1,)).A)(jnp.array([0.25, 1.0]))
    assert np.all(np.isnan(np.asarray(traced)))
    # an eager vmap (the parts compiled for the batch, the composition run eagerly): the same
    batched = jax.vmap(lambda v: linearize(bent, WP, q, v, coordinates=(0,), speeds=(1,)))(jnp.array([[0.25, 1.0]] * 2))
    assert all(np.all(np.isnan(np.asarray(x))) for x in (batched.A, batched.mass, batched.rates, batched.state))


def test_knife_edge_in_motion_and_parts_compiled_once(caplog):
    """The knife edge on an incline (jaxnh.models.knife_edge), linearised in motion, against the
    hand calculation; and how it is compiled.

    With ẋ, φ̇ independent (ẏ = ẋ tan φ) the projected equations are m sec²φ ẍ + m tan φ sec²φ ẋ φ̇
    = m g sin α and J φ̈ = 0, so for the state (φ, u = ẋ, w = φ̇)

        A = [[0, 0, 1], [−g sin α sin 2φ − u w sec²φ, −w tan φ, −u tan φ], [0, 0, 0]],

    mass diag(m sec²φ, J), and the rates (w, g sin α cos²φ − u w tan φ, 0): a motion, not an
    equilibrium, in which the derivatives of B and β all count.

    A concrete linearisation is compiled in parts (the kinematics, the dynamics, the checks). Each
    part is compiled exactly once, the dynamics too, although it runs twice (the operating
    accelerations are not given). A later call compiles nothing."""
    import logging

    from jaxnh.models import knife_edge

    mech, p = knife_edge.mechanism(), knife_edge.default_params()
    m, J, g, al = 1.0, 0.2, 9.81, 0.3
    names = ("jit(_kinematics_traced)", "jit(_dynamics_traced)", "jit(_checks_traced)")

    def compilations():
        messages = [r.getMessage() for r in caplog.records if "Finished XLA compilation" in r.getMessage()]
        return sum(any(n in msg for n in names) for msg in messages)

    for phi, u, w, fresh in ((0.4, 0.7, -1.3, True), (-0.9, 1.1, 0.6, False)):
        q, qd = jnp.array([0.3, -0.2, phi]), jnp.array([u, u * np.tan(phi), w])
        caplog.clear()
        with caplog.at_level(logging.DEBUG, logger="jax._src.dispatch"):
            lin = linearize(mech, p, q, qd, coordinates=(2,), speeds=(0, 2))
        # the three parts on the first call (unless another test of this process met this
        # structure first: then none), none on the second
        assert compilations() in ((3, 0) if fresh else (0,))
        sec2, tan = 1 / np.cos(phi) ** 2, np.tan(phi)
        A = [[0, 0, 1], [-g * np.sin(al) * np.sin(2 * phi) - u * w * sec2, -w * tan, -u * tan], [0, 0, 0]]
        np.testing.assert_allclose(lin.A, A, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(lin.mass, [[m * sec2, 0], [0, J]], rtol=1e-13, atol=1e-13)
        rates = [w, g * np.sin(al) * np.cos(phi) ** 2 - u * w * tan, 0]
        np.testing.assert_allclose(lin.rates, rates, rtol=1e-13, atol=1e-13)
        assert lin.states == ("phi", "dx", "dphi")
    # other static arguments, other programs (the position x kept as well: it moves at ẋ and enters
    # nothing), also on later calls that skip fingerprinting the static arguments
    for _ in range(2):
        big = linearize(mech, p, q, qd, coordinates=(0, 2), speeds=(0, 2))
        assert big.states == ("x", "phi", "dx", "dphi")
        np.testing.assert_allclose(big.A[1:, 1:], lin.A, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(big.A[:, 0], 0.0, atol=1e-13)
        np.testing.assert_allclose(big.A[0], [0, 0, 1, 0], atol=1e-13)
