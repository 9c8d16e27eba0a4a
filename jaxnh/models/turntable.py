"""A ball rolling without slipping on a turntable, in a unit quaternion and angular-velocity speeds.

A homogeneous (or any spherically symmetric) ball of mass m, radius a and moment of inertia
I = k² m a² about its centre rolls on a horizontal table that turns at the constant rate Ω
about the vertical axis through the origin. Coordinates `q = (x, y, e0, e1, e2, e3)`: the
centre's horizontal position (m) and the ball's orientation as a unit quaternion
(body → space). Speeds `u = (ẋ, ẏ, ωx, ωy, ωz)`: the centre's velocity (m/s) and the ball's
angular velocity in space axes (rad/s), with the quaternion's rate ė = ½ (0, ω) ⊗ e
(`jaxnh.rigid.quaternion_rate(..., frame="space")`). The orientation never locks: there is
no Euler-angle singularity to pass.

Rolling: the ball's material point at the contact moves with the table there,

    ẋ − a ωy + Ω y = 0,          ẏ + a ωx − Ω x = 0,

two constraints in the speeds (the slip velocity of the contact point, m/s, so that their
multipliers are the horizontal contact forces, N).

Closed form (Pars, *A Treatise on Analytical Dynamics*, 1965, §12.11; Bloch, *Nonholonomic
Mechanics and Control*, §1.7): the centre moves on a circle, uniformly, at the angular rate
Ω k²/(1 + k²) (2Ω/7 for a homogeneous ball), the same direction as the table: with
z = x + i y, `z(t) = c + (z0 − c) exp(i ν t)`, ν = Ω k²/(1 + k²), c = z0 + i ż0/ν
(`closed_form`).

Units: m, kg, rad, s.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxnh._model.mechanism import Mechanism
from jaxnh._model.rigid import quaternion_rate


__all__ = [
    "mechanism",
    "default_params",
    "kinetic",
    "kinematics",
    "constraint",
    "rolling_speeds",
    "initial_state",
    "closed_form",
    "circling_rate",
]


def kinetic(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """T = ½ m (ẋ² + ẏ²) + ½ k² m a² |ω|², J (in the speeds u)."""
    m, a = p["m"], p["a"]
    return 0.5 * m * (u[0] ** 2 + u[1] ** 2) + 0.5 * p["k2"] * m * a**2 * jnp.sum(u[2:] ** 2)


def kinematics(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """dq/dt from the speeds: (ẋ, ẏ) and ė = ½ (0, ω) ⊗ e (ω in space axes), 1/s."""
    return jnp.concatenate([u[:2], quaternion_rate(q[2:], u[2:], frame="space")])


def constraint(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """Slip velocity of the contact point relative to the table, (2,), m/s."""
    a, W = p["a"], p["Omega"]
    return jnp.stack([u[0] - a * u[3] + W * q[1], u[1] + a * u[2] - W * q[0]])


def mechanism() -> Mechanism:
    """The ball on the turntable (see the module note)."""
    return Mechanism(
        kinetic,
        constraints=constraint,
        kinematics=kinematics,
        quaternions=((2, 3, 4, 5),),
        names=("x", "y", "e0", "e1", "e2", "e3"),
    )


def default_params() -> dict[str, jax.Array]:
    """m = 1 kg, a = 0.1 m, k² = 2/5 (a homogeneous ball), Ω = 1 rad/s."""
    return {"m": jnp.asarray(1.0), "a": jnp.asarray(0.1), "k2": jnp.asarray(0.4), "Omega": jnp.asarray(1.0)}


def rolling_speeds(
    p: dict[str, Any], x: ArrayLike, y: ArrayLike, vx: ArrayLike, vy: ArrayLike, spin: ArrayLike
) -> jax.Array:
    """The speeds u (5,) of a ball rolling with its centre at (x, y) (m) moving at (vx, vy) (m/s)
    and spinning about the vertical at `spin` (rad/s): ωx, ωy from the two rolling constraints."""
    a, W = p["a"], p["Omega"]
    wx = (W * x - vy) / a
    wy = (vx + W * y) / a
    return jnp.stack([jnp.asarray(vx), jnp.asarray(vy), wx, wy, jnp.asarray(spin)]).astype(jnp.result_type(float))


def initial_state(
    p: dict[str, Any], x: float = 0.5, y: float = 0.0, vx: float = 0.0, vy: float = 0.2, spin: float = 3.0
) -> tuple[jax.Array, jax.Array]:
    """(q0, u0): the centre at (x, y) moving at (vx, vy), the orientation the identity, rolling."""
    dtype = jnp.result_type(float)
    q0 = jnp.array([x, y, 1.0, 0.0, 0.0, 0.0], dtype=dtype)
    return q0, rolling_speeds(p, x, y, vx, vy, spin)


def circling_rate(p: dict[str, Any]) -> jax.Array:
    """ν = Ω k²/(1 + k²), rad/s: the rate at which the centre circles (2Ω/7 for a homogeneous ball)."""
    return p["Omega"] * p["k2"] / (1.0 + p["k2"])


def closed_form(p: dict[str, Any], ts: ArrayLike, q0: ArrayLike, u0: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """The centre (x(t), y(t)), m, at the times ts (s) from the state (q0, u0) (see the module note)."""
    nu = circling_rate(p)
    q0, u0 = jnp.asarray(q0), jnp.asarray(u0)
    z0 = q0[0] + 1j * q0[1]
    zd0 = u0[0] + 1j * u0[1]
    c = z0 + 1j * zd0 / nu
    z = c + (z0 - c) * jnp.exp(1j * nu * jnp.asarray(ts))
    return jnp.real(z), jnp.imag(z)
