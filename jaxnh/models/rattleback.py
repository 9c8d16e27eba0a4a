"""The rattleback: a rigid body with an ellipsoidal bottom rolling on a plane, in a unit quaternion.

A rigid body of mass m whose bottom is part of the ellipsoid x²/A² + y²/B² + z²/C² = 1
(semi-axes A, B, C along its *curvature axes*, centre O) rolls without slipping on a fixed
horizontal plane under gravity g. The geometry is exact: the contact point is the ellipsoid's
support point for the downward normal, computed in closed form at every orientation, not a
truncated (paraboloid) expansion about the rest point. At rest the body stands on the lowest
point of the ellipsoid, where the principal radii of curvature are A²/C and B²/C; its mass
centre G lies on the ellipsoid's vertical axis, at height h above that point (0 < h < C, and
h < B²/C for the rest to be stable). The principal axes of inertia (moments I1, I2, I3) are the
curvature axes turned by the angle δ about the vertical axis; δ ≠ 0 couples the spin with the
rocking and makes the spin reverse (Walker 1896; Bondi 1986).

Body axes: the principal axes of inertia, origin G, z up at rest. In them the ellipsoid is
(r − o)ᵀ M (r − o) = 1 with o = (C − h) ẑ and M = Rz(δ)ᵀ diag(A⁻², B⁻², C⁻²) Rz(δ); the point
with outward normal n is o + E n / √(nᵀ E n), E = M⁻¹. With γ = Rᵀ ẑ the upward vertical in
body axes, the contact point is

    ρ(γ) = o − E γ / √(γᵀ E γ)       (G → contact, body axes, m),

and G's height above the plane is ζ = −γ·ρ = √(γᵀ E γ) − (C − h) γ·ẑ, a function of the
orientation alone (the holonomic contact condition is solved exactly: the height is not a
coordinate).

Coordinates `q = (x, y, e0, e1, e2, e3)`: G's horizontal position (m) and the orientation as a
unit quaternion e (body → space, `R = rotation_from_quaternion(e)`). Speeds
`u = (ẋ, ẏ, Ω1, Ω2, Ω3)`: G's horizontal velocity (m/s) and the angular velocity in body
(principal) axes (rad/s), with ė = ½ e ⊗ (0, Ω) (`quaternion_rate(..., frame="body")`).

Energy: with ż = dζ/dt = −ẑ·(R (Ω × ρ)) (the contact point moves along the surface, normal to
ẑ, so only the turning about it moves G up or down),

    T = ½ m (ẋ² + ẏ² + ż²) + ½ (I1 Ω1² + I2 Ω2² + I3 Ω3²),        V = m g ζ(e).

Rolling: the velocity of the body's material point at the contact, v_G + R (Ω × ρ), is zero.
Its vertical component vanishes identically (by the rate ż above), so the constraints are its
two horizontal components, in the speeds (m/s; their multipliers are the horizontal contact
forces, N). Rolling is lossless: E = T + V is constant (`energy`).

Spin reversal: with δ ≠ 0 a steady spin about the vertical is unstable in at least one sense
of rotation; rocking grows, takes the spin's energy and turns it back with the other sign.
Without dissipation the motion then continues, with further reversals (Garcia & Hubbard 1988;
Kondo & Nakanishi 2017). `spin` gives ωz, the vertical component of the angular velocity.

Default parameters (`default_params`): the rattleback of Kane & Levinson (1982), as reproduced
by later simulations (e.g. the PyDy rattleback example): semi-axes 20, 3, 2 cm, OG = 1 cm (so
h = C − OG = 1 cm), m = 1 kg, and in the curvature axes the inertia per unit mass
(A, B, C, D) = (2, 16, 17, −0.2) cm², D the product-of-inertia entry of the matrix. Their body
z axis points down; turned into this module's z-up axes (a half turn about the long axis) the
entry becomes +0.2 cm², whose eigen-decomposition gives the principal moments and δ here.

References:
* G. T. Walker, "On a dynamical top", Q. J. Pure Appl. Math. 28 (1896) 175–184.
* T. R. Kane, D. A. Levinson, "Realistic mathematical modeling of the rattleback",
  Int. J. Non-Linear Mech. 17 (1982) 175–186.
* H. Bondi, "The rigid body dynamics of unidirectional spin", Proc. R. Soc. A 405 (1986) 265–274.
* A. Garcia, M. Hubbard, "Spin reversal of the rattleback: theory and experiment",
  Proc. R. Soc. A 418 (1988) 165–197.
* Y. Kondo, H. Nakanishi, "Rattleback dynamics and its reversal time of rotation",
  Phys. Rev. E 95 (2017) 062207.

Units: m, kg, kg·m², rad, s, J.

Example (the spin reverses)::

    import jax, jax.numpy as jnp
    import jaxnh as nh
    from jaxnh.models import rattleback

    p = rattleback.default_params()
    q0, u0 = rattleback.initial_state(p, spin=-3.0, tilt=0.01)
    ts = jnp.linspace(0.0, 10.0, 201)
    sol = nh.simulate(rattleback.mechanism(), p, q0, u0, ts, rtol=1e-9, atol=1e-12)
    wz = jax.vmap(rattleback.spin, (0, 0, None))(sol.q, sol.u, p)    # rad/s
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxnh._model.mechanism import Mechanism
from jaxnh._model.rigid import quaternion_from_axis_angle, quaternion_rate, rotation_from_quaternion


__all__ = [
    "mechanism",
    "default_params",
    "kinetic",
    "potential",
    "kinematics",
    "constraint",
    "contact_point",
    "height",
    "rolling_speeds",
    "initial_state",
    "energy",
    "spin",
    "kane_levinson_inertia",
]


def _rz(delta: jax.Array) -> jax.Array:
    c, s = jnp.cos(delta), jnp.sin(delta)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def _shape_matrix(p: dict[str, Any]) -> jax.Array:
    """E = Rz(δ)ᵀ diag(A², B², C²) Rz(δ) (3, 3), m²: the inverse of the ellipsoid's matrix, body axes."""
    Rz = _rz(p["delta"])
    return (Rz.T * p["axes"] ** 2) @ Rz


def contact_point(gamma: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """ρ (3,), m: the contact point relative to G in body axes, for the upward vertical γ (3,),
    unit, body axes): the ellipsoid's point whose outward normal is −γ, o − E γ / √(γᵀ E γ)."""
    gamma = jnp.asarray(gamma)
    E = _shape_matrix(p)
    Eg = E @ gamma
    o = jnp.zeros(3, dtype=Eg.dtype).at[2].set(p["axes"][2] - p["h"])
    return o - Eg / jnp.sqrt(gamma @ Eg)


def _vertical(e: jax.Array) -> jax.Array:
    """γ = Rᵀ ẑ (3,): the upward vertical in body axes."""
    return rotation_from_quaternion(e)[2]


def height(q: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """ζ, m: the height of the mass centre G above the plane, −γ·ρ(γ), for the body resting on
    the plane at the orientation q[2:]."""
    gamma = _vertical(q[2:])
    return -gamma @ contact_point(gamma, p)


def _height_rate(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """ż = −ẑ·(R (Ω × ρ)), m/s: the exact rate of `height` along ė = ½ e ⊗ (0, Ω) (the contact
    point slides along the surface, normal to ẑ, so only the body's turning about it moves G up)."""
    R = rotation_from_quaternion(q[2:])
    return -(R[2] @ jnp.cross(u[2:5], contact_point(R[2], p)))


def kinetic(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """T = ½ m (ẋ² + ẏ² + ż²) + ½ Σ Iᵢ Ωᵢ², J (in the speeds u; ż the rate of the height ζ(e))."""
    zdot = _height_rate(q, u, p)
    return 0.5 * p["m"] * (u[0] ** 2 + u[1] ** 2 + zdot**2) + 0.5 * jnp.sum(p["I"] * u[2:] ** 2)


def potential(q: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """V = m g ζ(e), J: gravity, the plane at zero height."""
    return p["m"] * p["g"] * height(q, t, p)


def kinematics(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """dq/dt from the speeds: (ẋ, ẏ) in m/s and ė = ½ e ⊗ (0, Ω) (Ω in body axes) in 1/s."""
    return jnp.concatenate([u[:2], quaternion_rate(q[2:], u[2:], frame="body")])


def constraint(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """Velocity of the body's material point at the contact, v_G + R (Ω × ρ), horizontal part
    (2,), m/s (its vertical part is zero identically, see the module note)."""
    R = rotation_from_quaternion(q[2:])
    # u[2:5], not u[2:]: Appell's step check evaluates ∂c/∂u at a zero vector of q's length (6)
    w_rho = R @ jnp.cross(u[2:5], contact_point(R[2], p))
    return u[:2] + w_rho[:2]


def mechanism() -> Mechanism:
    """The rattleback rolling on a fixed horizontal plane (see the module note)."""
    return Mechanism(
        kinetic,
        constraints=constraint,
        potential=potential,
        kinematics=kinematics,
        quaternions=((2, 3, 4, 5),),
        names=("x", "y", "e0", "e1", "e2", "e3"),
    )


def kane_levinson_inertia(A: ArrayLike, B: ArrayLike, D: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """Principal moments (I1, I2) and the angle δ (rad) of the horizontal inertia block
    [[A, D], [D, B]] (kg·m², curvature axes): [[A, D], [D, B]] = Rz(δ) diag(I1, I2) Rz(δ)ᵀ,
    with I1 the moment about the axis nearer the curvature x axis (|δ| < π/4 when A < B)."""
    A, B, D = jnp.asarray(A), jnp.asarray(B), jnp.asarray(D)
    mean, half = 0.5 * (A + B), jnp.sqrt(0.25 * (B - A) ** 2 + D**2)
    sign = jnp.where(A <= B, 1.0, -1.0)
    I1, I2 = mean - sign * half, mean + sign * half
    # A − B = (I1 − I2) cos 2δ and D = ½ (I1 − I2) sin 2δ
    delta = 0.5 * jnp.arctan2(2.0 * D / (I1 - I2), (A - B) / (I1 - I2))
    return jnp.stack([I1, I2]), delta


def default_params() -> dict[str, jax.Array]:
    """Kane & Levinson's (1982) rattleback (see the module note), SI units.

    m = 1 kg; semi-axes (A, B, C) = (0.20, 0.03, 0.02) m (radii of curvature at rest
    A²/C = 2 m and B²/C = 0.045 m); h = 0.01 m; g = 9.81 m/s²; inertia per unit mass in the
    curvature axes (2, 16, 17)·10⁻⁴ m² with the product entry +0.2·10⁻⁴ m² (z up), giving
    principal moments I ≈ (1.997, 16.003, 17)·10⁻⁴ kg·m² and δ ≈ −0.01428 rad (−0.82°)."""
    m = jnp.asarray(1.0)
    (I1, I2), delta = kane_levinson_inertia(2.0e-4, 16.0e-4, 0.2e-4)
    return {
        "m": m,
        "g": jnp.asarray(9.81),
        "axes": jnp.array([0.20, 0.03, 0.02]),
        "h": jnp.asarray(0.01),
        "I": m * jnp.stack([I1, I2, jnp.asarray(17.0e-4)]),
        "delta": delta,
    }


def rolling_speeds(p: dict[str, Any], q: ArrayLike, omega: ArrayLike) -> jax.Array:
    """The speeds u (5,) of the body at q (6,) turning at the body-axes angular velocity
    ω = `omega` (3,), rad/s: G's horizontal velocity, m/s, from the two rolling constraints."""
    q = jnp.asarray(q, dtype=jnp.result_type(float))
    omega = jnp.asarray(omega, dtype=q.dtype)
    u = jnp.concatenate([jnp.zeros(2, dtype=q.dtype), omega])
    return u.at[:2].set(-constraint(q, u, 0.0, p))


def initial_state(
    p: dict[str, Any],
    spin: float = -3.0,
    tilt: float = 0.0,
    tilt_axis: tuple[float, float] = (1.0, 1.0),
    omega_xy: tuple[float, float] = (0.0, 0.0),
    x: float = 0.0,
    y: float = 0.0,
) -> tuple[jax.Array, jax.Array]:
    """(q0, u0): G at (x, y), m; the body turned from rest (identity orientation: principal axes
    along the space axes, z up) by `tilt` (rad) about the horizontal axis `tilt_axis` (space
    axes, normalised); turning at the body-axes angular velocity (omega_xy, spin), rad/s;
    rolling (G's horizontal velocity from the constraints)."""
    dtype = jnp.result_type(float)
    axis = jnp.array([tilt_axis[0], tilt_axis[1], 0.0], dtype=dtype)
    e = quaternion_from_axis_angle(axis / jnp.linalg.norm(axis), jnp.asarray(tilt, dtype=dtype))
    q0 = jnp.concatenate([jnp.array([x, y], dtype=dtype), e])
    return q0, rolling_speeds(p, q0, jnp.array([omega_xy[0], omega_xy[1], spin], dtype=dtype))


def energy(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """E = T + V, J (rolling without slip does no work). Constant."""
    return kinetic(q, u, 0.0, p) + potential(q, 0.0, p)


def spin(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """ωz = γ·Ω, rad/s: the vertical (space z) component of the angular velocity."""
    return _vertical(q[2:]) @ u[2:]
