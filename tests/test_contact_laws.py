"""Contact laws (`FrictionContact(law=...)`): the kinetic force of a slipping contact as a function
of its slip speed, checked against closed forms and a high-accuracy reference, for both formulations.

The scene: a block of mass m on a level floor (one coordinate x, m; one friction-held row, the slip
velocity x', m/s), pressed by N = m g and thrown with speed v0. It slides, slowed by the kinetic
force F(v), until it stops; then it sticks (it needs no force to stay). Closed forms:

* Viscous, F = μk N + σ v: m v' = −μk N − σ v, so with a = μk N/m and k = σ/m,
  v(t) = (v0 + a/k) e^(−k t) − a/k and x(t) = (v0 + a/k)(1 − e^(−k t))/k − a t/k until the stop at
  t_s = ln(1 + k v0/a)/k = (m/σ) ln(1 + σ v0/(μk N)), with
  dt_s/dσ = −(m/σ²) ln(1 + σ v0/(μk N)) + (m/σ)(v0/(μk N))/(1 + σ v0/(μk N)).
  All the kinetic energy ½ m v0² is dissipated, over the slip distance x(t_s).
* Stribeck, F = N (μk + (μs − μk) exp(−(v/vs)²)) + σ v: no closed form; the reference is scipy's
  DOP853 at rtol 1e-13 with an event at v = 0.

Tolerances. The solves use RTOL = 1e-10, ATOL = 1e-12 (float64, EPS = 2.2e-16). Unlike the
polynomial motions of tests/test_friction.py, these motions are exponential, so the solver's own
error remains: Tsit5 holds each step's local error to RTOL, the block's slip takes about ten steps,
and the report times are read from a fourth-order interpolant whose error is a few times the step's.
So the speeds are allowed TOL_V = 100 RTOL v0 (+ 100 EPS v0 of rounding); about 12 RTOL v0 is reached.
A time at which the speed crosses a value (the stop) carries that speed error divided by the
deceleration there, plus the event root finder's 1e3 EPS. The derivative of a discrete solution
differs from the derivative of the exact one by the derivative of its error, which scales like
the fifth power of the step, and the step like 1/σ: (5 + 1) × the stop time's error over σ.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxnh as nh


EPS = float(np.finfo(np.float64).eps)
RTOL, ATOL = 1e-10, 1e-12
ROOT = 1e3 * EPS  # the event root finder's tolerance on a time, relative and absolute (friction.ROOT_TOLERANCE)
G = 9.81  # m/s²
METHODS = ("lagrange", "appell")
V0 = 3.0  # m/s
TS = jnp.linspace(0.0, 1.0, 11)
TOL_V = 100 * RTOL * V0 + 100 * EPS * V0  # m/s: see the module docstring
P = {"m": 2.0, "mu_s": 0.5, "mu_k": 0.3, "sigma": 4.0, "vs": 0.5, "v_bad": -1.0, "drop": 0.0}


def _p(name):
    """A value read from params (differentiable)."""
    return lambda q, qd, t, p: p[name]


def contacts(sol) -> nh.ContactDiagnostics:
    """The contact diagnostics of a friction solve (present: the mechanism has contacts)."""
    assert sol.contacts is not None
    return sol.contacts


def block(law=None) -> nh.Mechanism:
    """The block on the floor, with `law` (None: FrictionContact's default)."""
    kw = {} if law is None else {"law": law}
    floor = nh.FrictionContact(0, normal_force=_normal, mu_static=_mu_s, mu_kinetic=_mu_k, name="floor", **kw)
    return nh.Mechanism(_block_T, constraints=_block_slip, contacts=floor, names=("x",))


def _block_T(q, qd, t, p):
    return 0.5 * p["m"] * qd[0] ** 2


def _block_slip(q, qd, t, p):
    return jnp.stack([qd[0]])


_normal, _mu_s, _mu_k = (lambda q, qd, t, p: p["m"] * G), _p("mu_s"), _p("mu_k")


def throw(mech, p, method, **kw):
    """Every solve of this module: the block thrown at V0 from x = 0."""
    return nh.simulate(mech, p, jnp.zeros(1), jnp.array([V0]), TS, method=method, rtol=RTOL, atol=ATOL,
                       max_transitions=2, **kw)  # fmt: skip


# --- viscous: closed form -------------------------------------------------------------------------

VISCOUS = block(nh.Viscous(damping=_p("sigma")))


def viscous_closed_form(p, t):
    """(v(t), x(t), t_s, dt_s/dσ) of the viscous block, t an array (s)."""
    m, sigma, N = p["m"], p["sigma"], p["m"] * G
    a, k = p["mu_k"] * N / m, sigma / m
    t_s = math.log(1 + k * V0 / a) / k
    tt = np.minimum(np.asarray(t), t_s)
    v = np.where(np.asarray(t) < t_s, (V0 + a / k) * np.exp(-k * tt) - a / k, 0.0)
    x = (V0 + a / k) * (1 - np.exp(-k * tt)) / k - a * tt / k
    r = sigma * V0 / (p["mu_k"] * N)
    dts = -(m / sigma**2) * math.log(1 + r) + (m / sigma) * (V0 / (p["mu_k"] * N)) / (1 + r)
    return v, x, t_s, dts


@pytest.fixture(scope="module", params=[pytest.param("lagrange", marks=pytest.mark.slow), "appell"])
def viscous(request):
    """(method, solution, d t_s/dσ or None), one compiled program per method. Lagrange's is `jax.grad` of
    the stop time (the first transition time in `sol.contacts`, through the restart) with the solution
    as its auxiliary output; Appell's is the solve alone (a reverse-mode program takes a minute to
    compile: one keeps this file within its time budget; forward mode through Appell's form, jax.jvp
    with adjoint=diffrax.ForwardMode(), reached the same accuracy when this test was written)."""
    method = request.param

    def stop_time(sigma):
        sol = throw(VISCOUS, {**P, "sigma": sigma}, method)
        return contacts(sol).transition_times[0, 0], sol

    if method == "appell":
        return method, stop_time(P["sigma"])[1], None
    (_, sol), dts = jax.value_and_grad(stop_time, has_aux=True)(jnp.asarray(P["sigma"]))
    return method, sol, float(dts)


def test_viscous_block_against_its_closed_form(viscous):
    method, sol, dts = viscous
    v, x, t_s, dts_exact = viscous_closed_form(P, TS)
    assert bool(sol.status == nh.STATUS.successful), sol.message
    c = contacts(sol)
    assert bool(c.initial_slipping[0]) and [k for _, k in c.transitions("floor")] == ["slip→stick"]
    # the speed at the report times, and the position (its error is the speed's integrated: ≤ TOL_V × 1 s)
    np.testing.assert_allclose(np.asarray(sol.qd[:, 0]), v, rtol=0, atol=TOL_V)
    np.testing.assert_allclose(np.asarray(sol.q[:, 0]), x, rtol=0, atol=TOL_V * 1.0)
    # the stop: the speed's error over the deceleration there, a = μk g (σ v = 0 at the stop)
    tol_t = TOL_V / (P["mu_k"] * G) + ROOT * (1 + t_s)
    t_stop = c.transitions("floor")[0][0]
    assert abs(t_stop - t_s) <= tol_t, (t_stop - t_s, tol_t)
    # d t_s/dσ by jax.grad through the restart: the error of t_s is ∝ step⁵ ∝ σ⁻⁵, so its σ-derivative
    # is 6 tol_t/σ
    if dts is not None:
        tol_g = 6 * tol_t / P["sigma"]
        assert abs(dts - dts_exact) <= tol_g, (dts, dts_exact, tol_g)
        print(f"dt_s/dσ relative error {dts / dts_exact - 1:.2e}")
    # the law's power is integrated with the motion: all of ½ m v0² is dissipated, over x(t_s)
    energy = 0.5 * P["m"] * V0**2
    assert abs(float(c.dissipated_energy[0]) - energy) <= 100 * RTOL * energy
    assert abs(float(c.slip_distance[0]) - x[-1]) <= TOL_V * 1.0
    print(f"{method}: |v − closed form| ≤ {np.max(np.abs(np.asarray(sol.qd[:, 0]) - v)):.2e} m/s, "
          f"t_s error {t_stop - t_s:.2e} s")  # fmt: skip


# --- Stribeck: a high-accuracy reference; a user-written law; a law that fails mid-run ---------------

STRIBECK = block(nh.Stribeck(speed_scale=_p("vs"), damping=_p("sigma")))


class MyStribeck(nh.ContactLaw):
    """Stribeck's law written by a user, reading its values from params. To test the checks along the
    run, it turns NaN below the speed p["v_bad"] (m/s) and falls by p["drop"] N every second."""

    def slip_force(self, speed, N, mu_s, mu_k, q, qd, t, params):
        force = N * (mu_k + (mu_s - mu_k) * jnp.exp(-((speed / params["vs"]) ** 2))) + params["sigma"] * speed
        return jnp.where(speed < params["v_bad"], jnp.nan, force - params["drop"] * t)


USER = block(MyStribeck())
P_STRIBECK = {**P, "sigma": 1.0}


def stribeck_force(v, p=P_STRIBECK):
    N = p["m"] * G
    return N * (p["mu_k"] + (p["mu_s"] - p["mu_k"]) * math.exp(-((v / p["vs"]) ** 2))) + p["sigma"] * v


def reference(event, drop=0.0):
    """scipy's DOP853 at rtol 1e-13 of m v' = −(F(v) − drop t) (y = (x, v)), stopped at the first zero
    of event(t, v)."""

    def stop(t, y):
        return event(t, y[1])

    def rhs(t, y):
        return [y[1], -(stribeck_force(y[1]) - drop * t) / P_STRIBECK["m"]]

    stop.terminal = True  # type: ignore[attr-defined]
    return solve_ivp(rhs, (0.0, 1.0), [0.0, V0], method="DOP853", rtol=1e-13, atol=1e-15, events=stop,
                     dense_output=True)  # fmt: skip


@pytest.fixture(scope="module")
def stribeck_reference():
    """(the stop time t_s, s; v at the report times, m/s) of the reference."""
    ref = reference(lambda t, v: v)
    t_s = float(ref.t_events[0][0])
    v = np.array([ref.sol(t)[1] if t < t_s else 0.0 for t in np.asarray(TS)])
    return t_s, v


_STRIBECK_RUNS: dict = {}


def stribeck_run(method):
    """The shipped Stribeck law's solve (one per method, shared by the tests)."""
    if method not in _STRIBECK_RUNS:
        _STRIBECK_RUNS[method] = throw(STRIBECK, P_STRIBECK, method)
    return _STRIBECK_RUNS[method]


@pytest.mark.parametrize("method", METHODS)
def test_stribeck_block_against_a_reference(method, stribeck_reference):
    t_s, v = stribeck_reference
    sol = stribeck_run(method)
    assert bool(sol.status == nh.STATUS.successful), sol.message
    np.testing.assert_allclose(np.asarray(sol.qd[:, 0]), v, rtol=0, atol=TOL_V)
    # at the stop the force is μs N (the Stribeck term is whole at v = 0): the deceleration μs g
    t_stop = contacts(sol).transitions("floor")[0][0]
    assert abs(t_stop - t_s) <= TOL_V / (P["mu_s"] * G) + ROOT * (1 + t_s), t_stop - t_s
    energy = 0.5 * P["m"] * V0**2
    assert abs(float(contacts(sol).dissipated_energy[0]) - energy) <= 100 * RTOL * energy
    print(f"{method}: |v − reference| ≤ {np.max(np.abs(np.asarray(sol.qd[:, 0]) - v)):.2e} m/s, "
          f"t_s error {t_stop - t_s:.2e} s")  # fmt: skip


def test_a_user_written_law_gives_the_shipped_ones_answer():
    """The same law written two ways ((v/vs)² against the shipped v² vs⁻²): the forces differ by a few
    EPS, which the solve carries along (its step sizes follow the values): 1e3 EPS of each scale."""
    shipped, user = stribeck_run("lagrange"), throw(USER, P_STRIBECK, "lagrange")
    assert bool(user.status == nh.STATUS.successful), user.message
    np.testing.assert_allclose(np.asarray(user.qd), np.asarray(shipped.qd), rtol=0, atol=1e3 * EPS * V0)
    np.testing.assert_allclose(np.asarray(user.q), np.asarray(shipped.q), rtol=0, atol=1e3 * EPS * V0)
    (t_user, kind), (t_shipped, _) = contacts(user).transitions(0)[0], contacts(shipped).transitions(0)[0]
    assert kind == "slip→stick" and abs(t_user - t_shipped) <= 1e3 * EPS
    print(f"user law against shipped: |Δqd| ≤ {np.max(np.abs(np.asarray(user.qd) - np.asarray(shipped.qd))):.1e} m/s, "
          f"Δt_s = {t_user - t_shipped:.1e} s")  # fmt: skip


def test_a_law_that_turns_bad_mid_run_stops_the_solve():
    """The user's law turns NaN below 1 m/s (a failure that depends on the state, not on t), or, falling
    by 20 N/s, negative once F(v) < 20 N/s × t: the solve stops at that instant with
    STATUS.contact_value_invalid, naming the contact and the law, never integrating past it. The
    instants are the reference's, to the speed's error TOL_V carried to the crossing's time (through the
    slopes of the crossing condition in v and t along the motion) plus the root finder's. A law that is
    bad at the start is refused as the initial state's values are."""
    drop = 20.0
    for p, event, rate in (
        ({**P_STRIBECK, "v_bad": 1.0}, lambda t, v: v - 1.0, 0.0),
        ({**P_STRIBECK, "drop": drop}, lambda t, v: stribeck_force(v) - drop * t, drop),
    ):
        sol = throw(USER, p, "lagrange", throw=False)
        c = contacts(sol)
        assert bool(sol.status == nh.STATUS.contact_value_invalid), sol.message
        cause = nh.ContactDiagnostics.STOP_CAUSES[int(c.stop_cause)]
        assert cause == "slip force of the contact law not finite or negative"
        assert "'floor'" in sol.message and "law" in sol.message
        ref = reference(event, rate)
        t_bad = float(ref.t_events[0][0])
        # the crossing's time error: the speed's error times |d event/dv| over |d event/dt| along the motion
        v_bad, h = float(ref.sol(t_bad)[1]), 1e-6
        slope_v = (event(t_bad, v_bad + h) - event(t_bad, v_bad - h)) / (2 * h)
        accel = -(stribeck_force(v_bad) - rate * t_bad) / P_STRIBECK["m"]
        tol = TOL_V * abs(slope_v) / abs(slope_v * accel - rate) + ROOT * (1 + t_bad)
        assert abs(float(c.stopped_at) - t_bad) <= tol, (float(c.stopped_at) - t_bad, tol)
        print(f"stopped {float(c.stopped_at) - t_bad:.2e} s from the reference's instant (allowed {tol:.1e} s)")
        before = np.asarray(TS) < t_bad
        qd = np.asarray(sol.qd[:, 0])
        assert np.all(np.isfinite(qd[before])) and np.all(np.isnan(qd[~before]))
    bad_start = throw(USER, {**P_STRIBECK, "v_bad": 2 * V0}, "lagrange", throw=False)
    assert bool(bad_start.status == nh.STATUS.friction_values_invalid), bad_start.message
    with pytest.raises(nh.SimulationError, match="law"):
        throw(USER, {**P_STRIBECK, "v_bad": 1.0}, "lagrange")


# --- the default, and what is refused ---------------------------------------------------------------


def test_the_default_law_is_coulombs_and_unchanged():
    """`law=Coulomb()` is the default: the same contact (so the same compiled program), and results
    equal bit for bit. The block's Coulomb motion is linear in t (integrated exactly by any Runge–Kutta
    method), stopping at V0/(μk g): rounding and the root finder remain (1e3 EPS, as in test_friction)."""
    assert nh.FrictionContact(0, 1.0, 0.5, 0.3, law=nh.Coulomb()) == nh.FrictionContact(0, 1.0, 0.5, 0.3)
    p = {**P, "mu_k": 0.4}  # (stopping at 0.76 s, inside the run)
    default, given = throw(block(), p, "lagrange"), throw(block(nh.Coulomb()), p, "lagrange")
    for a, b in zip(jax.tree_util.tree_leaves(default), jax.tree_util.tree_leaves(given)):
        assert np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    t_s = V0 / (p["mu_k"] * G)
    assert abs(contacts(default).transitions(0)[0][0] - t_s) <= 1e3 * EPS * (1 + t_s)
    v = np.maximum(V0 - p["mu_k"] * G * np.asarray(TS), 0.0)
    np.testing.assert_allclose(np.asarray(default.qd[:, 0]), v, rtol=0, atol=1e3 * EPS * V0)


def test_bad_law_arguments_are_refused_by_name():
    with pytest.raises(ValueError, match=r"Viscous: `damping` must be ≥ 0"):
        nh.Viscous(-1.0)
    with pytest.raises(ValueError, match=r"`damping` must be a finite scalar"):
        nh.Viscous(float("nan"))
    with pytest.raises(TypeError, match=r"`damping` must be a number or a function"):
        nh.Viscous("high")  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match=r"damping=lambda q, qd, t, p: p\['damping'\]"):
        jax.jit(lambda s: nh.Viscous(s))(1.0)
    with pytest.raises(ValueError, match=r"Stribeck: `speed_scale` must be > 0"):
        nh.Stribeck(0.0)
    with pytest.raises(ValueError, match=r"Stribeck: `exponent` must be ≥ 1.*exponent=1"):
        nh.Stribeck(0.1, exponent=0.5)
    with pytest.raises(ValueError, match=r"Stribeck: `damping` must be ≥ 0"):
        nh.Stribeck(0.1, damping=-2.0)
    with pytest.raises(TypeError, match="abstract"):
        nh.ContactLaw()  # type: ignore[abstract]
    with pytest.raises(TypeError, match=r"`law` must be an instance.*law=Viscous\(\.\.\.\)"):
        nh.FrictionContact(0, 1.0, 0.5, 0.3, law=nh.Viscous)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"`law` must be a jaxnh.ContactLaw"):
        nh.FrictionContact(0, 1.0, 0.5, 0.3, law="viscous")  # type: ignore[arg-type]

    class Table(nh.ContactLaw):
        mu: np.ndarray

        def slip_force(self, speed, N, mu_s, mu_k, q, qd, t, params):
            return N * jnp.interp(speed, jnp.arange(3.0), self.mu)

    with pytest.raises(TypeError, match="not hashable.*params"):
        nh.FrictionContact(0, 1.0, 0.5, 0.3, law=Table(np.array([0.3, 0.2, 0.1])))

    class Vector(nh.ContactLaw):
        def slip_force(self, speed, N, mu_s, mu_k, q, qd, t, params):
            return jnp.stack([mu_k * N, mu_k * N])

    # (checked when simulate traces the mechanism, before anything is compiled)
    with pytest.raises(ValueError, match=r"contacts\[0\].law \(Vector\).slip_force must return a scalar"):
        throw(block(Vector()), P, "lagrange")
