"""Unit-quaternion kinematics of `jaxnh.rigid`: R(e) is a proper rotation for any nonzero e, agrees with
`rot_axis` and is inverted by `quaternion_from_rotation` in each of Shepperd's branches; the quaternion rate
turns R at the given angular velocity and keeps |e|; a torque-free rigid body integrated in quaternions
conserves its energy and angular momentum; the Gibbs–Appell function gives Euler's equations.

Tolerances are multiples of the dtype's machine epsilon EPS (the spacing of floats at 1): each quantity
compared is a sum of a handful of products of O(1) numbers, so a correct formula is off by a few
roundings of its largest terms, and a wrong one by O(1). The factor in front of EPS is a bound on the
number of roundings (with margin), times the scale of the compared quantity, stated at each check.
Two tolerances come from elsewhere, derived where they are used: the finite-difference check of a
gradient (EPS^(2/3), from the step that balances truncation and rounding) and the integration of a
torque-free body (the solver's rtol times its number of steps).
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnh.rigid import (
    angular_velocity,
    angular_velocity_from_quaternion,
    quat_multiply,
    quaternion_from_axis_angle,
    quaternion_from_rotation,
    quaternion_rate,
    rigid_body_acceleration_energy,
    rot_axis,
    rot_x,
    rot_y,
    rot_z,
    rotation_from_quaternion,
    skew,
)


EPS = float(np.finfo(np.float64).eps)  # 2.2e-16

# an asymmetric body: a full inertia tensor with products of inertia, kg·m² (positive definite;
# principal moments 1.00, 1.44, 2.16)
INERTIA = np.array([[2.0, 0.3, -0.2], [0.3, 1.5, 0.1], [-0.2, 0.1, 1.1]])

# Test data come from NumPy: each eager JAX operation is compiled on its first use, and the checks are
# jitted as a whole, so the file spends its time on the functions under test.


def rng(seed=44):
    return np.random.default_rng(seed)


def random_quaternions(n, scale=1.0, seed=44):
    """n quaternions (n, 4) uniformly distributed in orientation, of norm `scale` (NumPy)."""
    e = rng(seed).standard_normal((n, 4))
    return scale * e / np.linalg.norm(e, axis=1, keepdims=True)


def near_half_turns():
    """Unit quaternions near and at half turns about axes close to x, y and z (Shepperd's x, y, z
    branches: the largest component is x, y or z), on both sides of w = 0, and near the identity (w)."""
    out = []
    tilt = np.array([0.01, -0.02, 0.015])
    for k in range(3):
        n = np.eye(3)[k] + tilt
        n = n / np.linalg.norm(n)
        for a in (np.pi, np.pi - 1e-9, np.pi + 1e-9, np.pi - 1e-3, np.pi + 0.3, 2.5):
            out.append(np.concatenate([[np.cos(a / 2)], np.sin(a / 2) * n]))
    for a in (0.0, 1e-9, 0.5):
        out.append(np.array([np.cos(a / 2), *(np.sin(a / 2) * np.array([0.6, 0.0, 0.8]))]))
    return np.array(out)


def test_hamilton_product():
    i, j, k, one = (np.eye(4)[n] for n in (1, 2, 3, 0))
    np.testing.assert_array_equal(quat_multiply(i, j), k)
    np.testing.assert_array_equal(quat_multiply(j, i), -k)
    np.testing.assert_array_equal(quat_multiply(i, i), -one)
    np.testing.assert_array_equal(quat_multiply(quat_multiply(i, j), k), -one)
    # composes like the matrices: R(a ⊗ b) = R(a) R(b); each side is a few roundings of O(1) entries
    a, b = random_quaternions(2)
    np.testing.assert_allclose(
        rotation_from_quaternion(quat_multiply(a, b)),
        np.asarray(rotation_from_quaternion(a)) @ np.asarray(rotation_from_quaternion(b)),
        rtol=0,
        atol=32 * EPS,
    )


def test_rotation_is_proper_for_unit_and_non_unit_quaternions():
    """RRᵀ = 1 and det R = 1 for any nonzero e: the homogeneous form divided by |e|². Each entry of R
    is ≲ 6 roundings of O(1) terms; RRᵀ sums 3 products of them (≲ 2·3·6 + 3 ≈ 40 EPS): 64 EPS. det R
    has 6 triple products (≲ 6·3·6 ≈ 110 EPS): 128 EPS."""
    scales = np.concatenate([[1.0, 1.0 + 1e-8, 1.0 - 3e-7, 1e-3, 2.5, 1e3], np.full(14, 0.7)])
    es = random_quaternions(20) * scales[:, None]
    R_of = jax.jit(jax.vmap(rotation_from_quaternion))
    Rs = np.asarray(R_of(es))
    RRt = np.einsum("nij,nkj->nik", Rs, Rs)
    np.testing.assert_allclose(RRt, np.broadcast_to(np.eye(3), RRt.shape), rtol=0, atol=64 * EPS)
    np.testing.assert_allclose(np.linalg.det(Rs), 1.0, rtol=0, atol=128 * EPS)
    # e and c·e (c ≠ 0, also c < 0) are the same rotation; relative to O(1) entries, a few roundings
    np.testing.assert_allclose(R_of(-3.0 * es), Rs, rtol=0, atol=32 * EPS)
    assert np.all(np.isnan(rotation_from_quaternion(np.zeros(4))))  # e = 0 is no rotation


def test_axis_angle_agrees_with_rot_axis():
    """Both are a few roundings of O(1) entries (sin, cos, products): 32 EPS."""
    axes = rng().standard_normal((10, 3))
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([[0.0, np.pi, -np.pi / 2, 3.0], rng().uniform(-7, 7, 6)])
    es = jax.jit(jax.vmap(quaternion_from_axis_angle))(axes, angles)
    np.testing.assert_allclose(np.linalg.norm(es, axis=1), 1.0, rtol=0, atol=4 * EPS)
    np.testing.assert_allclose(
        jax.jit(jax.vmap(rotation_from_quaternion))(es),
        jax.jit(jax.vmap(rot_axis))(axes, angles),
        rtol=0,
        atol=32 * EPS,
    )
    a = 0.83
    for k, rot in enumerate((rot_x, rot_y, rot_z)):  # eagerly, and against the elementary rotations
        np.testing.assert_allclose(
            rotation_from_quaternion(quaternion_from_axis_angle(np.eye(3)[k], a)), rot(a), rtol=0, atol=32 * EPS
        )


def test_round_trip_in_every_branch():
    """R → e → R, with e back to ±e (w ≥ 0). The chosen column of Shepperd's K has entries ≲ 4 with a few
    roundings each, divided by its norm ≥ 2: e is ≲ 8 EPS off (tolerance 32 EPS); R of it then ≲ 4·8
    EPS off (64 EPS)."""
    es = np.concatenate([random_quaternions(30), near_half_turns()])
    branches = set(np.argmax(np.abs(es), axis=1).tolist())  # K's diagonal is 4 e_k²
    assert branches == {0, 1, 2, 3}, branches
    R_of = jax.jit(jax.vmap(rotation_from_quaternion))
    Rs = R_of(es)
    back = np.asarray(jax.jit(jax.vmap(quaternion_from_rotation))(Rs))
    assert np.all(back[:, 0] >= 0)
    expected = es * np.where(es[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(back, expected, rtol=0, atol=32 * EPS)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, rtol=0, atol=4 * EPS)
    np.testing.assert_allclose(R_of(back), Rs, rtol=0, atol=64 * EPS)


def test_from_rotation_is_differentiable_in_every_branch():
    """Along a motion e(t) on the unit sphere (w > 0), d/dt quaternion_from_rotation(R(e(t))) = ė, in each
    branch: the derivative of R (≲ 6 roundings, times |ė|) through the normalised column (≲ 8): 64 EPS |ė|."""
    es = np.concatenate([random_quaternions(8), near_half_turns()])
    es = es * np.where(es[:, :1] < 0, -1.0, 1.0)
    es = es[es[:, 0] > 1e-6]  # away from the jump e → −e at w = 0
    assert set(np.argmax(np.abs(es), axis=1).tolist()) == {0, 1, 2, 3}
    omegas = rng(1).standard_normal((es.shape[0], 3))

    def check(e, w):
        ed = quaternion_rate(e, w)
        _, d = jax.jvp(lambda e_: quaternion_from_rotation(rotation_from_quaternion(e_)), (e,), (ed,))
        g = jax.grad(lambda R: quaternion_from_rotation(R) @ jnp.array([0.3, -1.0, 0.5, 2.0]))
        return jnp.max(jnp.abs(d - ed)) / jnp.linalg.norm(ed), g(rotation_from_quaternion(e))

    err, g = jax.jit(jax.vmap(check))(es, omegas)
    assert float(np.max(err)) <= 64 * EPS
    assert np.all(np.isfinite(g))


def unit_and_non_unit_states():
    es = random_quaternions(12) * np.linspace(0.5, 2.0, 12)[:, None]
    return es, 3.0 * rng(2).standard_normal((12, 3))


@pytest.mark.parametrize("frame", ["body", "space"])
def test_rate_turns_the_rotation_at_omega_and_keeps_the_norm(frame):
    """d/dt R(e(t)) = R [ω]× (body) or [ω]× R (space), by jax.jvp, for unit and non-unit e. Ṙ entries are
    ≲ 10 roundings of terms of size |ω| (the rate, R's derivative, the products): 64 EPS |ω|, as is
    the module's `angular_velocity(R, Ṙ)` against ω. e·ė sums 4 products of size |e|²|ω|, each a few
    roundings: 16 EPS |e|² |ω|."""

    def check(e, w):
        ed = quaternion_rate(e, w, frame=frame)
        R, Rd = jax.jvp(rotation_from_quaternion, (e,), (ed,))
        expected = R @ skew(w) if frame == "body" else skew(w) @ R
        wn = jnp.linalg.norm(w)
        return (
            jnp.max(jnp.abs(Rd - expected)) / wn,
            jnp.abs(e @ ed) / (e @ e) / wn,
            jnp.max(jnp.abs(angular_velocity(R, Rd, frame=frame) - w)) / wn,
        )

    rotation, norm, omega = jax.jit(jax.vmap(check))(*unit_and_non_unit_states())
    assert float(np.max(rotation)) <= 64 * EPS
    assert float(np.max(norm)) <= 16 * EPS
    assert float(np.max(omega)) <= 64 * EPS


@pytest.mark.parametrize("frame", ["body", "space"])
def test_angular_velocity_from_quaternion_inverts_the_rate(frame):
    """ω → ė → ω, also with a radial part 0.7 e added to ė (a change of |e|, no rotation). Two products
    of 4-vectors, each entry ≲ 8 roundings of size |ω|: 32 EPS |ω|; the radial part, of size |e|, adds
    its roundings: 32 EPS (|ω| + 1)."""

    def check(e, w):
        ed = quaternion_rate(e, w, frame=frame)
        wn = jnp.linalg.norm(w)
        plain = jnp.max(jnp.abs(angular_velocity_from_quaternion(e, ed, frame=frame) - w)) / wn
        radial = jnp.max(jnp.abs(angular_velocity_from_quaternion(e, ed + 0.7 * e, frame=frame) - w)) / (wn + 1)
        return plain, radial

    plain, radial = jax.jit(jax.vmap(check))(*unit_and_non_unit_states())
    assert float(np.max(plain)) <= 32 * EPS
    assert float(np.max(radial)) <= 32 * EPS


def test_frame_and_shapes_are_refused_by_name():
    e, w = np.array([1.0, 0, 0, 0]), np.zeros(3)
    with pytest.raises(ValueError, match="quaternion_rate: frame must be 'body' or 'space'; got 'world'"):
        quaternion_rate(e, w, frame="world")
    with pytest.raises(ValueError, match="angular_velocity_from_quaternion: frame must be 'body' or 'space'"):
        angular_velocity_from_quaternion(e, e, frame="inertial")
    with pytest.raises(ValueError, match=r"rotation_from_quaternion e: expected shape \(4,\), got shape \(3,\)"):
        rotation_from_quaternion(w)
    with pytest.raises(ValueError, match=r"quaternion_from_rotation R: expected shape \(3, 3\)"):
        quaternion_from_rotation(np.eye(4))


def test_gibbs_appell_function_gives_euler_equations():
    """∂S/∂ω̇ = I ω̇ + ω × I ω (by jax.grad); both sides are sums of a few products of size |I||ω|²,
    |I||ω̇|: 32 EPS times that scale. S is quadratic in ω̇ with Hessian I."""
    ws, wds = 2.0 * rng(3).standard_normal((10, 3)), 2.0 * rng(4).standard_normal((10, 3))
    dS = jax.jit(jax.vmap(jax.grad(rigid_body_acceleration_energy, argnums=2), in_axes=(None, 0, 0)))(INERTIA, ws, wds)
    expected = wds @ INERTIA.T + np.cross(ws, ws @ INERTIA.T)
    scale = 2.5 * (np.sum(ws**2, axis=1) + np.linalg.norm(wds, axis=1))[:, None]  # |I| ≤ 2.5
    assert np.all(np.abs(dS - expected) <= 32 * EPS * scale)
    H = jax.jit(jax.hessian(rigid_body_acceleration_energy, argnums=2))(INERTIA, ws[0], wds[0])
    np.testing.assert_allclose(H, INERTIA, rtol=0, atol=8 * EPS)


def test_torque_free_body_conserves_energy_and_angular_momentum():
    """Quaternion kinematics with Euler's equations from Appell's (∂S/∂ω̇ = 0: no torque), integrated by
    diffrax for 20 s (about 3 turns) of a body with products of inertia. The controller keeps each
    accepted step's error estimate below rtol relative to the state (O(1) here); the energy
    T = ½ ωᵀIω and the space angular momentum L = R(e) I ω are constant along the exact flow and
    smooth functions of the state with O(1) gradients (relative to T and |L|), so each step's error
    moves them by about rtol and the drift is at most (accepted steps) × rtol, the tolerance; |e|
    likewise. Checked at the step ends: the dense output between them is not error-controlled."""
    rtol = 1e-10

    def omega_dot(w):
        # S is quadratic in ω̇ with Hessian I: ∂S/∂ω̇ = I ω̇ + ∂S/∂ω̇|₀ = 0 gives ω̇
        torque_free = jax.grad(rigid_body_acceleration_energy, argnums=2)(INERTIA, w, jnp.zeros(3))
        return -jnp.linalg.solve(INERTIA, torque_free)

    def field(t, y, args):
        e, w = y
        return quaternion_rate(e, w), omega_dot(w)

    e0 = quaternion_from_axis_angle(np.array([0.0, 0.6, 0.8]), 0.4)
    # 2% off the intermediate principal axis (|ω| = 1 rad/s): the body flips over once in the 20 s (the
    # tennis-racket effect), a demanding motion for the integrator
    w0 = np.array([-0.3, 0.85, 0.45])
    sol = jax.jit(
        lambda y0: diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            diffrax.Tsit5(),
            0.0,
            20.0,
            0.05,
            y0,
            saveat=diffrax.SaveAt(steps=True),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            max_steps=1000,
        )
    )((e0, w0))
    steps = int(sol.stats["num_accepted_steps"])
    es, ws = (np.asarray(y)[:steps] for y in sol.ys)  # (the rows past the last step are padding)
    assert float(sol.ts[steps - 1]) == 20.0
    T = 0.5 * np.einsum("ni,ij,nj->n", ws, INERTIA, ws)
    L = np.einsum("nij,jk,nk->ni", jax.jit(jax.vmap(rotation_from_quaternion))(es), INERTIA, ws)
    L0 = INERTIA @ w0 @ np.asarray(rotation_from_quaternion(e0)).T
    tol = steps * rtol
    assert np.max(np.abs(T / (0.5 * w0 @ INERTIA @ w0) - 1)) <= tol
    assert np.max(np.linalg.norm(L - L0, axis=1)) <= tol * np.linalg.norm(L0)
    assert np.max(np.abs(np.linalg.norm(es, axis=1) - 1)) <= tol
    # it did flip: ω in body axes reversed along the intermediate axis
    assert np.min(ws @ w0) < -0.5 * (w0 @ w0)


def test_jit_vmap_and_grad():
    """jit and vmap reproduce single calls (same operations, at most reassociated by XLA: 8 EPS of O(1)
    values). grad of Σ W∘R(e) against central differences: with step h the error is
    ≈ h²|f'''|/6 + EPS|f|/h, smallest at h = EPS^(1/3), about EPS^(2/3) (|f'''|/6 + |f|); |f| and |f'''|
    are ≲ 30 for these W (entries ~1) and |e| = 1: tolerance 100 EPS^(2/3) ≈ 4e-9."""
    es = random_quaternions(6)
    ws = rng(5).standard_normal((6, 3))
    fns = {
        "R": (rotation_from_quaternion, (es,)),
        "e(R)": (quaternion_from_rotation, (np.asarray(jax.vmap(rotation_from_quaternion)(es)),)),
        "rate": (quaternion_rate, (es, ws)),
        "omega": (angular_velocity_from_quaternion, (es, 0.3 * es[::-1])),
        "axis-angle": (quaternion_from_axis_angle, (ws / np.linalg.norm(ws, axis=1, keepdims=True), es[:, 0])),
        "product": (quat_multiply, (es, es[::-1])),
        "S": (lambda w, wd: rigid_body_acceleration_energy(INERTIA, w, wd), (ws, ws[::-1])),
    }
    batched = jax.jit(lambda: {name: jax.vmap(f)(*args) for name, (f, args) in fns.items()})()
    for name, (f, args) in fns.items():
        single = np.stack([f(*(a[i] for a in args)) for i in (0, 3)])  # eagerly, one at a time
        np.testing.assert_allclose(batched[name][np.array([0, 3])], single, rtol=0, atol=8 * EPS, err_msg=name)

    W = rng(6).standard_normal((3, 3))
    f = lambda e: jnp.sum(W * rotation_from_quaternion(e))
    h = EPS ** (1 / 3)

    def check(e):
        g = jax.grad(f)(e)
        fd = jnp.stack([(f(e + h * d) - f(e - h * d)) / (2 * h) for d in np.eye(4)])
        return jnp.max(jnp.abs(g - fd)), jnp.abs(g @ e) / jnp.sum(jnp.abs(g))

    fd_error, along_e = jax.jit(jax.vmap(check))(es)
    assert float(np.max(fd_error)) <= 100 * EPS ** (2 / 3)
    # R does not change along e (R(c e) = R(e)): g·e = 0 up to a few roundings of each |g_i e_i| ≤ |g_i|
    assert float(np.max(along_e)) <= 32 * EPS


def test_float32_smoke():
    """float32 in, float32 out (under jit and eagerly), with the float64 checks' factors at float32's EPS."""
    eps = float(np.finfo(np.float32).eps)
    e = np.array([0.3, -0.5, 0.2, 0.7], np.float32)
    w = np.array([0.4, -1.0, 2.0], np.float32)

    def all_of_them(e, w):
        R = rotation_from_quaternion(e)
        ed = quaternion_rate(e, w, frame="space")
        return {
            "R": R,
            "e(R)": quaternion_from_rotation(R),
            "rate": ed,
            "omega": angular_velocity_from_quaternion(e, ed, frame="space"),
            "product": quat_multiply(e, e),
            "axis-angle": quaternion_from_axis_angle(w, np.float32(0.3)),
            "S": rigid_body_acceleration_energy(INERTIA.astype(np.float32), w, w),
            "grad": jax.grad(lambda e_: rotation_from_quaternion(e_)[0, 1])(e),
        }

    outs = jax.jit(all_of_them)(e, w)
    assert all(o.dtype == np.float32 for o in outs.values()), {k: o.dtype for k, o in outs.items()}
    assert rotation_from_quaternion(e).dtype == np.float32
    R = np.asarray(outs["R"], np.float64)
    np.testing.assert_allclose(R @ R.T, np.eye(3), rtol=0, atol=64 * eps)
    np.testing.assert_allclose(outs["e(R)"], e / np.linalg.norm(e), rtol=0, atol=32 * eps)
    np.testing.assert_allclose(outs["omega"], w, rtol=0, atol=32 * eps * float(np.linalg.norm(w)))
