"""A thin rigid disc (a coin, a wheel) rolling without slipping on a level plane.

Coordinates `q = (x, y, yaw, lean, spin)`: the contact point (m), the heading
ψ of the disc's line of travel, its lean φ from the vertical, and its spin θ
about the axle (rad). With z up, the disc's orientation is
`Rz(ψ) Rx(φ) Ry(θ)` (the axle is its body y axis) and its centre is
`(x, y, 0) + r Rz(ψ) Rx(φ) e_z`, so it touches the plane by construction;
rolling gives two nonholonomic constraints (`jaxnh.rigid.Wheel`). Mass m,
radius r, moments of inertia I1 about a diameter and I3 about the axle
(a uniform thin disc: I1 = m r²/4, I3 = m r²/2), gravity g.

Known answers (derived by Newton–Euler about the mass centre; see
`steady_spin` and `critical_spin`):

* Steady motions: at constant lean φ and yaw rate Ψ the spin rate is
  `θ̇ = (I1 Ψ² sin φ cos φ − m g r sin φ) / ((I3 + m r²) Ψ cos φ) − Ψ sin φ`,
  and the contact point runs round a circle of radius `r θ̇ / Ψ`.
* Upright straight rolling at spin Ω: the lean obeys
  `(I1 + m r²) λ² = m g r − (I3 + m r²) I3 Ω² / I1`, so it is stable
  (λ imaginary) iff `Ω² > m g r I1 / (I3 (I3 + m r²))`, i.e.
  `Ω² > g / (3 r)` for a uniform thin disc.

Units: m, kg, kg·m², rad, s.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxnh._analysis.linearize import linearize
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.rigid import RigidBodies, rot_x, rot_y, rot_z, Wheel


__all__ = [
    "COORDINATES",
    "mechanism",
    "default_params",
    "bodies",
    "steady_spin",
    "steady_state",
    "steady_path",
    "critical_spin",
    "lean_eigenvalue_squared",
    "upright",
    "linearized",
]

COORDINATES = ("x", "y", "yaw", "lean", "spin")
INDEPENDENT = (2, 3, 4)


def _pose(q, t, p):
    lean = rot_z(q[2]) @ rot_x(q[3])
    centre = jnp.stack([q[0], q[1], jnp.zeros_like(q[0])]) + p["r"] * lean[:, 2]
    return centre, lean @ rot_y(q[4])


def _inertias(p):
    return [(p["m"], jnp.diag(jnp.stack([p["I1"], p["I3"], p["I1"]])))]


def _gravity(p):
    z = jnp.zeros_like(p["g"])
    return jnp.stack([z, z, -p["g"]])


def _radius(p):
    return p["r"]


WHEEL = Wheel(_pose, _radius, axle=1, normal=(0.0, 0.0, 1.0))


def bodies() -> RigidBodies:
    """The disc as one rigid body under gravity (z up)."""
    return RigidBodies(lambda q, t, p: [_pose(q, t, p)], _inertias, gravity=_gravity, names=("disc",))


def rolling(q, qd, t, p):
    """Slip velocity of the disc's contact point along x and y, m/s (2,)."""
    return WHEEL.slip(q, qd, t, p)


_BODIES = bodies()
MECHANISM = Mechanism(
    _BODIES.kinetic,
    constraints=rolling,
    potential=_BODIES.potential,
    acceleration_energy=_BODIES.acceleration_energy,
    names=COORDINATES,
    independent=INDEPENDENT,
)


def mechanism() -> Mechanism:
    """The rolling disc; yaw, lean and spin rates independent (always regular)."""
    return MECHANISM


def default_params(m: float | jnp.ndarray = 1.0, r: float | jnp.ndarray = 0.3, g: float | jnp.ndarray = 9.81) -> dict:
    """A uniform thin disc of mass m (kg) and radius r (m): I1 = m r²/4, I3 = m r²/2."""
    f = jnp.result_type(float)
    m, r = jnp.asarray(m, f), jnp.asarray(r, f)
    return {"m": m, "r": r, "I1": m * r**2 / 4, "I3": m * r**2 / 2, "g": jnp.asarray(g, f)}


def steady_spin(lean: float | jnp.ndarray, yaw_rate: float | jnp.ndarray, p: dict) -> jnp.ndarray:
    """Spin rate θ̇ (rad/s) of the steady motion at lean φ (rad) and yaw rate Ψ (rad/s)."""
    s, c = jnp.sin(lean), jnp.cos(lean)
    w2 = (p["I1"] * yaw_rate**2 * s * c - p["m"] * p["g"] * p["r"] * s) / (
        (p["I3"] + p["m"] * p["r"] ** 2) * yaw_rate * c
    )
    return w2 - yaw_rate * s


def steady_state(lean: float | jnp.ndarray, yaw_rate: float | jnp.ndarray, p: dict) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(q, q̇) at t = 0 of the steady motion, starting at the origin heading along x."""
    spin = steady_spin(lean, yaw_rate, p)
    lean = jnp.asarray(lean, dtype=spin.dtype)
    z = jnp.zeros_like(spin)
    q = jnp.stack([z, z, z, lean, z])
    qd = jnp.stack([p["r"] * spin, z, jnp.asarray(yaw_rate, spin.dtype), z, spin])
    return q, qd


def steady_path(p: dict, ts: jnp.ndarray, lean: float | jnp.ndarray, yaw_rate: float | jnp.ndarray) -> jnp.ndarray:
    """Exact q (n, 5) of the steady motion from `steady_state`: the contact point
    on a circle of radius r θ̇ / Ψ, ψ = Ψ t, constant lean, θ = θ̇ t."""
    spin = steady_spin(lean, yaw_rate, p)
    R = p["r"] * spin / yaw_rate
    psi = yaw_rate * ts
    return jnp.stack([R * jnp.sin(psi), R * (1 - jnp.cos(psi)), psi, jnp.full_like(ts, lean), spin * ts], axis=-1)


def critical_spin(p: dict) -> jnp.ndarray:
    """Spin rate (rad/s) above which upright rolling is stable: √(m g r I1 / (I3 (I3 + m r²)))."""
    return jnp.sqrt(p["m"] * p["g"] * p["r"] * p["I1"] / (p["I3"] * (p["I3"] + p["m"] * p["r"] ** 2)))


def lean_eigenvalue_squared(spin: float | jnp.ndarray, p: dict) -> jnp.ndarray:
    """λ² of the lean mode of upright rolling at spin Ω (1/s²): negative when stable."""
    mr2 = p["m"] * p["r"] ** 2
    return (p["m"] * p["g"] * p["r"] - (p["I3"] + mr2) * p["I3"] * spin**2 / p["I1"]) / (p["I1"] + mr2)


def upright(spin: float | jnp.ndarray, p: dict) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(q, q̇) of upright straight rolling along x at spin Ω (rad/s), speed r Ω."""
    spin = jnp.asarray(spin, dtype=jnp.result_type(float))
    z = jnp.zeros_like(spin)
    return jnp.zeros(5, spin.dtype), jnp.stack([p["r"] * spin, z, z, z, spin])


def linearized(q: jnp.ndarray, qd: jnp.ndarray, p: dict, method: str = "lagrange", steady: bool = True) -> object:
    """`jaxnh.Linearization` about (q, q̇) with state (lean, d yaw, d lean, d spin).

    Position, heading and spin angle are ignorable. `steady=True` declares
    the operating point steady (zero independent accelerations, true for
    upright rolling and for the motions of `steady_state`), which saves a
    pass; `rates` shows whether it was.
    """
    acc = jnp.zeros(len(INDEPENDENT), jnp.result_type(q, float)) if steady else None
    return linearize(MECHANISM, p, q, qd, coordinates=(3,), speeds=INDEPENDENT, method=method, accelerations=acc)
