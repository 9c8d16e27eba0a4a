"""`fit` and `experiment` for a mechanism written in speeds (issue 44).

* The ball on a turntable (`jaxnh.models.turntable`: coordinates x, y and a unit quaternion,
  speeds ẋ, ẏ and the space angular velocity ω) observed by its centre, its orientation and a
  gyro's ω: a fit to a synthetic record (jaxnh's own simulation plus seeded Gaussian noise)
  lands within 4 of its own standard errors of the truth, for every unknown, the initial
  orientation's rotation vector included; on the noise-free record it recovers k² and a to a
  relative 1e2·rtol; the experiment's information is finite and positive definite, and its
  predicted standard errors are the fit's.
* The Chaplygin sleigh pushed by a thrust, once in q̇ (no `kinematics`) and once in the speeds
  u = M q̇ (the velocity in axes turned by a fixed angle, and θ̇): the two fits of one record, and
  the two experiments, agree.

Compiled functions are shared between tests through module-scoped fixtures.
"""

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.identify import experiment, predict, Record
from jaxnh.identify.problem import rotation_quaternion
from jaxnh.models import turntable
from jaxnh.rigid import quat_multiply, quaternion_from_axis_angle


CALIBRATION = 4.0  # |θ̂ − θ| ≤ 4 σ̂ for every unknown: fails by chance with probability 6e-5 each
RTOL = 1e-10  # the fits' ODE tolerance; the records are simulated at 1e-12

# --- the ball on a turntable ------------------------------------------------------------------

SPEEDS = ("vx", "vy", "wx", "wy", "wz")  # m/s, m/s, rad/s (space axes)
OBSERVE = ("x", "y", "e0", "e1", "e2", "e3", "wx", "wy", "wz")
NOISE = {"x": 1e-3, "y": 1e-3, "e0": 1e-3, "e1": 1e-3, "e2": 1e-3, "e3": 1e-3, "wx": 1e-2, "wy": 1e-2, "wz": 1e-2}
FREE = ("k2", "a")


@pytest.fixture(scope="module")
def ball():
    """The mechanism, true params, the true initial state, the times and the noise-free channels."""
    p = turntable.default_params()
    mech = turntable.mechanism()
    q0, u0 = turntable.initial_state(p, x=0.5, y=0.0, vx=0.0, vy=0.2, spin=1.0)
    ts = jnp.linspace(0.0, 10.0, 201)
    sol = nh.simulate(mech, p, q0, u0, ts, rtol=1e-12, atol=1e-14)
    assert sol.message == "success"
    channels = np.concatenate([np.asarray(sol.q), np.asarray(sol.u)], axis=1)
    names = tuple(mech.names or ()) + SPEEDS
    clean = {c: channels[:, names.index(c)] for c in OBSERVE}
    return mech, p, q0, u0, ts, clean


def _record(ball, noise: bool) -> Record:
    _, _, _, _, ts, clean = ball
    rng = np.random.default_rng(44)
    ys = {c: y + (NOISE[c] * rng.standard_normal(y.shape) if noise else 0.0) for c, y in clean.items()}
    return Record(np.asarray(ts), ys, {}, "synthetic ball on a turntable")


def _ball_fit(ball, noise: bool):
    mech, p, *_ = ball
    guess = dict(p, k2=jnp.asarray(0.38), a=jnp.asarray(0.105))
    return nh.fit(
        mech,
        guess,
        _record(ball, noise),
        free=FREE,
        positive=FREE,
        observe=OBSERVE,
        noise=NOISE,
        speed_names=SPEEDS,
        rtol=RTOL,
        atol=1e-12,
    )


@pytest.fixture(scope="module")
def ball_fit(ball):
    return _ball_fit(ball, noise=True)


def _rotation_vector(e_from, e_to) -> np.ndarray:
    """δθ (3,), rad, with e_to = e_from ⊗ exp(δθ/2) (body axes of e_from)."""
    r = np.asarray(quat_multiply(jnp.asarray(e_from) * jnp.array([1.0, -1, -1, -1]), jnp.asarray(e_to)))
    r = -r if r[0] < 0 else r
    s = np.linalg.norm(r[1:])
    return np.zeros(3) if s == 0 else 2.0 * math.atan2(s, r[0]) * r[1:] / s


def test_rotation_quaternion_is_the_exponential_and_smooth_at_zero():
    w = jnp.array([0.3, -0.2, 0.5])
    angle = float(jnp.linalg.norm(w))
    np.testing.assert_allclose(rotation_quaternion(w), quaternion_from_axis_angle(w / angle, angle), atol=1e-15)
    tiny = jnp.array([1e-5, 2e-5, -3e-5])  # below SMALL_ROTATION2: the series
    np.testing.assert_allclose(
        rotation_quaternion(tiny),
        quaternion_from_axis_angle(tiny / jnp.linalg.norm(tiny), jnp.linalg.norm(tiny)),
        atol=1e-17,
    )
    J = jax.jacfwd(rotation_quaternion)(jnp.zeros(3))
    np.testing.assert_array_equal(J, 0.5 * np.vstack([np.zeros(3), np.eye(3)]))
    H = jax.hessian(lambda v: rotation_quaternion(v)[0])(jnp.zeros(3))
    np.testing.assert_allclose(H, -0.25 * np.eye(3), atol=1e-15)


@pytest.mark.slow
def test_fit_in_speeds_lands_within_its_interval(ball, ball_fit):
    """Every unknown within CALIBRATION standard errors of the truth; s² ≈ 1; the fitted
    orientation is a unit quaternion."""
    mech, p, q0, u0, ts, _ = ball
    res = ball_fit
    assert res.converged and res.identifiable, res.summary()
    assert res.labels[2:] == (
        "x(t0)", "y(t0)", "rot_x[e0..e3](t0)", "rot_y[e0..e3](t0)", "rot_z[e0..e3](t0)",
        "vx(t0)", "vy(t0)", "wz(t0)",
    )  # fmt: skip
    assert 0.8 < res.chi2_dof < 1.2
    # the rotation's truth: from the nominal orientation (the first sample, normalised) to the true one
    e_nom = np.asarray(res.problem.q0_fixed)[2:6]
    truth = {"k2": 0.4, "a": 0.1, "x(t0)": 0.5, "y(t0)": 0.0, "vx(t0)": 0.0, "vy(t0)": 0.2, "wz(t0)": 1.0}
    truth.update(zip(res.labels[4:7], _rotation_vector(e_nom, q0[2:])))
    for label, value, std in zip(res.labels, res.values, res.std):
        assert abs(value - truth[label]) <= CALIBRATION * std, (label, value, std, truth[label])
    assert abs(np.linalg.norm(res.q0[2:]) - 1.0) < 1e-14
    assert res.qd0.shape == (5,) and res.q0.shape == (6,)
    # the fitted initial speeds roll: the constraints hold at t0
    np.testing.assert_allclose(turntable.constraint(res.q0, res.qd0, 0.0, res.params), 0.0, atol=1e-13)


@pytest.mark.slow
def test_fit_in_speeds_recovers_the_truth_without_noise(ball):
    """Noise-free record: k² and a to a relative 1e2·rtol (the record and the fit's solves differ by
    the integrator's error, of order rtol relative to the motion, amplified by the conditioning;
    measured 1.0e-10 and 6.0e-11 relative, initial coordinates 2.4e-10, speeds 1.6e-9)."""
    res = _ball_fit(ball, noise=False)
    assert res.converged, res.summary()
    for name, true in (("k2", 0.4), ("a", 0.1)):
        assert abs(res.estimates[name]["value"] - true) <= 1e2 * RTOL * true, (name, res.estimates[name])
    np.testing.assert_allclose(res.q0, np.asarray(ball[2]), atol=1e2 * RTOL)
    np.testing.assert_allclose(res.qd0, np.asarray(ball[3]), atol=1e2 * RTOL)


@pytest.mark.slow
def test_experiment_in_speeds_is_positive_definite_and_predicts_the_fit(ball, ball_fit):
    mech, p, q0, u0, ts, _ = ball
    exp = experiment(
        mech, p, ts, free=FREE, positive=FREE, observe=OBSERVE, noise=NOISE, q0=q0, qd0=u0, speed_names=SPEEDS,
        rtol=RTOL, atol=1e-12,
    )  # fmt: skip
    pred = predict(exp)
    F = np.asarray(pred.fisher)
    assert F.shape == (10, 10) and np.all(np.isfinite(F))
    assert np.min(np.linalg.eigvalsh(F)) > 0
    assert pred.labels == ball_fit.labels
    # the predicted standard errors of k² and a are the fit's (up to its s² and the noise realisation)
    for i in range(2):
        assert abs(pred.std[i] / ball_fit.std[i] - 1.0) < 0.1, (pred.labels[i], pred.std[i], ball_fit.std[i])


def test_observe_names_speeds_and_refuses_others(ball):
    mech, p, q0, u0, *_ = ball
    rec = _record(ball, noise=True)
    with pytest.raises(ValueError, match="speeds"):
        nh.fit(mech, p, rec, free=FREE, observe=("x", "omega"), noise=NOISE, speed_names=SPEEDS)
    with pytest.raises(ValueError, match="speed_names"):
        nh.fit(mech, p, rec, free=FREE, observe=("x",), noise=NOISE, qd0=u0, speed_names=("vx", "vy"))
    with pytest.raises(ValueError, match="more than one channel"):
        nh.fit(mech, p, rec, free=FREE, observe=("x",), noise=NOISE, speed_names=("x", "vy", "wx", "wy", "wz"))


# --- the same mechanism in q̇ and in speeds ----------------------------------------------------

ALPHA = 0.6  # rad: the speeds are the velocity in axes turned by ALPHA, and θ̇
M = np.array([[math.cos(ALPHA), math.sin(ALPHA), 0.0], [-math.sin(ALPHA), math.cos(ALPHA), 0.0], [0.0, 0.0, 1.0]])
CART_FREE = ("m", "I_C", "a")
CART_NOISE = {"x": 2e-3, "y": 2e-3, "theta": 5e-3, "theta'": 2e-2, "omega": 2e-2}


def _T(q, qd, t, p):
    th = q[2]
    vx = qd[0] - p["a"] * jnp.sin(th) * qd[2]
    vy = qd[1] + p["a"] * jnp.cos(th) * qd[2]
    return 0.5 * p["m"] * (vx**2 + vy**2) + 0.5 * p["I_C"] * qd[2] ** 2


def _blade(q, qd, t, p):
    return jnp.stack([-jnp.sin(q[2]) * qd[0] + jnp.cos(q[2]) * qd[1]])


def _thrust(q, qd, t, p):
    F = p["F0"] + p["F1"] * jnp.sin(1.5 * t)
    return jnp.stack([F * jnp.cos(q[2]), F * jnp.sin(q[2]), jnp.zeros_like(F)])


def _qdot(q, u, t, p):
    return jnp.asarray(M.T) @ u


CART_QD = nh.Mechanism(_T, constraints=_blade, forces=_thrust, names=("x", "y", "theta"))
CART_U = nh.Mechanism(
    lambda q, u, t, p: _T(q, _qdot(q, u, t, p), t, p),
    constraints=lambda q, u, t, p: _blade(q, _qdot(q, u, t, p), t, p),
    forces=lambda q, u, t, p: jnp.asarray(M) @ _thrust(q, _qdot(q, u, t, p), t, p),  # power Q·q̇ = (M Q)·u
    kinematics=_qdot,
    names=("x", "y", "theta"),
)
CART_SPEEDS = ("ua", "ub", "omega")
TRUTH = {"m": jnp.asarray(2.0), "I_C": jnp.asarray(0.15), "a": jnp.asarray(0.3), "F0": jnp.asarray(1.0),
         "F1": jnp.asarray(2.0)}  # fmt: skip
QD0 = np.array([0.5, 0.0, 0.8])


@pytest.fixture(scope="module")
def cart_record():
    ts = jnp.linspace(0.0, 3.0, 121)
    sol = nh.simulate(CART_QD, TRUTH, jnp.zeros(3), jnp.asarray(QD0), ts, rtol=1e-12, atol=1e-14)
    rng = np.random.default_rng(7)
    ys = {c: np.asarray(sol.q[:, i]) for i, c in enumerate(("x", "y", "theta"))}
    ys["theta'"] = np.asarray(sol.qd[:, 2])
    ys = {c: y + CART_NOISE[c] * rng.standard_normal(y.shape) for c, y in ys.items()}
    ys["omega"] = ys["theta'"]  # the same gyro, named as the speed of the mechanism in speeds
    return Record(np.asarray(ts), ys, {}, "synthetic cart")


def _cart_fits(record):
    guess = dict(TRUTH, m=jnp.asarray(1.8), I_C=jnp.asarray(0.13), a=jnp.asarray(0.28))
    kw: dict[str, Any] = dict(free=CART_FREE, positive=CART_FREE, noise=CART_NOISE, rtol=RTOL, atol=1e-12)
    a = nh.fit(CART_QD, guess, record, observe=("x", "y", "theta", "theta'"), **kw)
    b = nh.fit(CART_U, guess, record, observe=("x", "y", "theta", "omega"), speed_names=CART_SPEEDS, **kw)
    return a, b


@pytest.mark.extended
def test_fit_in_speeds_agrees_with_the_fit_in_qdot(cart_record):
    """One record, one mechanism written twice: the parameters agree to 0.1 of their standard errors
    (each fit stops within GN_STOP_TOL = 0.05 standard errors of its minimum), their standard errors
    to 2 % (each is evaluated where its fit stopped: measured 1e-2 standard errors apart, which moved
    I_C's standard error, 6.5 % of its value, by 0.4 %); the initial speeds are M q̇0."""
    a, b = _cart_fits(cart_record)
    assert a.converged and b.converged
    for i, name in enumerate(CART_FREE):
        assert abs(a.values[i] - b.values[i]) <= 0.1 * a.std[i], (name, a.values[i], b.values[i], a.std[i])
        assert abs(b.std[i] / a.std[i] - 1.0) < 2e-2, (name, a.std[i], b.std[i])
        assert abs(a.values[i] - float(TRUTH[name])) <= CALIBRATION * a.std[i]
    np.testing.assert_allclose(b.qd0, M @ a.qd0, atol=0.1 * float(np.max(b.std[6:])))
    assert a.labels[3:6] == ("x(t0)", "y(t0)", "theta(t0)") == b.labels[3:6]


@pytest.mark.extended
def test_experiment_in_speeds_agrees_with_the_experiment_in_qdot():
    """The same design, twice: the predicted standard errors of the parameters agree to 1e-8
    relative (both at the nominal motion; they differ by the integrators' errors at rtol 1e-10:
    measured 1.4e-11)."""
    ts = np.linspace(0.0, 3.0, 61)
    kw: dict[str, Any] = dict(free=CART_FREE, positive=CART_FREE, q0=np.zeros(3), rtol=RTOL, atol=1e-12)
    a = predict(experiment(CART_QD, TRUTH, ts, observe=("x", "y", "theta'"), noise=CART_NOISE, qd0=QD0, **kw))
    b = predict(
        experiment(
            CART_U, TRUTH, ts, observe=("x", "y", "omega"), noise=CART_NOISE, qd0=M @ QD0, speed_names=CART_SPEEDS,
            **kw,
        )
    )  # fmt: skip
    for F in (a.fisher, b.fisher):
        assert np.all(np.isfinite(F)) and np.min(np.linalg.eigvalsh(F)) > 0
    np.testing.assert_allclose(b.std[:3], a.std[:3], rtol=1e-8)


@pytest.mark.extended
def test_multiple_shooting_in_speeds_reaches_the_same_fit(ball, ball_fit):
    """Three segments, each starting from all coordinates (a quaternion divided by its norm for the
    solve, its continuity defect holding the raw entries at unit norm) and the independent speeds:
    the polished answer is the single-shooting fit's, to 0.1 of its standard errors (each fit stops
    within GN_STOP_TOL = 0.05 standard errors of the minimum)."""
    mech, p, *_ = ball
    guess = dict(p, k2=jnp.asarray(0.38), a=jnp.asarray(0.105))
    res = nh.fit(
        mech, guess, _record(ball, noise=True), free=FREE, positive=FREE, observe=OBSERVE, noise=NOISE,
        speed_names=SPEEDS, rtol=RTOL, atol=1e-12, shooting=3,
    )  # fmt: skip
    assert res.converged and res.labels == ball_fit.labels
    np.testing.assert_array_less(np.abs(res.values - ball_fit.values), 0.1 * ball_fit.std)
