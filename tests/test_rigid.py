"""The rigid-body helper: rotations, T and S by autodiff against hand formulas and the
Gibbs–Appell identity ∂S/∂q̈ = M q̈ + h, and the rolling-contact constraints."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnh._analysis.linearize import lagrange_expression
from jaxnh._model.mechanism import Mechanism
from jaxnh.models import disc as D
from jaxnh.rigid import RigidBodies, rot_axis, rot_x, rot_y, rot_z, skew, vee, Wheel


KEY = jax.random.PRNGKey(7)


def test_rotations_are_proper_and_agree():
    a = 0.83
    for R in (rot_x(a), rot_y(a), rot_z(a)):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
        assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(rot_axis(jnp.array([1.0, 0, 0]), a), rot_x(a), atol=1e-15)
    np.testing.assert_allclose(rot_axis(jnp.array([0, 1.0, 0]), a), rot_y(a), atol=1e-15)
    np.testing.assert_allclose(rot_axis(jnp.array([0, 0, 1.0]), a), rot_z(a), atol=1e-15)
    # right-handed: rotating x by +90° about z gives y
    np.testing.assert_allclose(rot_z(np.pi / 2) @ np.array([1.0, 0, 0]), [0, 1, 0], atol=1e-15)
    w, x = jnp.array([0.3, -1.2, 2.0]), jnp.array([1.1, 0.4, -0.7])
    np.testing.assert_allclose(skew(w) @ x, jnp.cross(w, x), atol=1e-15)
    np.testing.assert_allclose(vee(skew(w)), w, atol=1e-15)


def disc_T_by_hand(q, qd, p):
    """Disc energy from the classical angular velocity in the lean frame (e1, e2, e3):
    ω = (φ̇, ψ̇ sin φ + θ̇, ψ̇ cos φ), with the centre velocity by differentiation of
    c = (x, y, 0) + r (sin ψ sin φ, −cos ψ sin φ, cos φ)."""
    x, y, psi, phi, th = q
    xd, yd, psid, phid, thd = qd
    r = p["r"]
    c = lambda q_: jnp.stack(
        [q_[0] + r * jnp.sin(q_[2]) * jnp.sin(q_[3]), q_[1] - r * jnp.cos(q_[2]) * jnp.sin(q_[3]), r * jnp.cos(q_[3])]
    )
    v = jax.jvp(c, (q,), (qd,))[1]
    w1, w2, w3 = phid, psid * jnp.sin(phi) + thd, psid * jnp.cos(phi)
    return 0.5 * p["m"] * v @ v + 0.5 * (p["I1"] * (w1**2 + w3**2) + p["I3"] * w2**2)


def test_kinetic_energy_matches_hand_formula():
    p = D.default_params()
    k1, k2 = jax.random.split(KEY)
    qs, qds = jax.random.normal(k1, (20, 5)), jax.random.normal(k2, (20, 5))
    T = jax.jit(jax.vmap(lambda q, qd: D.bodies().kinetic(q, qd, 0.0, p)))(qs, qds)
    T_hand = jax.jit(jax.vmap(lambda q, qd: disc_T_by_hand(q, qd, p)))(qs, qds)
    np.testing.assert_allclose(T, T_hand, rtol=1e-13)


# an asymmetric body (full inertia tensor with products) flying freely and rheonomically
I_ASYM = jnp.array([[2.0, 0.3, -0.2], [0.3, 1.5, 0.1], [-0.2, 0.1, 1.1]])


def asym_poses(q, t, p):
    R = rot_z(q[3]) @ rot_x(q[4]) @ rot_y(q[5] + 0.3 * t)
    r = q[:3] + jnp.array([0.1 * jnp.sin(t), 0.0, 0.2]) + 0.5 * jnp.array([jnp.sin(q[4]), 0.0, jnp.cos(q[5])])
    return [(r, R)]


ASYM = RigidBodies(asym_poses, lambda p: [(p["m"], p["I"])], gravity=lambda p: jnp.array([0.0, 0.0, -9.81]))


def test_gibbs_appell_identity_for_an_asymmetric_body():
    """∂S/∂q̈ = d/dt ∂T/∂q̇ − ∂T/∂q: S (with its ω̇·(ω × Iω) term) and T describe the same body."""
    p = {"m": jnp.asarray(1.7), "I": I_ASYM}
    mech = Mechanism(ASYM.kinetic)
    k = jax.random.split(KEY, 4)
    qs, qds, qdds = (jax.random.normal(kk, (10, 6)) for kk in k[:3])
    ts = jax.random.uniform(k[3], (10,))

    def both(q, qd, qdd, t):
        dS = jax.grad(ASYM.acceleration_energy, argnums=2)(q, qd, qdd, t, p)
        return dS, lagrange_expression(mech, q, qd, qdd, t, p)

    dS, L = jax.jit(jax.vmap(both))(qs, qds, qdds, ts)
    np.testing.assert_allclose(dS, L, rtol=1e-11, atol=1e-11)


def test_potential_and_body_velocities():
    p = {"m": jnp.asarray(1.7), "I": I_ASYM}
    q = jnp.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    r, _ = asym_poses(q, 0.0, p)[0]
    assert np.isclose(ASYM.potential(q, 0.0, p), 1.7 * 9.81 * r[2])
    # a spin q̇5 about the body y axis, plus the rheonomic 0.3 rad/s, is Ω = (0, q̇5 + 0.3, 0) in body axes
    ((_, w),) = ASYM.velocities(q, jnp.zeros(6).at[5].set(2.0), 0.0, p)
    np.testing.assert_allclose(w, [0.0, 2.0 + 0.3, 0.0], atol=1e-14)


def test_wheel_contact_point_and_rolling():
    p = D.default_params()
    k1, k2 = jax.random.split(KEY)
    qs = jax.random.uniform(k1, (20, 5), minval=-1.2, maxval=1.2)
    qds = jax.random.normal(k2, (20, 5))
    # the contact point of the disc is (x, y, 0) by construction; height 0 however it leans
    P = jax.vmap(lambda q: D.WHEEL.contact_point(q, 0.0, p))(qs)
    np.testing.assert_allclose(P, np.c_[qs[:, :2], np.zeros(20)], atol=1e-15)
    np.testing.assert_allclose(jax.vmap(lambda q: D.WHEEL.height(q, 0.0, p))(qs), 0.0, atol=1e-15)
    # rolling: the contact point moves at r θ̇ along the heading, whatever ψ̇, φ̇ (see disc.py)
    rolling_qd = (
        qds.at[:, 0].set(p["r"] * qds[:, 4] * jnp.cos(qs[:, 2])).at[:, 1].set(p["r"] * qds[:, 4] * jnp.sin(qs[:, 2]))
    )
    slip = jax.vmap(lambda q, qd: D.WHEEL.slip(q, qd, 0.0, p))(qs, rolling_qd)
    np.testing.assert_allclose(slip, 0.0, atol=1e-14)
    # sliding sideways is slip
    slip = jax.vmap(lambda q, qd: D.WHEEL.slip(q, qd.at[1].add(0.3), 0.0, p))(qs, rolling_qd)
    np.testing.assert_allclose(slip[:, 1], 0.3, atol=1e-14)


def test_wheel_on_a_z_down_plane_and_errors():
    # z down: a wheel of radius 0.3 with its centre at height 0.3 above the ground touches it
    w = Wheel(lambda q, t, p: (jnp.array([q[0], 0.0, -0.3]), rot_y(q[1])), lambda p: 0.3, normal=(0.0, 0.0, -1.0))
    q = jnp.array([1.0, 0.4])
    np.testing.assert_allclose(w.contact_point(q, 0.0, None), [1.0, 0.0, 0.0], atol=1e-15)
    assert abs(w.height(q, 0.0, None)) < 1e-15
    # rolling forward (+x) with the axle along +y needs a negative spin in these axes
    assert np.allclose(w.slip(q, jnp.array([0.6, -2.0]), 0.0, None), 0.0)
    with pytest.raises(ValueError, match="normal"):
        Wheel(lambda q, t, p: None, lambda p: 1.0, normal=(0.0, 0.0, 2.0))
    with pytest.raises(ValueError, match="axle"):
        Wheel(lambda q, t, p: None, lambda p: 1.0, axle=3)
    bad = RigidBodies(lambda q, t, p: [(jnp.zeros(2), jnp.eye(3))], lambda p: [(1.0, jnp.eye(3))])
    with pytest.raises(ValueError, match="position r"):
        bad.kinetic(jnp.zeros(1), jnp.zeros(1), 0.0, None)
    with pytest.raises(ValueError, match="gravity"):
        ASYM.__class__(asym_poses, lambda p: [(1.0, I_ASYM)]).potential(jnp.zeros(6), 0.0, None)
