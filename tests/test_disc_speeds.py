"""The rolling disc in Kane's speeds (`jaxnh.models.disc_speeds`) against its closed forms, against
the same disc in q̇ (`jaxnh.models.disc`) and against Kane's equations as SymPy prints them.

References:
* steady circular rolling: `disc.steady_spin` (lean, yaw rate and spin rate stay constant; the
  contact point runs on the circle of `disc.steady_path`);
* Kane's equations of a uniform disc, SymPy's rolling-disc example ("A rolling disc, with Kane's
  method"): u̇1 = (4 g sin φ + 6 r u2 u3 − r u3² tan φ)/(5 r), u̇2 = −2 u1 u3/3,
  u̇3 = (u3 tan φ − 2 u2) u1; its contact forces ("... and constraint forces"):
  f1 = m r (u1 u3 + u̇2), f2 = m r (u1² sin φ + u2 u3 / cos φ − u̇1 cos φ).

Tolerances: a solve at rtol keeps its global error within a modest multiple of rtol times the
solution's scale over the run (here `K_GLOBAL` = 100 rtol times the largest magnitude of the
compared quantity over the run); one evaluation of the equations is exact to a few hundred eps.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import disc, disc_speeds


EPS = float(jnp.finfo(jnp.float64).eps)
RTOL, ATOL = 1e-10, 1e-12
K_GLOBAL = 100.0  # global error ≤ K_GLOBAL · RTOL · scale
P = disc_speeds.default_params()
LEAN, YAW_RATE = 0.3, -1.0  # rad, rad/s: spin 6.99 rad/s, above the critical 3.30 rad/s
WOBBLE = 0.5  # rad/s of lean rate added to the steady motion: the lean then wobbles between 0.25 and 0.35 rad
TS = jnp.linspace(0.0, 5.0, 51)
MECH = disc_speeds.mechanism()


@functools.lru_cache(maxsize=None)
def _solve(method: str, lean_rate: float):
    q0, u0 = disc_speeds.initial_state(P, LEAN, YAW_RATE, lean_rate)
    return nh.simulate(MECH, P, q0, u0, TS, method=method, rtol=RTOL, atol=ATOL)


@functools.lru_cache(maxsize=None)
def _qdot_model(lean_rate: float):
    """The same motion in `jaxnh.models.disc` (q̇), simulate's default formulation."""
    q0, qd0 = disc.steady_state(LEAN, YAW_RATE, P)
    qd0 = qd0.at[3].add(lean_rate)
    return nh.simulate(disc.mechanism(), P, q0, qd0, TS, rtol=RTOL, atol=ATOL)


def _bound(x) -> float:
    return K_GLOBAL * RTOL * float(jnp.max(jnp.abs(x)))


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_steady_circular_rolling_stays_steady(method):
    sol = _solve(method, 0.0)
    assert sol.success
    spin = float(disc_speeds.steady_spin(LEAN, YAW_RATE, P))
    scale = max(abs(spin), abs(YAW_RATE))  # rad/s: the rates' scale
    assert float(jnp.max(jnp.abs(sol.q[:, 3] - LEAN))) <= K_GLOBAL * RTOL * LEAN
    assert float(jnp.max(jnp.abs(sol.qd[:, 2] - YAW_RATE))) <= K_GLOBAL * RTOL * scale
    assert float(jnp.max(jnp.abs(sol.qd[:, 4] - spin))) <= K_GLOBAL * RTOL * scale
    assert float(jnp.max(jnp.abs(sol.qd[:, 3]))) <= K_GLOBAL * RTOL * scale
    path = disc.steady_path(P, TS, LEAN, YAW_RATE)
    np.testing.assert_allclose(sol.q, path, rtol=0, atol=_bound(path))
    # rolling: the slip speeds stay zero (Appell: exactly; Lagrange: to its drift)
    assert float(jnp.max(jnp.abs(sol.u[:, 3:]))) <= K_GLOBAL * RTOL * scale * float(P["r"])


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_same_motion_as_the_qdot_model(method):
    """A wobbling disc (not steady), from the same initial state, in speeds and in q̇."""
    sol, ref = _solve(method, WOBBLE), _qdot_model(WOBBLE)
    assert sol.success and ref.success
    lean = np.asarray(ref.q[:, 3])
    assert lean.max() - lean.min() > 0.05  # the lean does move
    np.testing.assert_allclose(sol.q, ref.q, rtol=0, atol=_bound(ref.q))
    np.testing.assert_allclose(sol.qd, ref.qd, rtol=0, atol=_bound(ref.qd))
    u = jax.vmap(disc_speeds.speeds_from_rates, (0, 0, None))(ref.q, ref.qd, P)
    np.testing.assert_allclose(sol.u[:, :3], u[:, :3], rtol=0, atol=_bound(u))


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_energy_is_conserved(method):
    sol = _solve(method, WOBBLE)
    E = jax.vmap(disc_speeds.energy, (0, 0, None))(sol.q, sol.u, P)
    assert float(jnp.max(jnp.abs(E - E[0]))) <= K_GLOBAL * RTOL * float(E[0])


STATE_Q = jnp.array([0.4, -0.2, 0.7, 0.35, 1.1])
STATE_U = jnp.array([0.4, 2.0, -1.5, 0.0, 0.0])


def _kane(q, u, p):
    """SymPy's printed Kane equations (uniform disc) and contact forces f1, f2 (N)."""
    lean, (u1, u2, u3) = q[3], u[:3]
    g, r, m = p["g"], p["r"], p["m"]
    ud = jnp.stack(
        [
            (4 * g * jnp.sin(lean) + 6 * r * u2 * u3 - r * u3**2 * jnp.tan(lean)) / (5 * r),
            -2 * u1 * u3 / 3,
            (u3 * jnp.tan(lean) - 2 * u2) * u1,
        ]
    )
    f1 = m * r * (u1 * u3 + ud[1])
    f2 = m * r * (u1**2 * jnp.sin(lean) + u2 * u3 / jnp.cos(lean) - ud[0] * jnp.cos(lean))
    return ud, jnp.stack([f1, f2])


def test_accelerations_are_kanes_equations():
    """Lagrange's form at a generic state (Appell's integrates the same equations: see the solves above)."""
    ud, lam = nh.accelerations(MECH, STATE_Q, STATE_U, 0.0, P)
    ud_ref, f_ref = _kane(STATE_Q, STATE_U, P)
    scale = float(jnp.max(jnp.abs(ud_ref)))
    np.testing.assert_allclose(ud[:3], ud_ref, rtol=0, atol=256 * EPS * scale)
    np.testing.assert_allclose(ud[3:], 0.0, rtol=0, atol=256 * EPS * scale * float(P["r"]))
    # the multipliers are the contact forces on the disc along L.x and Y.y
    assert lam is not None
    np.testing.assert_allclose(lam, f_ref, rtol=0, atol=256 * EPS * float(jnp.max(jnp.abs(f_ref))))


def test_speeds_from_rates_inverts_kinematics():
    qd = disc_speeds.kinematics(STATE_Q, STATE_U.at[3:].set(jnp.array([0.3, -0.2])), 0.0, P)
    u = disc_speeds.speeds_from_rates(STATE_Q, qd, P)
    np.testing.assert_allclose(u, STATE_U.at[3:].set(jnp.array([0.3, -0.2])), rtol=0, atol=16 * EPS * 2.0)


def test_reuses_the_closed_forms_of_the_qdot_model():
    assert disc_speeds.steady_spin is disc.steady_spin and disc_speeds.critical_spin is disc.critical_spin
    assert disc_speeds.default_params() == disc.default_params()
    assert disc_speeds.COORDINATES == disc.COORDINATES


def _embedded_kinematics(q, u, t, p):
    yaw, lean = q[2], q[3]
    spin_rate = u[1] - u[2] * jnp.tan(lean)
    return jnp.stack(
        [p["r"] * spin_rate * jnp.cos(yaw), p["r"] * spin_rate * jnp.sin(yaw), u[2] / jnp.cos(lean), u[0], spin_rate]
    )


def _embedded_kinetic(q, u, t, p):
    return 0.5 * p["m"] * p["r"] ** 2 * (u[0] ** 2 + u[1] ** 2) + 0.5 * (
        p["I1"] * (u[0] ** 2 + u[2] ** 2) + p["I3"] * u[1] ** 2
    )


def test_rolling_embedded_in_kinematics_is_refused():
    """Rolling written into `kinematics` (3 speeds for 5 coordinates, SymPy's C.set_vel(N, 0)): the
    commutator [K2, K3] points sideways, out of span(K), and would meet the sideways momentum
    −m r u1 cos φ, which T in the speeds does not give (u̇2 would miss −m r² u1 u3 / (I3 + m r²) and
    u̇3 m r² u1 u2 / I1). jaxnh refuses it: eagerly by name, under jit as NaN, in simulate with
    STATUS.speeds_incomplete. disc_speeds keeps the slip speeds u4, u5 with constraints instead."""
    mech = nh.Mechanism(_embedded_kinetic, kinematics=_embedded_kinematics, potential=disc_speeds.potential)
    with pytest.raises(ValueError, match="kinematics"):
        nh.accelerations(mech, STATE_Q, STATE_U[:3], 0.0, P)
    ud, _ = jax.jit(lambda q: nh.accelerations(mech, q, STATE_U[:3], 0.0, P))(STATE_Q)
    assert bool(jnp.all(jnp.isnan(ud)))
    sol = nh.simulate(mech, P, STATE_Q, STATE_U[:3], jnp.linspace(0.0, 0.1, 3), throw=False)
    assert sol.status == nh.STATUS.speeds_incomplete
