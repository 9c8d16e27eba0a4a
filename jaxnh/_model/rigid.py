"""Rigid-body kinematics: energies of a set of bodies, and wheels rolling on a plane.

A wheeled mechanism is described by where its bodies are: for each body the
position of its mass centre `r(q, t, p)` (m, inertial frame) and its
orientation `R(q, t, p)` (3×3 rotation matrix, body axes → inertial axes).
Everything else follows by automatic differentiation along the motion:

* velocities `ṙ = (∂r/∂q) q̇ + ∂r/∂t` and the body angular velocity
  `Ω = vee(Rᵀ Ṙ)` (body axes, rad/s);
* the kinetic energy `T = Σ ½ m |ṙ|² + ½ Ωᵀ I Ω` (J);
* the Gibbs–Appell acceleration energy, without the terms free of
  accelerations, `S = Σ ½ m |r̈|² + ½ Ω̇ᵀ I Ω̇ + Ω̇ · (Ω × I Ω)` (J/s²);
* the potential of uniform gravity `V = −Σ m g · r` (J).

`Wheel` describes a thin rigid disc touching a plane: the height of its
lowest rim point above the plane (a holonomic constraint when the wheel
must stay on the plane) and the velocity of the wheel's material point at
the contact (zero tangentially when it rolls without slipping: two
nonholonomic constraints).

Orientations may also be carried as unit quaternions e = (w, x, y, z)
(scalar first, Hamilton product, the same body → inertial convention as R):
`quat_multiply`, `rotation_from_quaternion` (exactly orthogonal for any
nonzero e), `quaternion_from_rotation` (Shepperd's method, w ≥ 0),
`quaternion_from_axis_angle`, the kinematics `quaternion_rate` (ė from ω in
body or space axes) and its inverse `angular_velocity_from_quaternion`; and
`rigid_body_acceleration_energy`, one body's rotational S from ω and ω̇ in
body axes (∂S/∂ω̇ is the left side of Euler's equations).

Inertia tensors are about the mass centre, in body axes, kg·m².
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxnh._base.linalg import mm
from jaxnh._base.types import ArrayInput


__all__ = [
    "RigidBodies",
    "Wheel",
    "rot_x",
    "rot_y",
    "rot_z",
    "rot_axis",
    "skew",
    "vee",
    "time_derivative",
    "angular_velocity",
    "quat_multiply",
    "rotation_from_quaternion",
    "quaternion_from_rotation",
    "quaternion_from_axis_angle",
    "quaternion_rate",
    "angular_velocity_from_quaternion",
    "rigid_body_acceleration_energy",
]


# --- rotations ----------------------------------------------------------------


def rot_x(a: ArrayLike) -> jax.Array:
    """Rotation by angle `a` (rad) about the x axis, a 3×3 matrix."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, c, -s]), jnp.stack([z, s, c])])


def rot_y(a: ArrayLike) -> jax.Array:
    """Rotation by angle `a` (rad) about the y axis, a 3×3 matrix."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, z, s]), jnp.stack([z, o, z]), jnp.stack([-s, z, c])])


def rot_z(a: ArrayLike) -> jax.Array:
    """Rotation by angle `a` (rad) about the z axis, a 3×3 matrix."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def skew(w: jax.Array | np.ndarray) -> jax.Array:
    """The cross-product matrix `[w]×` with `[w]× x = w × x`."""
    z = jnp.zeros_like(w[0])
    return jnp.stack(
        [
            jnp.stack([z, -w[2], w[1]]),
            jnp.stack([w[2], z, -w[0]]),
            jnp.stack([-w[1], w[0], z]),
        ]
    )


def vee(W: jax.Array | np.ndarray) -> jax.Array:
    """The vector `w` of a (nearly) skew-symmetric matrix `W = [w]×` (its skew part)."""
    return 0.5 * jnp.stack([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def rot_axis(axis: ArrayInput, a: ArrayLike) -> jax.Array:
    """Rotation by angle `a` (rad) about the unit vector `axis` (Rodrigues' formula)."""
    axis = jnp.asarray(axis, dtype=jnp.result_type(a, float))
    K = skew(axis)
    return jnp.eye(3, dtype=K.dtype) + jnp.sin(a) * K + (1 - jnp.cos(a)) * mm(K, K)


# --- differentiation along the motion ----------------------------------------------


def time_derivative(f: Callable[..., Any], q: ArrayLike, qd: ArrayLike, t: ArrayLike) -> tuple[Any, Any]:
    """`f(q, t)` and its rate `(∂f/∂q) q̇ + ∂f/∂t` along the motion (any pytree output)."""
    t = jnp.asarray(t, dtype=jnp.result_type(q))
    return jax.jvp(f, (q, t), (qd, jnp.ones_like(t)))


def angular_velocity(R: jax.Array | np.ndarray, Rdot: jax.Array | np.ndarray, frame: str = "body") -> jax.Array:
    """Angular velocity from an orientation R and its rate Ṙ, rad/s.

    `frame="body"`: components in body axes, `vee(Rᵀ Ṙ)`; `frame="space"`:
    inertial components, `vee(Ṙ Rᵀ)`.
    """
    if frame == "body":
        return vee(mm(R.T, Rdot))
    if frame == "space":
        return vee(mm(Rdot, R.T))
    raise ValueError(f"frame must be 'body' or 'space'; got {frame!r}")


# --- unit quaternions -----------------------------------------------------------------
#
# A quaternion is e = (w, x, y, z), scalar first; products are Hamilton's (i² = j² = k² = ijk = −1).
# The unit quaternion e describes the same rotation as R = rotation_from_quaternion(e), body axes →
# inertial axes: a body-axes vector v has inertial components vec(e ⊗ (0, v) ⊗ e*). Each function
# takes one quaternion (4,) (one 3-vector, one 3×3 matrix); `jax.vmap` maps it over a batch.


def _as_float(x: ArrayInput, shape: tuple[int, ...], name: str) -> jax.Array:
    """`x` as a floating array of the given shape (integers promoted to the default float)."""
    x = jnp.asarray(x)
    x = x.astype(jnp.result_type(x.dtype, float))
    if x.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got shape {x.shape}")
    return x


def _check_frame(frame: str, name: str) -> None:
    if frame not in ("body", "space"):
        raise ValueError(f"{name}: frame must be 'body' or 'space'; got {frame!r}")


def _conjugate(e: jax.Array) -> jax.Array:
    return e * jnp.array([1, -1, -1, -1], dtype=e.dtype)


def _pure(v: jax.Array) -> jax.Array:
    """The pure quaternion (0, v) of a 3-vector."""
    return jnp.concatenate([jnp.zeros((1,), dtype=v.dtype), v])


def quat_multiply(a: ArrayInput, b: ArrayInput) -> jax.Array:
    """The Hamilton product `a ⊗ b` of two quaternions (4,), scalar first.

    `a ⊗ b = (a_w b_w − a_v·b_v, a_w b_v + b_w a_v + a_v × b_v)` with `a_v`, `b_v` the vector
    parts. For unit quaternions it composes rotations as matrices do:
    `R(a ⊗ b) = R(a) R(b)` (first b, then a). Not commutative; |a ⊗ b| = |a| |b|. The result has
    the units of a times those of b (dimensionless for orientations).
    """
    a, b = _as_float(a, (4,), "quat_multiply a"), _as_float(b, (4,), "quat_multiply b")
    aw, av, bw, bv = a[0], a[1:], b[0], b[1:]
    w = aw * bw - jnp.sum(av * bv)
    v = aw * bv + bw * av + jnp.cross(av, bv)
    return jnp.concatenate([w[None], v])


def rotation_from_quaternion(e: ArrayInput) -> jax.Array:
    """The rotation matrix R (3, 3) of the orientation quaternion e = (w, x, y, z), body → inertial axes.

    R is the homogeneous (quadratic) form divided by |e|²:

        R = [[w²+x²−y²−z²,  2(xy − wz),   2(xz + wy) ],
             [2(xy + wz),   w²−x²+y²−z²,  2(yz − wx) ],
             [2(xz − wy),   2(yz + wx),   w²−x²−y²+z²]] / |e|²,

    so R is orthogonal with determinant 1 (to rounding) for any nonzero e, not only for |e| = 1:
    e and c·e (c ≠ 0) give the same R. An integrator that carries e, whose norm is 1 only to
    rounding or to its tolerance, thus always gets a proper rotation, and the derivative of R along
    e itself is zero. e = 0 is no rotation and gives NaN. e and −e give the same R.
    A rotation by angle a about the unit axis n is e = (cos(a/2), sin(a/2) n)
    (`quaternion_from_axis_angle`), and `R` then equals `rot_axis(n, a)`.
    """
    e = _as_float(e, (4,), "rotation_from_quaternion e")
    w, x, y, z = e[0], e[1], e[2], e[3]
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R = jnp.stack(
        [
            jnp.stack([ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)]),
            jnp.stack([2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)]),
            jnp.stack([2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz]),
        ]
    )
    return R / (ww + xx + yy + zz)


def quaternion_from_rotation(R: ArrayInput) -> jax.Array:
    """The unit quaternion e = (w, x, y, z) (4,) of a rotation matrix R (3, 3), body → inertial axes; w ≥ 0.

    The inverse of `rotation_from_quaternion` on unit quaternions with w ≥ 0 (e and −e are the same
    rotation; this returns the one with w ≥ 0). Shepperd's method: the symmetric 4×4 matrix

        K = [[1 + t,     R₂₁ − R₁₂,       R₀₂ − R₂₀,       R₁₀ − R₀₁     ],
             [R₂₁ − R₁₂, 1 + 2R₀₀ − t,    R₀₁ + R₁₀,       R₀₂ + R₂₀     ],
             [R₀₂ − R₂₀, R₀₁ + R₁₀,       1 + 2R₁₁ − t,    R₁₂ + R₂₁     ],
             [R₁₀ − R₀₁, R₀₂ + R₂₀,       R₁₂ + R₂₁,       1 + 2R₂₂ − t  ]],   t = trace R,

    equals 4 e eᵀ for a rotation, so each column is e times 4 e_k. The column with the largest
    diagonal entry 4 e_k² (at least 1, since the diagonal sums to 4) is used, normalised: no
    square root of a small or negative number and no division by a small one, near a half turn
    (w ≈ 0) as near the identity. The result has unit norm; for a matrix that is orthogonal only to
    rounding it differs from the exact rotation's quaternion by a few rounding errors.

    Differentiable (`jax.grad`, `jax.jvp`): the derivative is that of the chosen column,
    normalised. Along rotations (R → R exp([δ]×)) every column gives the same e and the same
    derivative, so the choice of column, a piecewise constant, changes neither; off the rotations
    (a perturbation that makes R non-orthogonal) the derivatives of different columns differ. The
    result is discontinuous only at half turns, where w passes through 0 and e jumps to −e (exactly
    at w = 0 the component of e largest in magnitude is positive).
    """
    R = _as_float(R, (3, 3), "quaternion_from_rotation R")
    t = R[0, 0] + R[1, 1] + R[2, 2]
    s0, s1, s2 = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]  # 4w·(x, y, z)
    p01, p02, p12 = R[0, 1] + R[1, 0], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1]  # 4xy, 4xz, 4yz
    K = jnp.stack(
        [
            jnp.stack([1 + t, s0, s1, s2]),
            jnp.stack([s0, 1 + 2 * R[0, 0] - t, p01, p02]),
            jnp.stack([s1, p01, 1 + 2 * R[1, 1] - t, p12]),
            jnp.stack([s2, p02, p12, 1 + 2 * R[2, 2] - t]),
        ]
    )
    k = jnp.argmax(jnp.diagonal(K))
    column = K[:, k]
    e = column / jnp.sqrt(jnp.sum(column * column))
    return jnp.where(e[0] < 0, -e, e)


def quaternion_from_axis_angle(axis: ArrayInput, angle: ArrayLike) -> jax.Array:
    """The unit quaternion (4,) of a rotation by `angle` (rad) about `axis`: (cos(a/2), sin(a/2) axis).

    `axis` (3,) is a unit vector in the axes the rotation is expressed in; it is not normalised
    here (as in `rot_axis`, whose matrix this quaternion's `rotation_from_quaternion` equals).
    Right-handed: a positive angle turns counter-clockwise seen from the tip of `axis`. Angles a
    and a + 2π give −e and e, the same rotation; w ≥ 0 only for |a| ≤ π.
    """
    angle = jnp.asarray(angle)
    axis = jnp.asarray(axis)
    dtype = jnp.result_type(axis, angle, float)
    axis = _as_float(axis.astype(dtype), (3,), "quaternion_from_axis_angle axis")
    half = 0.5 * angle.astype(dtype)
    if half.shape != ():
        raise ValueError(f"quaternion_from_axis_angle angle: expected a scalar, got shape {half.shape}")
    return jnp.concatenate([jnp.cos(half)[None], jnp.sin(half) * axis])


def quaternion_rate(e: ArrayInput, omega: ArrayInput, frame: str = "body") -> jax.Array:
    """The rate ė (4,), 1/s, of the orientation quaternion e (4,) turning at angular velocity ω (3,), rad/s.

    `frame="body"`: ω in body axes, `ė = ½ e ⊗ (0, ω)`; `frame="space"`: ω in inertial axes,
    `ė = ½ (0, ω) ⊗ e`. Then `d/dt rotation_from_quaternion(e) = R [ω]×` (body) or `[ω]× R`
    (space). The rate is orthogonal to e (`e·ė = 0`), so |e| is constant along the exact motion;
    a numerical integrator lets it drift by its error, which `rotation_from_quaternion` ignores.
    For a non-unit e the rate is |e| times that of e/|e|. Inverse:
    `angular_velocity_from_quaternion`.
    """
    _check_frame(frame, "quaternion_rate")
    e = _as_float(e, (4,), "quaternion_rate e")
    w = _pure(_as_float(omega, (3,), "quaternion_rate omega"))
    return 0.5 * (quat_multiply(e, w) if frame == "body" else quat_multiply(w, e))


def angular_velocity_from_quaternion(e: ArrayInput, edot: ArrayInput, frame: str = "body") -> jax.Array:
    """The angular velocity ω (3,), rad/s, of an orientation quaternion e (4,) changing at ė (4,), 1/s.

    `frame="body"`: body axes, `ω = 2 vec(e* ⊗ ė) / |e|²`; `frame="space"`: inertial axes,
    `ω = 2 vec(ė ⊗ e*) / |e|²` (e* the conjugate, vec the vector part). The inverse of
    `quaternion_rate` for any nonzero e, and the angular velocity of
    `rotation_from_quaternion(e)`: a component of ė along e (a change of |e|, which does not turn
    R) lands in the scalar part `e·ė` and is ignored. Compare `angular_velocity(R, Ṙ)`.
    """
    _check_frame(frame, "angular_velocity_from_quaternion")
    e = _as_float(e, (4,), "angular_velocity_from_quaternion e")
    edot = _as_float(edot, (4,), "angular_velocity_from_quaternion edot")
    ec = _conjugate(e)
    p = quat_multiply(ec, edot) if frame == "body" else quat_multiply(edot, ec)
    return 2 * p[1:] / jnp.sum(e * e)


def rigid_body_acceleration_energy(inertia: ArrayInput, omega: ArrayInput, omega_dot: ArrayInput) -> jax.Array:
    """The Gibbs–Appell acceleration energy of a rigid body's rotation, J/s² (scalar).

    `S = ½ ω̇ · I ω̇ + ω̇ · (ω × I ω)`, with `inertia` I (3, 3) the inertia tensor about the mass
    centre in body axes (kg·m²), `omega` ω (3,) the angular velocity in body axes (rad/s) and
    `omega_dot` ω̇ (3,) its rate (rad/s², the derivative of the body-axes components). The terms
    of the full `½ ∫ |a|² dm` that are free of ω̇ are left out (they do not enter Appell's
    equations). `∂S/∂ω̇ = I ω̇ + ω × I ω` is the left side of Euler's equations, equal to the
    torque about the mass centre in body axes, N·m. The translation's `½ m |r̈|²` is separate
    (`RigidBodies.acceleration_energy` sums both over its bodies).
    """
    I = _as_float(inertia, (3, 3), "rigid_body_acceleration_energy inertia")
    w = _as_float(omega, (3,), "rigid_body_acceleration_energy omega")
    dw = _as_float(omega_dot, (3,), "rigid_body_acceleration_energy omega_dot")
    return 0.5 * mm(dw, mm(I, dw)) + mm(dw, jnp.cross(w, mm(I, w)))


def _as_vec3(x, name):
    x = jnp.asarray(x)
    if x.shape != (3,):
        raise ValueError(f"{name}: expected a position vector of shape (3,), got shape {x.shape}")
    return x


def _as_mat3(x, name):
    x = jnp.asarray(x)
    if x.shape != (3, 3):
        raise ValueError(f"{name}: expected a 3×3 matrix, got shape {x.shape}")
    return x


# --- a set of rigid bodies ----------------------------------------------------------


class RigidBodies(eqx.Module):
    """Rigid bodies whose poses are functions of the generalized coordinates.

    Arguments:
        poses: `poses(q, t, params) -> [(r, R), ...]`, one pair per body: `r`
            the position of the body's mass centre (3,), m, and `R` its
            orientation (3, 3), the rotation from body axes to inertial axes.
            Writing all poses in one function lets bodies share frames (a
            bicycle's rear frame carries the fork, which carries the front
            wheel).
        inertias: `inertias(params) -> [(m, I), ...]` in the same order: mass
            m (kg) and central inertia tensor I (3, 3) in body axes (kg·m²).
        gravity: optional `gravity(params) -> (3,)`, the gravitational
            acceleration vector in inertial axes, m/s² (e.g. (0, 0, −9.81)
            with z up); gives `potential`.
        names: optional body names (for messages and users).

    The methods `kinetic`, `acceleration_energy` and `potential` have the
    signatures `jaxnh.Mechanism` expects, so a mechanism is
    `Mechanism(bodies.kinetic, potential=bodies.potential,
    acceleration_energy=bodies.acceleration_energy, constraints=...)`.
    """

    poses: Callable = eqx.field(static=True)
    inertias: Callable = eqx.field(static=True)
    gravity: Optional[Callable] = eqx.field(static=True, default=None)
    names: Optional[tuple] = eqx.field(static=True, default=None)

    def _poses(self, q, t, p):
        out = self.poses(q, t, p)
        checked = []
        for k, pose in enumerate(out):
            label = f"RigidBodies `poses` body {self.names[k] if self.names else k}"
            if len(pose) != 2:
                raise ValueError(f"{label}: expected a pair (r, R), got {len(pose)} items")
            checked.append((_as_vec3(pose[0], label + " position r"), _as_mat3(pose[1], label + " orientation R")))
        return checked

    def _inertias(self, p, n):
        out = list(self.inertias(p))
        if len(out) != n:
            raise ValueError(f"RigidBodies `inertias` returned {len(out)} (m, I) pairs for {n} bodies")
        return [
            (jnp.asarray(m), _as_mat3(I, f"RigidBodies `inertias` body {k} inertia I")) for k, (m, I) in enumerate(out)
        ]

    def velocities(self, q: ArrayLike, qd: ArrayLike, t: ArrayLike, p: Any) -> list[tuple[jax.Array, jax.Array]]:
        """Per body: mass-centre velocity ṙ (3,), m/s, and body angular velocity Ω (3,), rad/s."""

        def rates(q_, t_):
            return self._poses(q_, t_, p)

        poses, dposes = time_derivative(rates, q, qd, t)
        return [(dr, angular_velocity(R, dR)) for (r, R), (dr, dR) in zip(poses, dposes)]

    def kinetic(self, q: ArrayLike, qd: ArrayLike, t: ArrayLike, p: Any) -> jax.Array | float:
        """Kinetic energy `T = Σ ½ m |ṙ|² + ½ Ωᵀ I Ω`, J."""
        vel = self.velocities(q, qd, t, p)
        T = 0.0
        for (v, w), (m, I) in zip(vel, self._inertias(p, len(vel))):
            T = T + 0.5 * m * mm(v, v) + 0.5 * mm(w, mm(I, w))
        return T

    def accelerations(
        self, q: ArrayLike, qd: ArrayLike, qdd: ArrayLike, t: ArrayLike, p: Any
    ) -> list[tuple[jax.Array, jax.Array, jax.Array, jax.Array]]:
        """Per body: (ṙ, Ω, r̈, Ω̇) — velocities and their rates along the motion."""
        t = jnp.asarray(t, dtype=jnp.result_type(q))

        def vel(q_, qd_, t_):
            return self.velocities(q_, qd_, t_, p)

        v, a = jax.jvp(vel, (q, qd, t), (qd, qdd, jnp.ones_like(t)))
        return [(v_, w_, a_, dw_) for (v_, w_), (a_, dw_) in zip(v, a)]

    def acceleration_energy(
        self, q: ArrayLike, qd: ArrayLike, qdd: ArrayLike, t: ArrayLike, p: Any
    ) -> jax.Array | float:
        """Acceleration energy `S = Σ ½ m |r̈|² + ½ Ω̇ᵀ I Ω̇ + Ω̇ · (Ω × I Ω)`, J/s².

        Terms free of accelerations are left out (they do not enter Appell's
        equations); S is quadratic in q̈, as `jaxnh.Mechanism` requires.
        """
        acc = self.accelerations(q, qd, qdd, t, p)
        S = 0.0
        for (_, w, a, dw), (m, I) in zip(acc, self._inertias(p, len(acc))):
            S = S + 0.5 * m * mm(a, a) + rigid_body_acceleration_energy(I, w, dw)
        return S

    def potential(self, q: ArrayLike, t: ArrayLike, p: Any) -> jax.Array | float:
        """Gravitational potential `V = −Σ m g · r`, J (needs `gravity`)."""
        if self.gravity is None:
            raise ValueError("RigidBodies.potential: no `gravity` was given")
        g = _as_vec3(self.gravity(p), "RigidBodies `gravity`")
        poses = self._poses(q, t, p)
        V = 0.0
        for (r, _), (m, _) in zip(poses, self._inertias(p, len(poses))):
            V = V - m * mm(g, r)
        return V


# --- a wheel rolling on a plane -----------------------------------------------------


def _tangent_basis(normal):
    """n and two orthonormal tangents: Gram–Schmidt of e_x, e_y (e_z) against n.

    For a level plane (n = ±e_z) the tangents are e_x and e_y.
    """
    n = np.asarray(normal, dtype=float)
    if n.shape != (3,) or not np.isclose(np.linalg.norm(n), 1.0):
        raise ValueError(f"Wheel: `normal` must be a unit vector of 3 components; got {normal!r}")
    basis = [n]
    for e in np.eye(3):
        u = e - sum(np.dot(e, b) * b for b in basis)
        if np.linalg.norm(u) > 1e-6:
            basis.append(u / np.linalg.norm(u))
        if len(basis) == 3:
            break
    return basis[0], basis[1], basis[2]


class Wheel(eqx.Module):
    """A thin rigid disc of radius ρ touching the plane `normal · x = 0`.

    Arguments:
        pose: `pose(q, t, params) -> (c, R)`: the wheel centre c (3,), m, and
            the wheel's orientation R (3, 3) (body → inertial axes).
        radius: `radius(params)`, m.
        axle: which body axis (0, 1 or 2) is the wheel's axle.
        normal: unit normal of the ground plane, pointing from the ground
            towards the wheel ("up"): (0, 0, 1) with z up, (0, 0, −1) in the
            z-down axes of vehicle dynamics.

    The contact point is the rim point lowest along `normal`:
    `P = c − ρ u`, with `u` the unit vector in the wheel plane closest to
    `normal` (`u ∝ n − (n·a) a`, a the axle). `height` is `n · P` (zero when
    the wheel touches the ground: a holonomic constraint); `slip` is the
    tangential velocity of the wheel's material point at P (zero when it
    rolls without slipping: two nonholonomic constraints, linear in the
    velocities). The multipliers of the `slip` constraints are the
    tangential contact-force components along `tangents`, N.
    """

    pose: Callable = eqx.field(static=True)
    radius: Callable = eqx.field(static=True)
    axle: int = eqx.field(static=True, default=1)
    normal: tuple = eqx.field(static=True, default=(0.0, 0.0, 1.0))

    def __check_init__(self):
        if self.axle not in (0, 1, 2):
            raise ValueError(f"Wheel: `axle` must be 0, 1 or 2 (a body axis); got {self.axle!r}")
        _tangent_basis(self.normal)

    @property
    def tangents(self) -> np.ndarray:
        """Two orthonormal directions in the ground plane (a NumPy (2, 3) array):
        e_x and e_y projected on the plane and orthonormalised (e_x, e_y for a level plane)."""
        _, t1, t2 = _tangent_basis(self.normal)
        return np.stack([t1, t2])

    def _geometry(self, c, R, p):
        n = jnp.asarray(self.normal, dtype=c.dtype)
        a = R[:, self.axle]
        u = n - mm(n, a) * a
        u = u / jnp.sqrt(mm(u, u))
        return c - self.radius(p) * u

    def contact_point(self, q: ArrayLike, t: ArrayLike, p: Any) -> jax.Array:
        """The contact point P (3,), m: the rim point lowest along the normal."""
        c, R = self.pose(q, t, p)
        return self._geometry(_as_vec3(c, "Wheel `pose` centre"), _as_mat3(R, "Wheel `pose` orientation"), p)

    def height(self, q: ArrayLike, t: ArrayLike, p: Any) -> jax.Array:
        """Height of the lowest rim point above the plane, m (scalar; 0 on the ground)."""
        n = jnp.asarray(self.normal)
        return mm(n, self.contact_point(q, t, p))

    def contact_velocity(self, q: ArrayLike, qd: ArrayLike, t: ArrayLike, p: Any) -> jax.Array:
        """Velocity of the wheel's material point at the contact, m/s (3,)."""
        (c, R), (dc, dR) = time_derivative(lambda q_, t_: self.pose(q_, t_, p), q, qd, t)
        P = self._geometry(c, R, p)
        w = angular_velocity(R, dR, frame="space")
        return dc + jnp.cross(w, P - c)

    def slip(self, q: ArrayLike, qd: ArrayLike, t: ArrayLike, p: Any) -> jax.Array:
        """Tangential slip velocity at the contact along `tangents`, m/s (2,)."""
        v = self.contact_velocity(q, qd, t, p)
        return mm(jnp.asarray(self.tangents, dtype=v.dtype), v)
