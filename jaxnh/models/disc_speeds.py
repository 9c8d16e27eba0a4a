"""The rolling disc of `jaxnh.models.disc`, written in Kane's generalized speeds.

The same thin rigid disc (mass m, radius r, moments of inertia I1 about a diameter and I3
about the axle, gravity g, z up), rolling without slipping on a level plane, in the same
coordinates `q = (x, y, yaw, lean, spin)` = (x, y, ψ, φ, θ): the contact point (m), the heading
of the disc's line of travel, its lean from the vertical and its spin about the axle (rad).
The frames are those of Kane & Levinson's rolling disc and of SymPy's example of it
(`sympy.physics.mechanics`, "A rolling disc, with Kane's method"): Y is N turned by ψ about
N.z, the lean frame L is Y turned by φ about Y.x, and the disc R is L turned by θ about L.y
(the axle), i.e. the disc's orientation is `Rz(ψ) Rx(φ) Ry(θ)` as in `jaxnh.models.disc`.

Speeds `u = (u1, u2, u3, u4, u5)`:

* u1, u2, u3 (rad/s): the disc's angular velocity in the lean frame, ω = u1 L.x + u2 L.y +
  u3 L.z. These are exactly the generalized speeds of SymPy's rolling-disc example
  (`R.set_ang_vel(N, u1*L.x + u2*L.y + u3*L.z)`), and they are the independent speeds here;
* u4, u5 (m/s): the velocity of the disc's material point at the contact, along L.x (the line
  of travel) and along Y.y = Y.z × L.x (sideways, horizontal). These are the auxiliary speeds
  u4, u5 of SymPy's "rolling disc, with Kane's method and constraint forces" (its u6, along the
  vertical, is zero here by construction: the disc touches the plane in these coordinates).
  Rolling is the two constraints `u4 = u5 = 0` (`slip`, m/s), so their multipliers are the
  horizontal contact forces on the disc (N) along L.x and Y.y, SymPy's f1 and f2.

Why the slip speeds are kept (with constraints) rather than embedded: SymPy's example imposes
rolling kinematically (the contact point has no velocity, `C.set_vel(N, 0)`), leaving three
speeds for five coordinates. jaxnh's Boltzmann–Hamel terms, as of this writing, are exact only
when the commutators of the columns of K = ∂q̇/∂u stay in their span, which a nonholonomic
embedding breaks (here [K2, K3] points sideways); with three speeds the solve drifts from
`jaxnh.models.disc` as soon as the lean moves. With u4, u5 as speeds K is square and
invertible (for |φ| < π/2) and the solve agrees with `jaxnh.models.disc`; Appell's form then
integrates the same state as SymPy's Kane equations, (q, u1, u2, u3).

Kinematic differential equations (`kinematics`), from ω = ψ̇ Y.z + φ̇ L.x + θ̇ L.y:

    φ̇ = u1,   ψ̇ = u3 / cos φ,   θ̇ = u2 − u3 tan φ,
    ẋ = (u4 + r θ̇) cos ψ − u5 sin ψ,   ẏ = (u4 + r θ̇) sin ψ + u5 cos ψ

(the geometric contact point moves at the material point's velocity plus r θ̇ along L.x).
The centre D = C + r L.z moves at v_D = u4 L.x + u5 Y.y + ω × r L.z, in L axes
(u4 + r u2, u5 cos φ − r u1, −u5 sin φ), and

    T = ½ m |v_D|² + ½ (I1 u1² + I3 u2² + I1 u3²),   V = m g r cos φ.

For a uniform disc (I1 = m r²/4, I3 = m r²/2) rolling, Kane's equations are SymPy's printed
right-hand side: u̇1 = (4 g sin φ + 6 r u2 u3 − r u3² tan φ) / (5 r), u̇2 = −2 u1 u3 / 3,
u̇3 = (u3 tan φ − 2 u2) u1. The speeds are singular where the disc lies flat (cos φ = 0), as
the Euler angles of `jaxnh.models.disc` are.

Closed forms are those of `jaxnh.models.disc`, reused: `steady_spin` (the spin rate of steady
circular rolling at lean φ and yaw rate Ψ) and `critical_spin` (the spin above which upright
rolling is stable); `initial_state` starts the steady motion.

References: T. R. Kane and D. A. Levinson, *Dynamics: Theory and Applications*, McGraw-Hill,
1985 (the rolling disc; generalized speeds, auxiliary speeds for constraint forces); SymPy,
`sympy.physics.mechanics` documentation, "A rolling disc, with Kane's method" and "... and
constraint forces".

Units: m, kg, kg·m², rad, s, N, J.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxnh._model.mechanism import Mechanism
from jaxnh.models import disc


__all__ = [
    "COORDINATES",
    "SPEEDS",
    "INDEPENDENT",
    "mechanism",
    "default_params",
    "kinetic",
    "potential",
    "kinematics",
    "slip",
    "speeds_from_rates",
    "initial_state",
    "energy",
    "steady_spin",
    "critical_spin",
]

COORDINATES = disc.COORDINATES
SPEEDS = ("u1", "u2", "u3", "u4", "u5")
INDEPENDENT = (0, 1, 2)

steady_spin = disc.steady_spin
critical_spin = disc.critical_spin


def kinematics(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """dq/dt (5,) from the speeds: (ẋ, ẏ) in m/s, (ψ̇, φ̇, θ̇) in rad/s (see the module note)."""
    yaw, lean = q[2], q[3]
    spin_rate = u[1] - u[2] * jnp.tan(lean)
    along = u[3] + p["r"] * spin_rate
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([along * c - u[4] * s, along * s + u[4] * c, u[2] / jnp.cos(lean), u[0], spin_rate])


def kinetic(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """T = ½ m |v_D|² + ½ (I1 u1² + I3 u2² + I1 u3²), J, with v_D the centre's velocity in L axes."""
    m, r, lean = p["m"], p["r"], q[3]
    v = jnp.stack([u[3] + r * u[1], u[4] * jnp.cos(lean) - r * u[0], -u[4] * jnp.sin(lean)])
    return 0.5 * m * jnp.sum(v**2) + 0.5 * (p["I1"] * (u[0] ** 2 + u[2] ** 2) + p["I3"] * u[1] ** 2)


def potential(q: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """V = m g r cos φ, J: the centre's height r cos φ above the plane."""
    return p["m"] * p["g"] * p["r"] * jnp.cos(q[3])


def slip(q: jax.Array, u: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """Velocity (2,) of the disc's material point at the contact along L.x and Y.y, m/s: zero when rolling."""
    return u[3:5]


MECHANISM = Mechanism(
    kinetic,
    constraints=slip,
    potential=potential,
    kinematics=kinematics,
    names=COORDINATES,
    independent=INDEPENDENT,
)


def mechanism() -> Mechanism:
    """The rolling disc in Kane's speeds; u1, u2, u3 independent (regular for |lean| < π/2)."""
    return MECHANISM


def default_params(
    m: float | jax.Array = 1.0, r: float | jax.Array = 0.3, g: float | jax.Array = 9.81
) -> dict[str, jax.Array]:
    """`jaxnh.models.disc.default_params`: a uniform thin disc of mass m (kg) and radius r (m),
    I1 = m r²/4, I3 = m r²/2 (kg·m²), gravity g (m/s²)."""
    return disc.default_params(m, r, g)


def speeds_from_rates(q: ArrayLike, qd: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """The speeds u (5,) (rad/s, m/s) of the state (q, q̇) of `jaxnh.models.disc` (the inverse of
    `kinematics`; u4 = u5 = 0 when q̇ satisfies that model's rolling constraints)."""
    q, qd = jnp.asarray(q), jnp.asarray(qd)
    yaw, lean = q[2], q[3]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    u1 = qd[3]
    u2 = qd[4] + qd[2] * jnp.sin(lean)
    u3 = qd[2] * jnp.cos(lean)
    u4 = qd[0] * c + qd[1] * s - p["r"] * qd[4]
    u5 = -qd[0] * s + qd[1] * c
    return jnp.stack([u1, u2, u3, u4, u5])


def initial_state(
    p: dict[str, Any],
    lean: float | jax.Array = 0.3,
    yaw_rate: float | jax.Array = -1.0,
    lean_rate: float | jax.Array = 0.0,
) -> tuple[jax.Array, jax.Array]:
    """(q0, u0) of steady circular rolling at lean φ (rad) and yaw rate Ψ (rad/s), starting at the
    origin heading along x, the spin rate from `steady_spin` (`jaxnh.models.disc.steady_state`);
    a nonzero `lean_rate` (rad/s) adds a lean rate to it, which starts a wobble.

    The defaults, with `default_params()`: spin 6.99 rad/s (above `critical_spin`, 3.30 rad/s),
    rolling forwards at 2.10 m/s on a circle of radius 2.10 m, leaning 0.3 rad into the turn."""
    q0, qd0 = disc.steady_state(lean, yaw_rate, p)
    qd0 = qd0.at[3].add(jnp.asarray(lean_rate, qd0.dtype))
    return q0, speeds_from_rates(q0, qd0, p)


def energy(q: jax.Array, u: jax.Array, p: dict[str, Any]) -> jax.Array:
    """T + V, J."""
    return kinetic(q, u, 0.0, p) + potential(q, 0.0, p)
