"""The Chaplygin sleigh: a rigid body on a plane resting on a knife edge.

Coordinates `q = (x, y, θ)`: the position of the blade's contact point P
(m) and the heading θ of the body axis (rad). The mass centre G lies on the
body axis at distance `a` ahead of P. The blade cannot slide sideways:

    −ẋ sin θ + ẏ cos θ = 0                    (one nonholonomic constraint)

With the forward speed of P `v = ẋ cos θ + ẏ sin θ` and `ω = θ̇`, the motion
obeys (Bloch, *Nonholonomic Mechanics and Control*, §1.7)

    v̇ = a ω²,      I ω̇ = −m a v ω,      I = I_C + m a²,

which integrates in closed form (`closed_form`): with
`V = √(v0² + I ω0²/m)`, `k = m a V / I`, `c = artanh(v0 / V)`,

    v = V tanh(k t + c),     ω = ω0 cosh c / cosh(k t + c),
    θ = θ0 + (ω0 cosh c / k) (gd(k t + c) − gd(c)),   gd(u) = 2 atan(tanh(u/2)).

The kinetic energy is built by `jaxnh.rigid.RigidBodies` from the body's
pose. The model fixes the split (independent ẋ, θ̇): the dependent velocity
ẏ is regular while cos θ ≠ 0, so keep the whole turn inside (−π/2, π/2)
(a run that leaves it fails with STATUS.singular_split), or use "lagrange",
or `jaxnh.Appell()` on a Mechanism without `independent`, which re-chooses
the split during the run.

Units: m, kg, kg·m², rad, s.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxnh._model.mechanism import Mechanism
from jaxnh._model.rigid import RigidBodies, rot_z


__all__ = ["bodies", "mechanism", "default_params", "closed_form", "forward_speed", "initial_velocities"]


def _poses(q, t, p):
    x, y, th = q
    G = jnp.stack([x + p["a"] * jnp.cos(th), y + p["a"] * jnp.sin(th), jnp.zeros_like(x)])
    return [(G, rot_z(th))]


def _inertias(p):
    I = jnp.diag(jnp.stack([p["I_C"], p["I_C"], p["I_C"]]))  # only I_zz matters in plane motion
    return [(p["m"], I)]


def bodies() -> RigidBodies:
    """The sleigh as one rigid body (mass centre G, heading θ about z)."""
    return RigidBodies(_poses, _inertias, names=("sleigh",))


def knife_edge(q: jax.Array, qd: jax.Array, t: ArrayLike, p: dict[str, Any]) -> jax.Array:
    """Sideways velocity of the blade's contact point, m/s (must vanish)."""
    th = q[2]
    return jnp.stack([-qd[0] * jnp.sin(th) + qd[1] * jnp.cos(th)])


def mechanism() -> Mechanism:
    """The sleigh: T from the rigid-body helper, S too; ẋ and θ̇ independent."""
    b = bodies()
    return Mechanism(
        b.kinetic,
        constraints=knife_edge,
        acceleration_energy=b.acceleration_energy,
        names=("x", "y", "theta"),
        independent=(0, 2),
    )


def default_params() -> dict[str, jax.Array]:
    """m = 1 kg, I_C = 0.1 kg·m² about G, a = 0.5 m (G ahead of the blade)."""
    return {"m": jnp.asarray(1.0), "I_C": jnp.asarray(0.1), "a": jnp.asarray(0.5)}


def initial_velocities(q0: jax.Array, v0: ArrayLike, w0: ArrayLike) -> jax.Array:
    """q̇ at heading q0[2] for forward speed v0 (m/s) and turning rate w0 (rad/s)."""
    th = q0[2]
    return jnp.stack([v0 * jnp.cos(th), v0 * jnp.sin(th), jnp.asarray(w0, dtype=jnp.result_type(v0, float))])


def forward_speed(q: jax.Array, qd: jax.Array) -> jax.Array:
    """v = ẋ cos θ + ẏ sin θ, m/s (works on batches of states)."""
    return qd[..., 0] * jnp.cos(q[..., 2]) + qd[..., 1] * jnp.sin(q[..., 2])


def closed_form(
    p: dict[str, Any], ts: ArrayLike, v0: float | jax.Array, w0: float | jax.Array, th0: float | jax.Array = 0.0
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Exact (v, ω, θ) at times ts from v(0) = v0, ω(0) = w0, θ(0) = th0.

    Needs a ≠ 0 and (v0, ω0) ≠ 0. Returns three arrays shaped like ts.
    """
    I = p["I_C"] + p["m"] * p["a"] ** 2
    V = jnp.sqrt(v0**2 + I * w0**2 / p["m"])
    k = p["m"] * p["a"] * V / I
    c = jnp.arctanh(v0 / V)
    u = k * ts + c

    def gd(z):
        return 2 * jnp.arctan(jnp.tanh(z / 2))

    v = V * jnp.tanh(u)
    w = w0 * jnp.cosh(c) / jnp.cosh(u)
    th = th0 + w0 * jnp.cosh(c) / k * (gd(u) - gd(c))
    return v, w, th
