"""The Chaplygin sphere: a dynamically asymmetric ball rolling on a plane, in a unit quaternion.

A ball of mass m and radius a whose mass centre is at its geometric centre but whose principal
moments of inertia about the centre, I1, I2, I3 (body axes), differ, rolls without slipping on a
fixed horizontal plane under gravity. The centre stays at height a, so gravity does no work and
does not enter the equations (the normal force is m g; g is not a parameter).
Coordinates `q = (x, y, e0, e1, e2, e3)`: the centre's horizontal position (m) and the ball's
orientation as a unit quaternion e (body → space, `R = rotation_from_quaternion(e)`). Speeds
`u = (ẋ, ẏ, ωx, ωy, ωz)`: the centre's velocity (m/s) and the angular velocity in space axes
(rad/s), with ė = ½ (0, ω) ⊗ e (`jaxnh.rigid.quaternion_rate(..., frame="space")`).

Kinetic energy, with J = R diag(I1, I2, I3) Rᵀ the inertia tensor in space axes:

    T = ½ m (ẋ² + ẏ²) + ½ ωᵀ J ω.

Rolling: the velocity of the ball's material point at the contact, v + ω × (−a ẑ), is zero,

    ẋ − a ωy = 0,          ẏ + a ωx = 0,

two constraints in the speeds (m/s, so that their multipliers are the horizontal contact
forces, N).

Integrals (Chaplygin 1903; Borisov & Mamaev 2002, the section on Chaplygin's ball). The energy
E = T (`energy`). The angular momentum about the contact point,

    K = J ω + m r × v,   r = a ẑ (contact → centre),  v = ω × r (rolling),
      = J ω + m a² (ω − (ω·ẑ) ẑ),

is constant in space axes (`contact_angular_momentum`): the contact force and the weight have
no moment about the contact point, and that point moves parallel to the centre, so the term
v_P × m v of a moving reference point vanishes. In body axes, M = Rᵀ K and γ = Rᵀ ẑ obey
Ṁ = M × Ω, γ̇ = γ × Ω (Ω = Rᵀ ω), with M = I Ω + m a² γ × (Ω × γ), and have the integrals
H = ½ (M, Ω) (= E), F1 = (M, M), F2 = (M, γ) and (γ, γ) = 1, with which Chaplygin integrated
the motion by quadratures. F1 = |K|² and F2 = K·ẑ (`chaplygin_integrals`) follow from the
constancy of K. With I1 = I2 = I3 (a spherical inertia) J no longer depends on the orientation:
ω and the centre's velocity are constant, the centre moves on a straight line.

References:
* S. A. Chaplygin, "On a ball's rolling on a horizontal plane", Mat. Sbornik 24 (1903)
  139–168; English translation in Regular and Chaotic Dynamics 7 (2002) 131–148.
* A. V. Borisov, I. S. Mamaev, "Rolling of a rigid body on plane and sphere. Hierarchy of
  dynamics", Regular and Chaotic Dynamics 7 (2002) 177–200.

Units: m, kg, kg·m², rad, s, J.

Example (energy and K kept by the solve)::

    import jax, jax.numpy as jnp
    import jaxnh as nh
    from jaxnh.models import chaplygin

    p = chaplygin.default_params()
    q0, u0 = chaplygin.initial_state(p)
    ts = jnp.linspace(0.0, 10.0, 11)
    sol = nh.simulate(chaplygin.mechanism(), p, q0, u0, ts, rtol=1e-10, atol=1e-12)
    E = jax.vmap(chaplygin.energy, (0, 0, None))(sol.q, sol.u, p)                    # J
    K = jax.vmap(chaplygin.contact_angular_momentum, (0, 0, None))(sol.q, sol.u, p)  # kg·m²/s
    print(float(jnp.ptp(E) / E[0]), float(jnp.max(jnp.abs(K - K[0]))))
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
    "kinematics",
    "constraint",
    "rolling_speeds",
    "initial_state",
    "energy",
    "contact_angular_momentum",
    "chaplygin_integrals",
]


def _space_inertia(q: jax.Array, p: dict[str, Any]) -> jax.Array:
    """J = R diag(I) Rᵀ (3, 3), kg·m²: the inertia tensor about the centre in space axes."""
    R = rotation_from_quaternion(q[2:])
    return (R * p["I"]) @ R.T


def kinetic(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """T = ½ m (ẋ² + ẏ²) + ½ ωᵀ R I Rᵀ ω, J (in the speeds u)."""
    w = u[2:]
    return 0.5 * p["m"] * (u[0] ** 2 + u[1] ** 2) + 0.5 * w @ (_space_inertia(q, p) @ w)


def kinematics(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """dq/dt from the speeds: (ẋ, ẏ) in m/s and ė = ½ (0, ω) ⊗ e (ω in space axes) in 1/s."""
    return jnp.concatenate([u[:2], quaternion_rate(q[2:], u[2:], frame="space")])


def constraint(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """Velocity of the ball's material point at the contact, v + ω × (−a ẑ), horizontal part (2,), m/s."""
    a = p["a"]
    return jnp.stack([u[0] - a * u[3], u[1] + a * u[2]])


def mechanism() -> Mechanism:
    """The Chaplygin sphere rolling on a fixed horizontal plane (see the module note)."""
    return Mechanism(
        kinetic,
        constraints=constraint,
        kinematics=kinematics,
        quaternions=((2, 3, 4, 5),),
        names=("x", "y", "e0", "e1", "e2", "e3"),
    )


def default_params() -> dict[str, jax.Array]:
    """m = 1 kg, a = 0.1 m, principal moments I = (2, 3, 4.5)·10⁻³ kg·m² (m a² = 10⁻² kg·m²).

    The moments satisfy the triangle inequalities of a real body and sum to less than
    2 m a² (all mass within the radius)."""
    return {"m": jnp.asarray(1.0), "a": jnp.asarray(0.1), "I": jnp.array([2.0e-3, 3.0e-3, 4.5e-3])}


def rolling_speeds(p: dict[str, Any], wx: ArrayLike, wy: ArrayLike, wz: ArrayLike) -> jax.Array:
    """The speeds u (5,) of the ball rolling at angular velocity ω = (wx, wy, wz), rad/s, in space
    axes: the centre's velocity (a ωy, −a ωx), m/s, from the two rolling constraints."""
    a = p["a"]
    wx, wy, wz = jnp.asarray(wx), jnp.asarray(wy), jnp.asarray(wz)
    return jnp.stack([a * wy, -a * wx, wx, wy, wz]).astype(jnp.result_type(float))


def initial_state(
    p: dict[str, Any],
    tilt: float = 0.5,
    wx: float = 1.0,
    wy: float = -0.5,
    wz: float = 4.0,
    x: float = 0.0,
    y: float = 0.0,
) -> tuple[jax.Array, jax.Array]:
    """(q0, u0): the centre at (x, y), m; the body turned by `tilt` (rad) about the horizontal axis
    (1, 1, 0)/√2 from the identity (so the body z-axis is tilted by `tilt` from the vertical); rolling
    at angular velocity (wx, wy, wz), rad/s, in space axes."""
    dtype = jnp.result_type(float)
    axis = jnp.array([1.0, 1.0, 0.0], dtype=dtype) / jnp.sqrt(jnp.asarray(2.0, dtype=dtype))
    e = quaternion_from_axis_angle(axis, jnp.asarray(tilt, dtype=dtype))
    q0 = jnp.concatenate([jnp.array([x, y], dtype=dtype), e])
    return q0, rolling_speeds(p, wx, wy, wz)


def energy(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """The energy E = T, J (gravity does no work: the centre stays at height a). Constant."""
    return kinetic(q, u, 0.0, p)


def contact_angular_momentum(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """K = R I Rᵀ ω + m a² (ω − (ω·ẑ) ẑ) (3,), kg·m²/s, space axes: the angular momentum about the
    contact point, J ω + m r × v with r = a ẑ and v = ω × r (rolling). Constant."""
    w = u[2:]
    horizontal = w.at[2].set(0.0)  # ẑ × (ω × ẑ) = ω − (ω·ẑ) ẑ
    return _space_inertia(q, p) @ w + p["m"] * p["a"] ** 2 * horizontal


def chaplygin_integrals(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """Chaplygin's integrals (F1, F2) = ((M, M), (M, γ)) (2,): |K|², (kg·m²/s)², and K·ẑ, kg·m²/s,
    with M = Rᵀ K and γ = Rᵀ ẑ the body-axes momentum and vertical. Constant."""
    K = contact_angular_momentum(q, u, p)
    return jnp.stack([K @ K, K[2]])
