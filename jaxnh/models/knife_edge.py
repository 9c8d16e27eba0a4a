"""A knife edge (a skate) sliding on an inclined plane.

Coordinates `q = (x, y, φ)`: the contact point in the plane (m; x points
down the slope, y across it) and the heading φ of the blade (rad). The mass
centre is at the contact point; mass m (kg), moment of inertia J about the
normal (kg·m²); the plane is inclined at angle α (rad) under gravity g. The
blade cannot move sideways (Bloch, *Nonholonomic Mechanics and Control*,
§1.6):

    ẋ sin φ − ẏ cos φ = 0,          V = −m g sin α · x.

Released at rest at the origin, spinning at φ̇ = ω, it turns uniformly
(φ = ω t) and its contact point follows the cycloid-like closed form
(`closed_form`)

    x = (g sin α / 2ω²) sin² ωt,    y = (g sin α / 2ω²)(ωt − ½ sin 2ωt).

The heading passes π/2 every half turn, where the dependent velocity ẏ of
the split (independent ẋ, φ̇) cannot be solved (cos φ = 0). The default
Appell formulation re-chooses the split during the run (ẋ becomes the
dependent velocity near φ = π/2, ẏ again near φ = π), so it is valid for the
whole motion; a fixed split (`mechanism(independent=(0, 2))`) fails there
with `STATUS.singular_split` instead of returning a wrong motion.

Units: m, kg, kg·m², rad, s.
"""

from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxnh._model.mechanism import Mechanism


__all__ = ["mechanism", "default_params", "closed_form", "kinetic", "potential", "constraint"]


def kinetic(q: jax.Array, qd: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """T = ½ m (ẋ² + ẏ²) + ½ J φ̇², J."""
    return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * p["J"] * qd[2] ** 2


def potential(q: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """V = −m g sin α · x, J (x down the slope)."""
    return -p["m"] * p["g"] * jnp.sin(p["alpha"]) * q[0]


def constraint(q: jax.Array, qd: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """Sideways velocity of the blade, m/s: ẋ sin φ − ẏ cos φ."""
    return jnp.stack([qd[0] * jnp.sin(q[2]) - qd[1] * jnp.cos(q[2])])


def acceleration_energy(q: jax.Array, qd: jax.Array, qdd: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """S = ½ m (ẍ² + ÿ²) + ½ J φ̈², J/s²."""
    return 0.5 * p["m"] * (qdd[0] ** 2 + qdd[1] ** 2) + 0.5 * p["J"] * qdd[2] ** 2


def mechanism(independent: Optional[tuple[int, ...]] = None) -> Mechanism:
    """The knife edge; `independent`: fixed independent velocities, or None (default) for
    the automatic choice that changes during the run (see the module note)."""
    return Mechanism(
        kinetic,
        constraints=constraint,
        potential=potential,
        acceleration_energy=acceleration_energy,
        names=("x", "y", "phi"),
        independent=independent,
    )


def default_params() -> dict[str, jax.Array]:
    """m = 1 kg, J = 0.2 kg·m², g = 9.81 m/s², α = 0.3 rad."""
    return {"m": jnp.asarray(1.0), "J": jnp.asarray(0.2), "g": jnp.asarray(9.81), "alpha": jnp.asarray(0.3)}


def closed_form(p: dict[str, Any], ts: ArrayLike, omega: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """Exact q (n, 3) and q̇ (n, 3) released at rest at the origin spinning at ω (rad/s)."""
    A = p["g"] * jnp.sin(p["alpha"]) / (2 * omega**2)
    wt = omega * ts
    x = A * jnp.sin(wt) ** 2
    y = A * (wt - 0.5 * jnp.sin(2 * wt))
    xd = A * omega * jnp.sin(2 * wt)
    yd = A * omega * (1 - jnp.cos(2 * wt))
    q = jnp.stack([x, y, wt], axis=-1)
    qd = jnp.stack([xd, yd, jnp.full_like(wt, omega)], axis=-1)
    return q, qd
