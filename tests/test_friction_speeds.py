"""Friction contacts on a mechanism written in speeds (issue 44): a ball in a unit quaternion, with
its angular velocity in space or in body axes as speeds, held by a two-row point contact.

Closed forms (ball of radius r, mass m, moment I = k m r² about its centre, k = 2/5; ẑ the normal of
the plane; the contact point at −r ẑ from the centre):

* **Thrown on level ground.** The slip velocity of the contact point is w = v + ω × (−r ẑ), so
  ẇ = v̇ − r ω̇ × ẑ. While it slips, the kinetic force F = −μk m g ŵ acts at the contact point:
  m v̇ = F and I ω̇ = (−r ẑ) × F, so ω̇ × ẑ = −(r/I) (ẑ × F) × ẑ = −(r/I) F (F horizontal) and
  ẇ = F/m + (r²/I) F = −(1 + 1/k) μk g ŵ. The slip keeps its direction ŵ0 and its size falls
  linearly, ‖w‖ = ‖w0‖ − (7/2) μk g t, to zero at

      t* = 2 ‖w0‖ / (7 μk g),

  when the ball starts rolling (μs ≥ μk: the force a free rolling ball needs is zero). Then
  v* = v0 + F t*/m = v0 − (2/7) w0, i.e. with w0 = v0 − r ω0 × ẑ

      v* = (5 v0 + 2 r ω0 × ẑ) / 7,     ω0 × ẑ = (ω0y, −ω0x, 0),

  and ω* has the horizontal part of rolling, (−v*y/r, v*x/r), and its vertical part ω0z
  (the force's moment about the centre is horizontal). Backspin makes ‖w0‖ > ‖v0‖, topspin
  (ω0 × ẑ beyond v0/r) reverses w0: both are run.
* **On an incline of angle α** (x down the slope), from rest. Rolling needs the force
  −(2/7) m g sin α along x (m a = m g sin α + F, I a / r² = −F, so a = (5/7) g sin α), inside
  the static cone μs m g cos α iff tan α ≤ (7/2) μs. Just below the threshold the ball rolls
  with x = (5/14) g sin α t²; just above, it slips from the start, the centre with
  a = g (sin α − μk cos α) and the slip with g (sin α − (7/2) μk cos α) > 0, never stopping.

These are checked in both formulations, with the angular velocity in space axes (the rows do not
depend on q) and in body axes (the rows are v + R(e) Ω × (−r ẑ): they depend on the integrated
quaternion, and their rates ∂c/∂q · q̇ go through `kinematics`).

A Chaplygin ball (unequal principal moments, mass centre at the geometric centre) thrown sliding
exercises Hamel's terms (its T depends on the orientation): its angular momentum about the contact
point, J ω + m r ẑ × v, is constant whether it slips or rolls (the kinetic force's moment about the
centre, (−r ẑ) × F, is cancelled by the change of m r ẑ × v, m v̇ = F), and the energy it loses is
the energy the contact dissipates.

Tolerances (RTOL = 1e-10, ATOL = 1e-12, float64, the default solver: Dopri8). The transition time
is located by Newton's method on the solver's interpolant to ROOT_TOLERANCE · eps = 1e3 eps
(relative and absolute, in s), after which the restart adds rounding. In space axes the speeds are
polynomial in t of degree ≤ 1 (positions 2) between transitions and the rows do not involve q, so
every Runge–Kutta method integrates them exactly: only the root finder and rounding remain, and
`EXACT` = 1e4 eps (10× the root finder's tolerance) bounds the relative errors. In body axes the
rows (and the Chaplygin ball's T) involve the integrated orientation, whose error is the solver's:
the local error per step is kept below RTOL |y| + ATOL, and over the O(1) s runs here (tens of
steps) its global error is bounded by the sum of the local errors the step control allowed, RTOL
(relative) per accepted step, plus EXACT: `integrated(sol)` (the runs are too short for the errors
to grow; measured, the largest is 1.0e-9 after 68 steps, against a bound of 6.8e-9).
A quaternion is rescaled after every step and at every report, so
| |e| − 1 | is the rounding of one division and one square root: ≤ 4 eps.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import chaplygin
from jaxnh.rigid import quaternion_rate, rotation_from_quaternion


EPS = float(np.finfo(np.float64).eps)
RTOL, ATOL = 1e-10, 1e-12
EXACT = 1e4 * EPS


def integrated(sol: nh.Solution) -> float:
    """The relative error bound of a run in body axes: RTOL per accepted step, plus EXACT."""
    return RTOL * int(sol.stats["num_accepted_steps"]) + EXACT


UNIT = 4 * EPS
G = 9.81  # m/s²
METHODS = ("lagrange", "appell")
# every (method, frame) is one compiled program (70-100 s to compile on a loaded 2-core machine):
# the quick tier runs two of them, which between them cover both formulations, both frames and
# Appell's re-chosen partition (body axes turn the dependent block through singular)
CASES = [
    ("lagrange", "space"),
    ("appell", "body"),
    pytest.param("appell", "space", marks=pytest.mark.extended),
    pytest.param("lagrange", "body", marks=pytest.mark.extended),
]
TS = jnp.linspace(0.0, 1.0, 11)


def contacts(sol) -> nh.ContactDiagnostics:
    """The contact diagnostics of a friction solve (present: the mechanism has contacts)."""
    assert sol.contacts is not None
    return sol.contacts


def slipping(sol) -> np.ndarray:
    """Which contacts slip at each report time (present: the mechanism has contacts)."""
    assert sol.slipping is not None
    return np.asarray(sol.slipping)


def unit_error(sol) -> float:
    """max | |e| − 1 | over the reports, for the quaternion q[2:6]."""
    return float(jnp.max(jnp.abs(jnp.linalg.norm(sol.q[:, 2:], axis=1) - 1)))


# --- a homogeneous ball in a unit quaternion -------------------------------------------------------


def _p(name):
    """A contact value read from params (differentiable)."""
    return lambda q, u, t, p: p[name]


@functools.cache
def ball(frame: str) -> nh.Mechanism:
    """The ball on a plane inclined at α (x down the slope): q = (x, y, e0, e1, e2, e3) (m; the unit
    quaternion body → space), u = (vx, vy, ωx, ωy, ωz) (m/s; rad/s, in `frame` axes). One object
    per frame: one compiled program per frame and method for the whole module."""

    def kinetic(q, u, t, p):
        """½ m |v|² + ½ k m r² |ω|², J (|ω| is the same in either axes)."""
        return 0.5 * p["m"] * (u[0] ** 2 + u[1] ** 2) + 0.5 * p["k"] * p["m"] * p["r"] ** 2 * jnp.sum(u[2:] ** 2)

    def qdot(q, u, t, p):
        return jnp.concatenate([u[:2], quaternion_rate(q[2:], u[2:], frame=frame)])

    def slip(q, u, t, p):
        """Slip velocity of the contact point, v + ω × (−r ẑ) (x, y), m/s, ω in space axes."""
        w = u[2:] if frame == "space" else rotation_from_quaternion(q[2:]) @ u[2:]
        return jnp.stack([u[0] - p["r"] * w[1], u[1] + p["r"] * w[0]])

    def potential(q, t, p):
        """Gravity along the slope, J."""
        return -p["m"] * G * jnp.sin(p["alpha"]) * q[0]

    def normal_force(q, u, t, p):
        """m g cos α, N; called with the speeds u (5,), never with dq/dt (6,) (checked as traced)."""
        assert u.shape == (5,), u.shape
        return p["m"] * G * jnp.cos(p["alpha"])

    ground = nh.FrictionContact(
        (0, 1),
        normal_force=normal_force,
        mu_static=_p("mu_s"),
        mu_kinetic=_p("mu_k"),
        name="ground",
    )
    return nh.Mechanism(
        kinetic,
        constraints=slip,
        potential=potential,
        kinematics=qdot,
        quaternions=((2, 3, 4, 5),),
        contacts=ground,
        names=("x", "y", "e0", "e1", "e2", "e3"),
    )


BALL = {"m": 0.17, "r": 0.03, "k": 0.4, "mu_s": 0.3, "mu_k": 0.2, "alpha": 0.0}
IDENTITY = jnp.array([1.0, 0.0, 0.0, 0.0])


def space_omega(sol, frame: str) -> np.ndarray:
    """ω in space axes at the reports (n, 3), rad/s."""
    w = np.asarray(sol.u[:, 2:])
    if frame == "space":
        return w
    return np.asarray(jax.vmap(lambda e, o: rotation_from_quaternion(e) @ o)(sol.q[:, 2:], sol.u[:, 2:]))


def run_ball(frame: str, method: str, p: dict, q0, u0) -> nh.Solution:
    """Every ball solve of this module (one compiled program per frame and method)."""
    return nh.simulate(
        ball(frame), p, q0, u0, TS, method=method, rtol=RTOL, atol=ATOL, max_transitions=4,
        record=("multipliers", "residual"),
    )  # fmt: skip


def level_ground_closed_form(v0: np.ndarray, w0: np.ndarray, p: dict) -> tuple[float, np.ndarray, np.ndarray]:
    """(t*, v*, ω*) of the ball thrown on level ground (the module docstring): s, m/s (2,), rad/s
    (3,) in space axes."""
    r, mu_k = p["r"], p["mu_k"]
    w_x_z = np.array([w0[1], -w0[0]])  # ω0 × ẑ, horizontal part
    slip0 = v0 - r * w_x_z
    t_star = 2 * np.linalg.norm(slip0) / (7 * mu_k * G)
    v_star = (5 * v0 + 2 * r * w_x_z) / 7
    w_star = np.array([-v_star[1] / r, v_star[0] / r, w0[2]])
    return float(t_star), v_star, w_star


SPINS = {
    # v0 (m/s), ω0 in space axes (rad/s): backspin (ωy < 0 while moving along +x) makes the slip
    # larger than v0; topspin beyond rolling (ωy > vx/r) reverses it
    "backspin": (np.array([2.0, 0.5]), np.array([5.0, -30.0, 10.0])),
    "topspin": (np.array([1.0, -0.2]), np.array([20.0, 80.0, -6.0])),
}


@pytest.mark.parametrize("spin", sorted(SPINS))
@pytest.mark.parametrize(("method", "frame"), CASES)
def test_thrown_ball_slides_then_rolls(method, frame, spin):
    v0, w0 = SPINS[spin]
    p = BALL
    t_star, v_star, w_star = level_ground_closed_form(v0, w0, p)
    assert 0.05 < t_star < 0.9  # the transition lies well inside the run
    # the body's angular velocity: ω0 in body axes is ω0 itself at the identity orientation
    u0 = jnp.array([*v0, *w0])
    sol = run_ball(frame, method, p, jnp.concatenate([jnp.zeros(2), IDENTITY]), u0)
    tol = EXACT if frame == "space" else integrated(sol)
    assert sol.message == "success"
    ((t, kind),) = contacts(sol).transitions("ground")
    assert kind == "slip→stick"
    assert abs(float(contacts(sol).transition_times[0, 0]) / t_star - 1) <= tol, (t, t_star)
    assert bool(contacts(sol).initial_slipping[0]) and contacts(sol).slip_intervals(0) == [(0.0, t)]
    speed = float(np.linalg.norm(v_star))
    np.testing.assert_allclose(np.asarray(sol.u[-1, :2]), v_star, rtol=0, atol=tol * speed)
    np.testing.assert_allclose(space_omega(sol, frame)[-1], w_star, rtol=0, atol=tol * float(np.linalg.norm(w_star)))
    # while slipping, the multipliers are the kinetic force −μk m g ŵ0 (N), the rows the slip
    # velocity (1 − t/t*) w0; rolling, the force is zero and so are the rows
    slip0 = v0 - p["r"] * np.array([w0[1], -w0[0]])
    slips = slipping(sol)[:, 0]
    assert slips.any() and (~slips).any()
    force = -p["mu_k"] * p["m"] * G * slip0 / np.linalg.norm(slip0)
    lam = np.asarray(sol.multipliers)
    np.testing.assert_allclose(lam[slips], np.broadcast_to(force, lam[slips].shape), atol=tol * p["m"] * G)
    np.testing.assert_allclose(lam[~slips], 0.0, atol=tol * p["m"] * G)
    w = np.outer(1 - np.asarray(TS) / t_star, slip0)
    res = np.asarray(sol.residual)
    size = float(np.linalg.norm(slip0))
    np.testing.assert_allclose(res[slips], w[slips], atol=tol * size)
    np.testing.assert_allclose(res[~slips], 0.0, atol=tol * size)
    # the energy lost is the energy dissipated: ½ m (|v0|² − |v*|²) + ½ I (|ω0|² − |ω*|²)
    I = p["k"] * p["m"] * p["r"] ** 2
    lost = 0.5 * p["m"] * (v0 @ v0 - v_star @ v_star) + 0.5 * I * (w0 @ w0 - w_star @ w_star)
    assert abs(float(contacts(sol).dissipated_energy[0]) / lost - 1) <= tol
    # sol.qd is dq/dt: the centre's velocity and the quaternion's rate from `kinematics`
    np.testing.assert_allclose(np.asarray(sol.qd[:, :2]), np.asarray(sol.u[:, :2]), rtol=0, atol=0)
    rates = jax.vmap(lambda q, u: quaternion_rate(q[2:], u[2:], frame=frame))(sol.q, sol.u)
    np.testing.assert_allclose(np.asarray(sol.qd[:, 2:]), np.asarray(rates), rtol=1e3 * EPS, atol=1e3 * EPS)
    assert unit_error(sol) <= UNIT


def incline_threshold(p: dict) -> float:
    """α (rad) at which rolling needs the whole static cone: tan α = (7/2) μs."""
    return math.atan(3.5 * p["mu_s"])


@pytest.mark.parametrize(("method", "frame"), CASES)
def test_ball_on_an_incline_rolls_below_the_threshold_and_slips_above(method, frame):
    q0, u0 = jnp.concatenate([jnp.zeros(2), IDENTITY]), jnp.zeros(5)
    ts = np.asarray(TS)
    for factor, slips in ((0.99, False), (1.01, True)):
        alpha = factor * incline_threshold(BALL)
        p = {**BALL, "alpha": alpha}
        sol = run_ball(frame, method, p, q0, u0)
        tol = EXACT if frame == "space" else integrated(sol)
        assert sol.message == "success"
        assert contacts(sol).transitions("ground") == []
        assert np.all(slipping(sol)[:, 0] == slips)
        a = G * (math.sin(alpha) - p["mu_k"] * math.cos(alpha)) if slips else 5 / 7 * G * math.sin(alpha)
        scale = 0.5 * a * ts[-1] ** 2  # m
        np.testing.assert_allclose(np.asarray(sol.q[:, 0]), 0.5 * a * ts**2, rtol=0, atol=tol * scale)
        np.testing.assert_allclose(np.asarray(sol.u[:, 0]), a * ts, rtol=0, atol=tol * a * ts[-1])
        np.testing.assert_allclose(np.asarray(sol.q[:, 1]), 0.0, atol=tol * scale)
        lam = np.asarray(sol.multipliers)
        weight = p["m"] * G
        if slips:
            slip_rate = G * (math.sin(alpha) - 3.5 * p["mu_k"] * math.cos(alpha))
            np.testing.assert_allclose(np.asarray(sol.residual)[:, 0], slip_rate * ts, atol=tol * slip_rate)
            np.testing.assert_allclose(lam[:, 0], -p["mu_k"] * weight * math.cos(alpha), atol=tol * weight)
            assert math.isnan(float(contacts(sol).peak_utilisation[0]))
        else:
            np.testing.assert_allclose(np.asarray(sol.residual), 0.0, atol=tol * a)
            F = -2 / 7 * weight * math.sin(alpha)
            np.testing.assert_allclose(lam[:, 0], F, atol=tol * weight)
            use = abs(F) / (p["mu_s"] * weight * math.cos(alpha))  # = tan α / ((7/2) μs)
            assert abs(float(contacts(sol).peak_utilisation[0]) - use) <= tol
        np.testing.assert_allclose(lam[:, 1], 0.0, atol=tol * weight)
        # the ball turns about the y axis by θ = x/r (rolling), or by θ = (5/4) μk g cos α t²/r
        # (slipping: I ω̇ = r μk m g cos α), so e = (cos θ/2, 0, sin θ/2, 0): integrated through
        # `kinematics` (the solver's error in either axes: its rates are not polynomial in t)
        spin = 0.5 * a / p["r"] if not slips else 1.25 * p["mu_k"] * G * math.cos(alpha) / p["r"]
        theta = spin * ts**2
        e = np.stack([np.cos(theta / 2), 0 * theta, np.sin(theta / 2), 0 * theta], axis=1)
        assert theta[-1] > 10.0  # many turns
        np.testing.assert_allclose(np.asarray(sol.q[:, 2:]), e, rtol=0, atol=integrated(sol) * theta[-1])
        assert unit_error(sol) <= UNIT


# --- Hamel's terms: a Chaplygin ball thrown sliding ---------------------------------------------


@functools.cache
def chaplygin_ball() -> nh.Mechanism:
    """`jaxnh.models.chaplygin`'s ball (space-axes speeds, T depending on the orientation) with its
    two rolling rows held by friction on level ground."""
    table = nh.FrictionContact((0, 1), lambda q, u, t, p: p["m"] * G, _p("mu_s"), _p("mu_k"), name="table")
    return nh.Mechanism(
        chaplygin.kinetic,
        constraints=chaplygin.constraint,
        kinematics=chaplygin.kinematics,
        quaternions=((2, 3, 4, 5),),
        contacts=table,
        names=("x", "y", "e0", "e1", "e2", "e3"),
    )


def contact_momentum(q, u, p):
    """J ω + m a ẑ × v (3,), kg·m²/s: the angular momentum about the contact point, slipping or not."""
    R = rotation_from_quaternion(q[2:])
    J = (R * p["I"]) @ R.T
    return J @ u[2:] + p["m"] * p["a"] * jnp.stack([-u[1], u[0], 0.0 * u[0]])


@pytest.mark.extended
def test_chaplygin_ball_thrown_sliding_keeps_its_contact_momentum():
    p = {**chaplygin.default_params(), "mu_s": jnp.asarray(0.3), "mu_k": jnp.asarray(0.2)}
    q0, u0 = chaplygin.initial_state(p)
    throw = jnp.array([1.5, -1.0])  # the centre 1.8 m/s off rolling: it slips for about 0.2 s
    u0 = u0.at[:2].add(throw)
    slip0 = float(jnp.linalg.norm(throw))
    ts = jnp.linspace(0.0, 0.5, 11)
    tau = math.sqrt(EPS) * 2 * float(jnp.linalg.norm(u0))  # m/s: see the rolling rows below
    sols, budgets = {}, {}
    for method in METHODS:
        sol = nh.simulate(
            chaplygin_ball(), p, q0, u0, ts, method=method, rtol=RTOL, atol=ATOL, max_transitions=4,
            record=("energy", "residual"),
        )  # fmt: skip
        assert sol.message == "success"
        # this motion is not polynomial: its global error is bounded by the sum of the local errors
        # the step control allowed, RTOL (relative) per accepted step (the run is too short for the
        # errors to grow), plus the root finder's and rounding's EXACT
        budget = integrated(sol)
        ((t, kind),) = contacts(sol).transitions("table")
        assert kind == "slip→stick" and 0.05 < t < 0.45, t
        K = np.asarray(jax.vmap(contact_momentum, (0, 0, None))(sol.q, sol.u, p))
        scale = float(np.linalg.norm(K[0]))
        np.testing.assert_allclose(K, np.broadcast_to(K[0], K.shape), rtol=0, atol=budget * scale)
        E = np.asarray(sol.energy)
        lost = float(contacts(sol).dissipated_energy[0])
        assert lost > 0.1 * E[0]
        assert abs(E[0] - E[-1] - lost) <= budget * E[0], (E[0] - E[-1], lost, budget)
        # rolling, the rows hold what they were at the lock: this slip turns as it stops, so it stops
        # within the regularisation of its direction, tau = √eps × the contact's velocity scale
        # (`Mode`; ≤ 2 ‖u0‖ for these rows of unit and radius-sized coefficients), not at 0
        rolling = ~slipping(sol)[:, 0]
        assert rolling.any()
        assert float(np.max(np.abs(np.asarray(sol.residual)[rolling]))) <= budget * slip0 + tau
        assert unit_error(sol) <= UNIT
        sols[method], budgets[method] = sol, budget
    # the two formulations agree to their budgets until the lock; there Appell's engaged rows hold
    # c = 0 exactly while Lagrange's keep the remainder (≤ tau): the speeds then differ by up to
    # tau/a (rad/s) and the orientations by that over the rest of the run
    lag, app = sols["lagrange"], sols["appell"]
    budget = budgets["lagrange"] + budgets["appell"]
    lock = tau / float(p["a"])
    t_l, t_a = (float(contacts(s).transition_times[0, 0]) for s in (lag, app))
    assert abs(t_l - t_a) <= budget * t_l
    np.testing.assert_allclose(np.asarray(lag.q), np.asarray(app.q), rtol=0, atol=budget + lock * float(ts[-1]))
    u_scale = float(jnp.max(jnp.abs(u0)))
    np.testing.assert_allclose(np.asarray(lag.u), np.asarray(app.u), rtol=0, atol=budget * u_scale + lock)


def test_a_quaternion_off_unit_norm_is_refused():
    """The friction solve checks what simulate's solve checks of a state in speeds."""
    q0 = jnp.array([0.0, 0.0, 1.0 + 1e-6, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="quaternion"):
        run_ball("space", "lagrange", BALL, q0, jnp.array([1.0, 0.0, 0.0, 0.0, 0.0]))


@pytest.mark.slow
def test_stick_margin_reads_the_contacts_in_the_speeds():
    """`stick_margin` of a mechanism in speeds calls the contacts' functions with the speeds u
    (not dq/dt, which has the quaternion's four rates: the ball's normal force checks the shape):
    on the incline just below the threshold the rolling ball uses (2/7) tan α / μs of its static
    cone at every instant."""
    alpha = 0.99 * incline_threshold(BALL)
    p = {**BALL, "alpha": alpha}
    margin = nh.stick_margin(
        ball("space"), p, jnp.concatenate([jnp.zeros(2), IDENTITY]), jnp.zeros(5), TS, rtol=RTOL, atol=ATOL
    )
    use = 2 / 7 * math.tan(alpha) / p["mu_s"]
    np.testing.assert_allclose(np.asarray(margin.utilisation)[:, 0], use, rtol=0, atol=EXACT)
