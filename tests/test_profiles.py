"""Profiles: splines against SciPy, continuity, positivity maps, trainable leaves, transformations."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.interpolate as si

import jaxnh  # noqa: F401  (64-bit mode)
from jaxnh.profiles import Bounded, Constant, CubicSpline, Fourier, PiecewiseLinear, Positive, Sampled, trainable


RNG = np.random.default_rng(0)
KNOTS = np.sort(RNG.uniform(0.0, 3.0, 8))
VALUES = RNG.normal(size=8)
T_IN = np.linspace(KNOTS[0], KNOTS[-1], 97)


@eqx.filter_jit
def _ev(profile, ts, d):
    f = (profile, profile.derivative, jax.grad(jax.grad(profile)))[d]
    return jax.vmap(f)(ts)


def ev(profile, ts, d=0):
    """The profile (d = 0) or its d-th time derivative at the times ts (compiled once per kind)."""
    return np.asarray(_ev(profile, jnp.asarray(ts, dtype=jnp.float64), d))


def test_cubic_spline_equals_scipy_natural_spline():
    ref = si.CubicSpline(KNOTS, VALUES, bc_type="natural")
    s = CubicSpline(KNOTS, VALUES)
    for d in (0, 1, 2):
        # values O(1): rounding of a few operations only
        np.testing.assert_allclose(ev(s, T_IN, d), ref(T_IN, d), rtol=0, atol=1e-11 * 10**d)


def test_cubic_spline_is_c2_at_knots_and_linear_outside():
    s = CubicSpline(KNOTS, VALUES)
    eps = 1e-9
    for d in (0, 1, 2):
        left, right = ev(s, KNOTS[1:-1] - eps, d), ev(s, KNOTS[1:-1] + eps, d)
        # a jump would be O(1–10); continuity leaves |third derivative| (< 1e3 here) × 2 eps ≲ 2e-6
        np.testing.assert_allclose(left, right, atol=1e-5)
    out = np.array([KNOTS[0] - 1.0, KNOTS[0] - 0.3, KNOTS[-1] + 0.2, KNOTS[-1] + 2.0])
    np.testing.assert_allclose(ev(s, out, 2), 0.0, atol=1e-12)
    slope0, slope1 = ev(s, KNOTS[[0, -1]], 1)
    np.testing.assert_allclose(ev(s, out[:2]), VALUES[0] + slope0 * (out[:2] - KNOTS[0]), atol=1e-12)
    np.testing.assert_allclose(ev(s, out[2:]), VALUES[-1] + slope1 * (out[2:] - KNOTS[-1]), atol=1e-12)


def test_cubic_spline_reproduces_straight_lines_and_is_linear_in_values():
    line = CubicSpline(KNOTS, 0.7 - 1.3 * KNOTS)
    ts = np.linspace(-1.0, 4.0, 41)
    np.testing.assert_allclose(ev(line, ts), 0.7 - 1.3 * ts, atol=1e-12)
    a, b = RNG.normal(size=8), RNG.normal(size=8)
    np.testing.assert_allclose(
        ev(CubicSpline(KNOTS, 2 * a - b), ts),
        2 * ev(CubicSpline(KNOTS, a), ts) - ev(CubicSpline(KNOTS, b), ts),
        atol=1e-12,
    )


def test_piecewise_linear_and_sampled():
    pl = PiecewiseLinear(KNOTS, VALUES)
    ts = np.linspace(-0.5, 3.5, 81)
    np.testing.assert_allclose(ev(pl, ts), np.interp(ts, KNOTS, VALUES), atol=1e-13)
    inner = T_IN[1:-1]
    i = np.searchsorted(KNOTS, inner, side="right") - 1
    np.testing.assert_allclose(ev(pl, inner, 1), np.diff(VALUES)[i] / np.diff(KNOTS)[i], rtol=1e-12)
    # Sampled: the same natural spline, prepared once with NumPy; or straight lines
    np.testing.assert_allclose(ev(Sampled(KNOTS, VALUES), ts), ev(CubicSpline(KNOTS, VALUES), ts), atol=1e-12)
    np.testing.assert_allclose(ev(Sampled(KNOTS, VALUES, kind="linear"), ts), ev(pl, ts), atol=1e-13)


def test_constant_and_fourier_derivatives():
    f = Fourier(0.3, cos=[0.2, -0.1], sin=[0.5], period=2.0)
    ts = np.linspace(0, 4, 33)
    w = np.pi
    ref = 0.3 + 0.2 * np.cos(w * ts) - 0.1 * np.cos(2 * w * ts) + 0.5 * np.sin(w * ts)
    dref = -0.2 * w * np.sin(w * ts) + 0.2 * w * np.sin(2 * w * ts) + 0.5 * w * np.cos(w * ts)
    np.testing.assert_allclose(ev(f, ts), ref, atol=1e-13)
    np.testing.assert_allclose(ev(f, ts, 1), dref, atol=1e-12)
    np.testing.assert_allclose(ev(Constant(2.5), ts), 2.5)
    np.testing.assert_allclose(ev(Constant(2.5), ts, 1), 0.0)


def test_positive_and_bounded_keep_their_range():
    wild = CubicSpline([0.0, 1.0, 2.0], [-60.0, 0.0, 50.0])
    ts = np.linspace(-1, 3, 50)
    p = ev(Positive(wild, scale=0.02), ts)
    assert np.all(p >= 0) and np.all(np.isfinite(p))
    b = ev(Bounded(wild, 0.5, 2.0), ts)
    assert np.all((b >= 0.5) & (b <= 2.0))
    # Positive.of equals the profile at its knots; Bounded.inverse inverts the map
    s = CubicSpline(KNOTS, 1.0 + np.abs(VALUES))
    np.testing.assert_allclose(ev(Positive.of(s), KNOTS), 1.0 + np.abs(VALUES), rtol=1e-13)
    x = Bounded.inverse(1.7, 0.5, 2.0)
    np.testing.assert_allclose(Bounded(Constant(x), 0.5, 2.0)(0.0), 1.7, rtol=1e-14)


def test_trainable_marks_values_not_knots_or_period():
    s = CubicSpline(KNOTS, VALUES)
    m = trainable(
        {"J": jnp.ones(()), "U": s, "F": Fourier(1.0, sin=[0.1], period=2.0), "P": Positive.of(Constant(3.0))}
    )
    assert m["J"] is True
    assert m["U"].values is True and m["U"].knots is False
    assert m["F"].mean and m["F"].sin and m["F"].cos and m["F"].period is False
    assert m["P"].inner.value is True and m["P"].scale is False
    assert jax.tree_util.tree_leaves(trainable(Sampled(KNOTS, VALUES))) == [False, False, False]


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="knots must be finite and strictly increasing"):
        CubicSpline([0.0, 2.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="values must have the shape of knots"):
        PiecewiseLinear([0.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="at least 2"):
        CubicSpline([0.0], [1.0])
    with pytest.raises(ValueError, match="must be finite"):
        Sampled([0.0, 1.0, 2.0], [0.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="kind"):
        Sampled([0.0, 1.0], [0.0, 1.0], kind="spline")
    with pytest.raises(ValueError, match="must be > 0"):
        Positive.of(CubicSpline([0.0, 1.0], [1.0, -1.0]))
    with pytest.raises(TypeError, match="inner must be a jaxnh Profile"):
        Bounded(lambda t: t, 0.0, 1.0)  # pyright: ignore[reportArgumentType]  (wrong on purpose)


def test_jit_vmap_grad_through_a_spline():
    ts = jnp.linspace(0.0, 3.0, 31)

    def mean_square(values):
        s = CubicSpline(KNOTS, values)
        return jnp.mean(jax.vmap(s)(ts) ** 2)

    v = jnp.asarray(VALUES)
    g = jax.jit(jax.grad(mean_square))(v)
    # the spline is linear in its values: grad = 2/n Bᵀ B v, with B its basis matrix
    B = np.stack([ev(CubicSpline(KNOTS, e), ts) for e in np.eye(8)], axis=1)
    np.testing.assert_allclose(g, 2 / ts.size * B.T @ (B @ VALUES), rtol=1e-10)
    batch = jnp.stack([v, 2 * v, -v])

    @jax.jit
    def batched(batch):
        out = jax.vmap(lambda vals: CubicSpline(KNOTS, vals)(1.234))(batch)
        # a vmapped batch of splines (the knots batched too), as eqx modules
        splines = eqx.filter_vmap(lambda vals: CubicSpline(KNOTS, vals))(batch)
        return out, eqx.filter_vmap(lambda s: s(1.234))(splines)

    out, out2 = batched(batch)
    np.testing.assert_allclose(out, np.array([1, 2, -1]) * ev(CubicSpline(KNOTS, v), [1.234])[0], rtol=1e-12)
    np.testing.assert_allclose(out2, out, rtol=1e-14)


def test_smooth_step_and_declared_breakpoints():
    """SmoothStep against its closed form; breakpoints declared by kinked and steep profiles,
    through wrappers and nested params; none from smooth ones."""
    from jaxnh._model.profiles import declared_breakpoints, SmoothStep

    s = SmoothStep(1.0, 3.0, 2.0, 0.1)
    for t in (0.0, 1.9, 2.0, 2.05, 5.0):
        assert float(s(t)) == pytest.approx(1.0 + 2.0 * 0.5 * (1 + np.tanh((t - 2.0) / 0.1)), rel=1e-15)
    assert float(s.derivative(2.0)) == pytest.approx(2.0 * 0.5 / 0.1, rel=1e-12)
    np.testing.assert_allclose(np.asarray(s.breakpoints()), [1.7, 2.0, 2.3], rtol=1e-15)
    with pytest.raises(ValueError, match="width"):
        SmoothStep(1.0, 2.0, 0.0, 0.0)
    lin = PiecewiseLinear([0.0, 1.0, 4.0], [1.0, 2.0, 0.5])
    params = {"a": 1.0, "laws": [Positive.of(lin), CubicSpline([0.0, 1.0, 2.0], [1.0, 2.0, 1.0])], "s": s}
    np.testing.assert_allclose(np.asarray(declared_breakpoints(params)), [0.0, 1.0, 1.7, 2.0, 2.3, 4.0])
    assert declared_breakpoints({"a": Constant(1.0), "b": Sampled([0.0, 1.0, 2.0], [0.0, 1.0, 0.0])}) is None
    assert Sampled([0.0, 1.0, 2.0], [0.0, 1.0, 0.0], kind="linear").breakpoints() is not None


def test_step_ts_with_own_controllers():
    """Declared breakpoints and step_ts wrap an own PIDController; step_ts with a controller that
    cannot take them is refused naming step_ts."""
    import diffrax

    from jaxnh.profiles import SmoothStep

    def T(q, qd, t, p):
        return 0.5 * qd[0] ** 2

    def Q(q, qd, t, p):
        return jnp.stack([p["F"].derivative(t)])

    mech = jaxnh.Mechanism(T, forces=Q)
    p = {"F": SmoothStep(0.0, 1.0, 43.21, 1e-8)}  # force = its rate: a unit impulse 10 ns wide at 43.21 s
    ts = jnp.linspace(0.0, 100.0, 3)
    pid = diffrax.PIDController(rtol=1e-9, atol=1e-12)
    for ctrl in (None, pid):
        sol = jaxnh.simulate(mech, p, jnp.zeros(1), jnp.zeros(1), ts, stepsize_controller=ctrl)
        # the unit impulse sets qd = 1 (the smoothing cancels by symmetry): q(100) = 100 − 43.21; the
        # same pulse written by hand (no breakpoints) falls between the stages: q(100) came out 0
        assert float(sol.q[-1, 0]) == pytest.approx(56.79, rel=1e-6)
    with pytest.raises(ValueError, match="step_ts"):
        jaxnh.simulate(
            mech, p, jnp.zeros(1), jnp.zeros(1), ts, stepsize_controller=diffrax.ConstantStepSize(), step_ts=[0.5]
        )
