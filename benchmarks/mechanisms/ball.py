"""A solid ball rolling without slipping on a turntable (a rheonomic test mechanism with a closed form).

A ball of mass m, radius r and moment of inertia I about any axis through its
centre (a solid ball: I = 2/5 m r²) rolls without slipping on a horizontal
turntable that turns at the constant rate Ω (rad/s) about the vertical z
axis through the origin.

Coordinates (s = 6): `q = (x, y, e0, e1, e2, e3)` — the centre's horizontal
position (m; its height is r throughout) and the orientation as a quaternion
e = (e0, e1, e2, e3) (scalar first, body → world).

* Angular velocity (world frame) from the quaternion rates: the 4-vector
  `ω̃ = 2 ė ⊗ e*` has the angular velocity as its vector part and
  `2 e·ė = d|e|²/dt` as its scalar part.
* Kinetic energy `T = ½ m (ẋ² + ẏ²) + ½ I |ω̃|²`. On the unit sphere
  (`e·ė = 0`) the scalar part vanishes and this is the ball's kinetic
  energy; keeping it makes ∂²T/∂ė² = 4 I |e|² 1 positive definite, as jaxnh
  requires (with the vector part alone the mass matrix is singular along e).
* Holonomic constraint `g = e·e − 1 = 0` (jaxnh imposes it as
  `ġ = 2 e·ė = 0`, one velocity constraint; its multiplier absorbs the
  radial force the scalar part of T would otherwise exert).
* Rolling (2 nonholonomic constraints, slip velocity in m/s): the velocity of
  the ball's material point at the contact, `v + ω × (−r ẑ)`, equals the
  turntable's velocity there, `Ω ẑ × (x, y)`:

      ẋ − r ω_y + Ω y = 0,        ẏ + r ω_x − Ω x = 0.

  They are affine in the velocities (the turntable's motion makes them
  rheonomic). m = 3 velocity constraints in all, k = s − m = 3 degrees of
  freedom (the angular velocity).

Closed form. With ρ = (x, y) and F the horizontal contact force,
`m ρ̈ = F` and `I ω̇ = (−r ẑ) × F`; differentiating the rolling constraint
`ρ̇ = Ω ẑ × ρ + r ω × ẑ` gives `ρ̈ = Ω ẑ × ρ̇ − (m r²/I) ρ̈`, i.e.

    dv/dt = κ Ω ẑ × v,     κ = I / (I + m r²)   (= 2/7 for a solid ball),

so the centre's velocity v = ρ̇ turns at the constant rate ω_c = κ Ω and the
centre runs round a circle, at that rate, about the fixed point

    ρ_c = ρ0 + (ẑ × v0) / ω_c,
    ρ(t) = ρ_c + R(ω_c t) (ρ0 − ρ_c)      (R(φ) a rotation by φ about z),

with v0 = ρ̇(0) given by the rolling constraint at the initial state. The
vertical spin ω_z is constant (the contact torque is horizontal). The radius
of the circle is |v0| / ω_c.

Units: m, kg, kg·m², rad, s. Only the public API of jaxnh is used.
"""

from __future__ import annotations

import jax.numpy as jnp

import jaxnh as nh


__all__ = [
    "COORDINATES",
    "GOOD_INDEPENDENT",
    "mechanism",
    "params",
    "initial_state",
    "closed_form",
    "angular_velocity",
    "circle_rate",
]

COORDINATES = ("x", "y", "e0", "e1", "e2", "e3")

GOOD_INDEPENDENT = (1, 4, 5)
"""A fixed split that stays regular for the motions of `initial_state`: ẏ, ė2, ė3 independent,
ẋ, ė0, ė1 dependent. Its dependent block (rolling rows and 2 e·ė) has the determinant
−4 r (e0² + e1²), which never changes sign and vanishes only where e0 = e1 = 0 (a half turn
about a horizontal axis in the y–z plane). Splits with ẋ and ẏ both independent have the
determinant ±8 r² × one quaternion component, and those with ẋ and ẏ both dependent 2 × one
quaternion component (times the rolling rows' diagonal): each changes sign as the ball turns
over, so as fixed splits they fail with `STATUS.singular_split` within seconds. Checked
along the default motion over 50 s (smallest |det| of the row-normalised block 3.3e-4)."""


def _qmul(a, b):
    """Quaternion product a ⊗ b (scalar first)."""
    a0, av = a[0], a[1:]
    b0, bv = b[0], b[1:]
    return jnp.concatenate([jnp.stack([a0 * b0 - av @ bv]), a0 * bv + b0 * av + jnp.cross(av, bv)])


def _conj(e):
    return jnp.concatenate([e[:1], -e[1:]])


def omega4(e, ed):
    """ω̃ = 2 ė ⊗ e* (4,): (2 e·ė, ω_world)."""
    return 2.0 * _qmul(ed, _conj(e))


def angular_velocity(q, qd):
    """World-frame angular velocity ω (3,), rad/s."""
    return omega4(q[2:6], qd[2:6])[1:]


def kinetic(q, qd, t, p):
    """T = ½ m (ẋ² + ẏ²) + ½ I |2 ė ⊗ e*|², J."""
    w = omega4(q[2:6], qd[2:6])
    return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * p["I"] * (w @ w)


def rolling(q, qd, t, p):
    """Slip velocity of the contact point relative to the turntable, m/s (2,)."""
    w = angular_velocity(q, qd)
    r, Om = p["r"], p["Omega"]
    return jnp.stack([qd[0] - r * w[1] + Om * q[1], qd[1] + r * w[0] - Om * q[0]])


def unit_quaternion(q, t, p):
    """e·e − 1 (1,), dimensionless."""
    e = q[2:6]
    return jnp.stack([e @ e - 1.0])


MECHANISM = nh.Mechanism(kinetic, constraints=rolling, holonomic=unit_quaternion, names=COORDINATES)


def mechanism() -> nh.Mechanism:
    """The ball on the turntable (no default split: `method="appell"` chooses it automatically)."""
    return MECHANISM


def params(m=1.0, r=0.1, Omega=1.0, I=None) -> dict:
    """Mass m (kg), radius r (m), turntable rate Ω (rad/s); I (kg·m²) defaults to a solid ball's 2/5 m r²."""
    f = jnp.result_type(float)
    m, r = jnp.asarray(m, f), jnp.asarray(r, f)
    I = 0.4 * m * r**2 if I is None else jnp.asarray(I, f)
    return {"m": m, "r": r, "Omega": jnp.asarray(Omega, f), "I": I}


def initial_state(p, centre=(0.5, 0.0), omega=(1.0, -2.0, 3.0), e=(1.0, 0.0, 0.0, 0.0)):
    """(q0, qd0) satisfying all constraints: centre (m), world angular velocity ω (rad/s),
    orientation quaternion e (normalised here). ė = ½ (0, ω) ⊗ e, and (ẋ, ẏ) from rolling."""
    f = jnp.result_type(float)
    e = jnp.asarray(e, f)
    e = e / jnp.linalg.norm(e)
    w = jnp.asarray(omega, f)
    ed = 0.5 * _qmul(jnp.concatenate([jnp.zeros(1, f), w]), e)
    x, y = (jnp.asarray(c, f) for c in centre)
    r, Om = p["r"], p["Omega"]
    xd = r * w[1] - Om * y
    yd = -r * w[0] + Om * x
    q0 = jnp.concatenate([jnp.stack([x, y]), e])
    qd0 = jnp.concatenate([jnp.stack([xd, yd]), ed])
    return q0, qd0


def circle_rate(p):
    """ω_c = Ω I / (I + m r²), rad/s (2Ω/7 for a solid ball)."""
    return p["Omega"] * p["I"] / (p["I"] + p["m"] * p["r"] ** 2)


def closed_form(ts, p, q0, qd0):
    """Exact centre position (n, 2), m, and velocity (n, 2), m/s, at the times ts (s, from t = 0,
    where the state is (q0, qd0)).

    ρ(t) = ρ_c + R(ω_c t)(ρ0 − ρ_c), ρ_c = ρ0 + (ẑ × v0)/ω_c, v(t) = R(ω_c t) v0.
    """
    ts = jnp.asarray(ts)
    wc = circle_rate(p)
    rho0, v0 = q0[:2], qd0[:2]
    zxv0 = jnp.stack([-v0[1], v0[0]])
    rc = rho0 + zxv0 / wc
    d = rho0 - rc
    c, s = jnp.cos(wc * ts), jnp.sin(wc * ts)
    rho = rc + jnp.stack([c * d[0] - s * d[1], s * d[0] + c * d[1]], axis=-1)
    v = jnp.stack([c * v0[0] - s * v0[1], s * v0[0] + c * v0[1]], axis=-1)
    return rho, v
