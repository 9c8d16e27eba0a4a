"""simulate is transform-native: the default method under jit, vmap and grad with no hints;
checks in the graph give the same status eagerly and under jit/vmap; Appell's partition is
chosen and re-chosen inside the program; events, dense output and `ode` pass diffrax through."""

import re
from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxnh as nh
from jaxnh.models import knife_edge as K


# --- the README variator -------------------------------------------------------------------


def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def U21(t):
    return 1.0 + 0.4 * jnp.sin(jnp.pi * t)


def rolling(q, qd, t, p):
    return jnp.stack([U21(t) * qd[0] - qd[1]])


def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


MECH = nh.Mechanism(T, constraints=rolling, forces=torques, names=("phi1", "phi2"))
P = {"J1": 0.02, "J2": 0.05, "M1": 0.3, "M2": -0.1}
TS = jnp.linspace(0.0, 3.0, 31)
QD0 = jnp.array([2.0, 2.0])


def final_angle(p, **kw):
    return nh.simulate(MECH, p, jnp.zeros(2), QD0, TS, **kw).q[-1, 0]


@pytest.mark.slow
def test_readme_example_under_jit_vmap_grad_without_hints():
    eager = final_angle(P)
    np.testing.assert_allclose(jax.jit(final_angle)(P), eager, rtol=1e-12, atol=0)
    J2s = jnp.array([0.04, 0.05, 0.06])
    batched = jax.vmap(lambda j: final_angle({**P, "J2": j}))(J2s)
    loop = jnp.stack([final_angle({**P, "J2": j}) for j in J2s])
    np.testing.assert_allclose(batched, loop, rtol=1e-12, atol=0)
    g = jax.grad(lambda j: final_angle({**P, "J2": j}))(0.05)
    # central differences of rtol-1e-12 solves, h = 1e-5: truncation (h/J2)² ≈ 4e-8 relative,
    # solver noise ≈ 1e-12·|phi1|/h ≈ 1e-6 rad/(kg·m²) against |g| ≈ 160; the gradient itself
    # (rtol 1e-8, sensitivities error-controlled) is good to ≈ 1e-7 relative
    fine = jax.jit(lambda j: final_angle({**P, "J2": j}, rtol=1e-12, atol=1e-14))
    h = 1e-5
    fd = (fine(0.05 + h) - fine(0.05 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


# --- the partition of Appell's velocities through a singular block ----------------------


def cos_ratio(q, qd, t, p):
    return jnp.stack([1.5 * jnp.cos(t) * qd[0] - qd[1]])


COS = nh.Mechanism(
    lambda q, qd, t, p: 0.5 * (0.02 * qd[0] ** 2 + 0.05 * qd[1] ** 2),
    constraints=cos_ratio,
    forces=lambda q, qd, t, p: jnp.stack([0.1, 0.0 * q[0]]),
)


@pytest.fixture(scope="module")
def cos_runs():
    ts = jnp.array([0.0, 2 * jnp.pi])

    def run(qd0, method):
        return nh.simulate(COS, {}, jnp.zeros(2), qd0, ts, method, rtol=1e-10, atol=1e-12)

    qd0 = jnp.array([[1.0, 1.5], [0.5, 0.75]])
    out: dict[str, Any] = {m: [run(x, m) for x in qd0] for m in ("appell", "lagrange")}
    out["jit"] = jax.jit(lambda x: run(x, "appell").q)(qd0[0])
    out["vmap"] = jax.vmap(lambda x: run(x, "appell").q)(qd0)
    out["fixed"] = nh.simulate(
        COS, {}, jnp.zeros(2), qd0[0], ts, "appell", independent=(1,), throw=False, rtol=1e-10, atol=1e-12
    )
    return out


def test_appell_through_a_singular_block_agrees_with_lagrange(cos_runs):
    """The ratio 1.5 cos t passes through zero at t = π/2 and 3π/2 between the two report
    times: the partition chosen at t = 0 (φ2' dependent) stays valid, but the block of
    φ1' (if it were dependent) goes singular; both halves of the motion must agree with
    Lagrange's multiplier form at rtol 1e-10 to 1e-8."""
    for a, l in zip(cos_runs["appell"], cos_runs["lagrange"]):
        assert a.message == "success"
        np.testing.assert_allclose(a.q, l.q, rtol=0, atol=1e-8)
        np.testing.assert_allclose(a.qd, l.qd, rtol=0, atol=1e-8)
    np.testing.assert_allclose(cos_runs["jit"], cos_runs["lagrange"][0].q, atol=1e-8)
    for i in range(2):
        np.testing.assert_allclose(cos_runs["vmap"][i], cos_runs["lagrange"][i].q, atol=1e-8)


def test_a_fixed_partition_that_goes_singular_fails_clearly(cos_runs):
    sol = cos_runs["fixed"]
    assert sol.status == nh.STATUS.singular_split
    assert "singular" in sol.message


@pytest.mark.slow
def test_knife_edge_through_heading_pi_over_2_with_coarse_report_times():
    """Released spinning, the blade's heading passes π/2, π, 3π/2: whichever of ẋ, ẏ is
    dependent becomes unsolvable somewhere. The partition is re-chosen during the run;
    the motion matches the closed form (Bloch §1.6) and Lagrange's, under vmap too."""
    p, w = K.default_params(), 1.3
    ts = jnp.array([0.0, 1.0, 2.5, 3 * jnp.pi / w])
    mech = K.mechanism()

    def run(omega, method):
        return nh.simulate(mech, p, jnp.zeros(3), jnp.stack([0.0, 0.0, omega]), ts, method, rtol=1e-10, atol=1e-12)

    a, l = run(w, "appell"), run(w, "lagrange")
    q_ref, qd_ref = K.closed_form(p, ts, w)
    np.testing.assert_allclose(a.q, q_ref, atol=1e-8)
    np.testing.assert_allclose(a.qd, qd_ref, atol=1e-8)
    np.testing.assert_allclose(a.q, l.q, atol=1e-8)
    omegas = jnp.array([w, 0.9])
    qv = jax.vmap(lambda o: run(o, "appell").q)(omegas)
    for i, o in enumerate(omegas):
        np.testing.assert_allclose(qv[i], K.closed_form(p, ts, o)[0], atol=1e-8)


# --- every check of the initial state, eagerly and under jit and vmap -------------------


def c_adversarial(q, qd, t, p):
    """Two constraints whose defects are switched on by parameters: a = b = 0 removes the
    velocities from the first (a holonomic constraint in disguise), n ≠ 0 makes it nonlinear,
    s ≠ 0 adds s·√|qd0|, not differentiable at qd0 = 0 (∂c/∂qd infinite there), r = 1 repeats
    it in the second (redundant constraints)."""
    rooted = p["s"] != 0  # (the √ only where switched on: 0·∞ in its derivative at 0 would be NaN)
    root = jnp.where(rooted, p["s"] * jnp.sqrt(jnp.abs(jnp.where(rooted, qd[0], 1.0))), 0.0)
    c1 = p["a"] * qd[0] + p["b"] * qd[1] + p["h"] * (q[0] - q[1]) + p["n"] * qd[0] ** 2 + root
    c2 = p["r"] * (p["a"] * qd[0] + p["b"] * qd[1]) + (1 - p["r"]) * qd[2]
    return jnp.stack([c1, c2])


ADV = nh.Mechanism(lambda q, qd, t, p: 0.5 * jnp.sum(p["m"] * qd**2), constraints=c_adversarial)
GOOD = {"a": 1.0, "b": -1.0, "h": 0.0, "n": 0.0, "r": 0.0, "s": 0.0, "m": jnp.array([1.0, 2.0, 3.0])}
QD_GOOD = jnp.array([1.0, 1.0, 0.0])

CASES = {
    "non_finite_input": ({"m": jnp.array([1.0, jnp.nan, 3.0])}, QD_GOOD, jnp.zeros(3)),
    "mass_matrix_not_positive_definite": ({"m": jnp.array([1.0, -2.0, 3.0])}, QD_GOOD, jnp.zeros(3)),
    "velocity_free_constraint": ({"a": 0.0, "b": 0.0, "h": 1.0}, QD_GOOD, jnp.zeros(3)),
    "constraints_nonlinear": ({"n": 1.0}, jnp.array([1.0, 2.0, 0.0]), jnp.zeros(3)),
    "constraints_not_finite": ({"s": 1.0}, jnp.zeros(3), jnp.zeros(3)),
    "singular_split": ({"r": 1.0}, QD_GOOD, jnp.zeros(3)),
    "inconsistent_velocities": ({}, jnp.array([2e-9, 1e-9, 0.0]), jnp.zeros(3)),
    "successful": ({}, QD_GOOD, jnp.zeros(3)),
}


def _adv(p_change, qd0, q0):
    p = {**GOOD, **p_change}
    return p, q0, qd0


def _solve(p, q0, qd0):
    # Appell's form: it has one check more than Lagrange's (a regular dependent-velocity block)
    return nh.simulate(ADV, p, q0, qd0, jnp.linspace(0.0, 1.0, 3), "appell", throw=False)


@pytest.fixture(scope="module")
def check_outcomes():
    names = list(CASES)
    inputs = [_adv(*CASES[n]) for n in names]
    eager = [_solve(*x) for x in inputs]
    jitted = jax.jit(_solve)
    jit = [jitted(*x) for x in inputs]
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *inputs)
    batch = jax.vmap(_solve)(*stacked)
    return names, inputs, eager, jit, batch


def test_every_check_gives_the_same_status_eagerly_under_jit_and_vmap(check_outcomes):
    names, _, eager, jit, batch = check_outcomes
    messages = batch.messages
    for i, name in enumerate(names):
        expected = getattr(nh.STATUS, name)
        assert eager[i].status == expected, (name, eager[i].message)
        assert jit[i].status == expected, name
        assert int(batch.status._value[i]) == int(expected._value), name
        assert eager[i].message == jit[i].message == messages[i], name
        if name != "successful":
            assert bool(jnp.all(jnp.isnan(eager[i].q))), name  # never a plausible answer
            # and said at once: a zero stand-in state under a zero field ends in a few steps
            assert int(eager[i].stats["num_steps"]) < 50, (name, eager[i].stats)


def test_failed_checks_raise_with_throw_true(check_outcomes):
    names, inputs, *_ = check_outcomes
    for name, (p, q0, qd0) in zip(names, inputs):
        if name == "successful":
            continue
        with pytest.raises(nh.SimulationError, match=re.escape(nh.STATUS[getattr(nh.STATUS, name)][:30])):
            nh.simulate(ADV, p, q0, qd0, jnp.linspace(0.0, 1.0, 3), "appell")


def test_batched_message_counts_outcomes(check_outcomes):
    *_, batch = check_outcomes
    assert batch.message.startswith(f"{len(CASES) - 1} of {len(CASES)} failed")


def test_new_values_of_float_parameters_reuse_the_compiled_program():
    """Python floats in params are data: a loop over J2 traces the user's T once, not per value."""
    traced = []

    def T_counting(q, qd, t, p):
        traced.append(1)
        return T(q, qd, t, p)

    mech = nh.Mechanism(T_counting, constraints=rolling, forces=torques)
    nh.simulate(mech, P, jnp.zeros(2), QD0, TS)
    after_first = len(traced)
    for j2 in (0.06, 0.07):
        nh.simulate(mech, {**P, "J2": j2}, jnp.zeros(2), QD0, TS)
    assert len(traced) == after_first


def test_every_input_closed_over_inside_jit():
    """Inside a caller's jit with every input a constant, simulate gives the eager answer, and an
    invalid input raises from inside the program (no input is traced, but the outputs are)."""
    eager = nh.simulate(MECH, P, jnp.zeros(2), QD0, TS).q[-1]
    inside = jax.jit(lambda x: nh.simulate(MECH, P, jnp.zeros(2), QD0, TS).q[-1] + x)(0.0)
    # the same solve compiled twice (the eager one with jaxnh's XLA options): they differ by
    # rounding, and should a step decision flip by it, by up to the requested rtol (1e-8)
    np.testing.assert_allclose(inside, eager, rtol=1e-8, atol=0)
    bad = jnp.array([2.0, 3.0])  # violates rolling: U21(0) = 1 needs qd[1] = qd[0]
    with pytest.raises(Exception, match="violates the nonholonomic constraints"):
        jax.block_until_ready(jax.jit(lambda x: nh.simulate(MECH, P, jnp.zeros(2), bad, TS).q[-1] + x)(0.0))
    status = jax.jit(lambda: nh.simulate(MECH, P, jnp.zeros(2), bad, TS, throw=False).status)()
    assert status == nh.STATUS.inconsistent_velocities


# --- NaN in, NaN out; a failed solve gives NaN gradients ----------------------------------


def test_nan_parameter_gives_nan_gradient_not_zero():
    g = jax.grad(lambda j: nh.simulate(MECH, {**P, "J1": j}, jnp.zeros(2), QD0, TS, throw=False).q[-1, 0])(jnp.nan)
    assert bool(jnp.isnan(g))


@pytest.mark.slow
def test_failed_solve_gives_nan_gradient_in_reverse_mode():
    def f(j):
        sol = nh.simulate(
            MECH,
            {**P, "J1": j},
            jnp.zeros(2),
            QD0,
            TS,
            throw=False,
            max_steps=3,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
        )
        return jnp.sum(sol.q[:2])

    assert bool(jnp.isnan(jax.grad(f)(0.02)))


# --- events, dense output and ode ----------------------------------------------------------


@pytest.mark.slow
def test_event_time_is_a_root_of_the_dense_output():
    """Stop when phi1 reaches 3 rad; the event time solves phi1(t) = 3 on the dense output."""
    target = 3.0
    event = diffrax.Event(lambda t, y, p, **kw: y[0][0] - target, root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
    sol = nh.simulate(
        MECH,
        P,
        jnp.zeros(2),
        QD0,
        TS,
        event=event,
        rtol=1e-10,
        atol=1e-12,
        saveat=diffrax.SaveAt(ts=TS, t1=True, dense=True),
    )
    # diffrax writes the t1 entry after the last report time reached; the later ones are inf
    t_event = jnp.max(jnp.where(jnp.isfinite(sol.ts), sol.ts, -jnp.inf))
    assert 0.0 < float(t_event) < float(TS[-1]) and bool(sol.event_mask)
    lo, hi = float(t_event) - 0.1, float(t_event) + 0.1
    for _ in range(60):  # bisection on the dense output
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(sol.evaluate(mid)[0][0]) < target else (lo, mid)
    assert abs(float(t_event) - 0.5 * (lo + hi)) < 1e-8
    assert int(jnp.sum(jnp.isfinite(sol.ts))) == int(jnp.sum(TS <= t_event)) + 1


@pytest.mark.slow
def test_event_without_root_finder_gets_one_and_its_time_is_differentiable():
    """An Event given without a root finder (before: located at the end of the crossing step, with
    a time whose gradient was exactly 0) is located by Newton's method on the interpolant: the
    event time t_e solves phi1(t_e) = target, so d t_e / d target = 1 / phi1'(t_e) (the implicit
    function theorem), which the gradient through the solve must give. Tolerance: the solve's rtol
    1e-10 times the few steps that carry an error into phi1'(t_e), with a margin of 100."""

    def event_time(target):
        event = diffrax.Event(lambda t, y, p, **kw: y[0][0] - target)
        sol = nh.simulate(MECH, P, jnp.zeros(2), QD0, TS, event=event, rtol=1e-10, atol=1e-12,
                          saveat=diffrax.SaveAt(t1=True))  # fmt: skip
        return sol.ts[-1], sol.qd[-1][0]

    (t_e, w_e), (dt_e, _) = jax.jvp(event_time, (3.0,), (1.0,))
    assert 0.0 < float(t_e) < float(TS[-1])
    np.testing.assert_allclose(float(dt_e), 1.0 / float(w_e), rtol=1e-8)


def test_ode_with_diffeqsolve_equals_simulate():
    o = nh.ode(MECH, P, jnp.zeros(2), QD0, 0.0)
    sol = diffrax.diffeqsolve(
        o.term,
        o.solver(diffrax.Tsit5()),
        0.0,
        float(TS[-1]),
        None,
        o.y0,
        args=o.args,
        saveat=diffrax.SaveAt(ts=TS),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12, norm=o.error_norm),
    )
    q, qd = jax.vmap(o.unpack)(sol.ys, sol.ts)
    ref = nh.simulate(MECH, P, jnp.zeros(2), QD0, TS, rtol=1e-10, atol=1e-12, solver=diffrax.Tsit5())
    np.testing.assert_allclose(q, ref.q, atol=1e-12)
    np.testing.assert_allclose(qd, ref.qd, atol=1e-12)


# --- holonomic constraints handled by Mechanism ------------------------------------------


def test_holonomic_constraint_in_mechanism():
    """A pendulum of length 1 written in Cartesian (x, y) with g = x² + y² − 1: period of
    small oscillations 2π/√(g/L); the holonomic constraint stays satisfied to the tolerance,
    Appell equals Lagrange."""
    grav = 9.81
    mech = nh.Mechanism(
        lambda q, qd, t, p: 0.5 * jnp.sum(qd**2),
        potential=lambda q, t, p: grav * q[1],
        holonomic=lambda q, t, p: jnp.stack([q[0] ** 2 + q[1] ** 2 - 1.0]),
    )
    th0 = 0.01
    q0 = jnp.array([jnp.sin(th0), -jnp.cos(th0)])
    period = 2 * jnp.pi / jnp.sqrt(grav)
    ts = jnp.linspace(0.0, period, 5)
    a = nh.simulate(mech, {}, q0, jnp.zeros(2), ts, "appell", rtol=1e-10, atol=1e-12)
    l = nh.simulate(mech, {}, q0, jnp.zeros(2), ts, "lagrange", rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.q, l.q, atol=1e-8)
    # small-angle period: the finite amplitude lengthens it by θ0²/16 (relative)
    np.testing.assert_allclose(a.q[-1], q0, atol=2 * th0 * th0**2)
    g = jax.vmap(lambda q: mech.holonomic_residual(q, 0.0, {}))(a.q)
    assert float(jnp.max(jnp.abs(g))) < 1e-8


def test_holonomic_q0_off_the_constraint_is_refused():
    """A bead on a hoop of radius 1 m (g = x² + y² − 1) started 0.1 m off it (g(q0) = 0.21 of a
    scale 2·1.1² + 1 = 3.4): refused with its own status, eagerly, under jit and under vmap;
    a q0 on the hoop to rounding (g ≈ 1e-16) is accepted."""
    mech = nh.Mechanism(
        lambda q, qd, t, p: 0.5 * jnp.sum(qd**2),
        holonomic=lambda q, t, p: jnp.stack([q[0] ** 2 + q[1] ** 2 - 1.0]),
    )
    ts = jnp.linspace(0.0, 1.0, 3)
    off, on = jnp.array([1.1, 0.0]), jnp.array([jnp.cos(0.3), jnp.sin(0.3)])
    qd = jnp.array([0.0, 1.0])
    for method in ("appell", "lagrange"):
        with pytest.raises(nh.InvalidInitialState, match="holonomic constraints"):
            nh.simulate(mech, {}, off, qd, ts, method)
        status = jax.jit(lambda q: nh.simulate(mech, {}, q, qd, ts, method, throw=False).status)
        assert status(off) == nh.STATUS.holonomic_violated
        both = jax.vmap(lambda q: nh.simulate(mech, {}, q, qd, ts, method, throw=False).status)(jnp.stack([off, on]))
        assert bool((both == nh.STATUS.holonomic_violated)[0])
        qd_on = jnp.array([-jnp.sin(0.3), jnp.cos(0.3)])
        assert bool(nh.simulate(mech, {}, on, qd_on, ts, method).success)


def _identity_rule_inputs():
    """A point x, a batch of two points, a tangent, and exact equality of two arrays: for the tests
    of jaxnh's identity primitives, whose results must equal those without them bit for bit."""
    x = jnp.array([0.3, -1.2, 2.0])

    def same(a, b):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    return x, jnp.stack([x, 2.0 * x]), jnp.array([1.0, 0.5, -2.0]), same


def test_forward_only_outputs_keep_forward_mode_and_refuse_reverse_mode():
    """`jaxnh._base.modes.forward_only` (what simulate applies to the outputs of a solve by
    diffrax.ForwardMode()): the identity in value and in every forward-mode derivative, eagerly and
    under jit and vmap, so the results equal those without it exactly; reverse mode through an
    output that carries a cotangent raises its message, eagerly and under jit and vmap; an output
    the loss does not use does not."""
    from jaxnh._base.modes import forward_only

    def plain(x):
        return jnp.sin(2.0 * x) * x[::-1]

    def guarded(x):
        return jnp.sin(2.0 * forward_only(x, "refused: use jax.jacfwd")) * x[::-1]

    x, xs, v, same = _identity_rule_inputs()

    same(guarded(x), plain(x))
    same(jax.jit(guarded)(x), jax.jit(plain)(x))  # (each against its own kind: jit's fusions round apart)
    same(jax.vmap(guarded)(xs), jax.vmap(plain)(xs))
    same(jax.jvp(guarded, (x,), (v,))[1], jax.jvp(plain, (x,), (v,))[1])
    same(jax.jit(jax.jacfwd(guarded))(x), jax.jit(jax.jacfwd(plain))(x))
    same(jax.vmap(jax.jacfwd(guarded))(xs), jax.vmap(jax.jacfwd(plain))(xs))
    same(jax.jacfwd(jax.jacfwd(guarded))(x), jax.jacfwd(jax.jacfwd(plain))(x))

    def loss(y):
        return jnp.sum(guarded(y))

    for call in (
        lambda: jax.grad(loss)(x),
        lambda: jax.jit(jax.grad(loss))(x),
        lambda: jax.vmap(jax.grad(loss))(xs),
        lambda: jax.jacrev(guarded)(x),
        lambda: jax.vjp(guarded, x)[1](v),
    ):
        with pytest.raises(TypeError, match="refused: use jax.jacfwd"):
            call()
    # a loss that does not use the guarded output: its cotangent is zero, nothing to refuse
    g = jax.grad(lambda y: jnp.sum(y**2) + 0.0 * jnp.sum(jax.lax.stop_gradient(forward_only(y, "unused"))))(x)
    same(g, 2 * x)


def test_reverse_once_inputs_keep_first_derivatives_and_refuse_reverse_over_reverse():
    """`jaxnh._base.modes.reverse_once` (what simulate applies to the inputs of a solve by a
    reverse-mode diffrax adjoint, whose backward loop JAX cannot transpose): the identity in value
    and in every first derivative, eagerly and under jit and vmap; forward mode over reverse mode
    (`jax.jacfwd(jax.grad(f))`) gives the exact second derivative; reverse mode over reverse mode
    raises its message, eagerly and under jit and vmap."""
    from jaxnh._base.modes import reverse_once

    def plain(x):
        return jnp.sum(jnp.sin(2.0 * x) * x**2)

    def guarded(x):
        y = reverse_once(x, "refused: use jax.jacfwd(jax.grad(f))")
        return jnp.sum(jnp.sin(2.0 * y) * y**2)

    x, xs, v, same = _identity_rule_inputs()

    same(guarded(x), plain(x))
    same(jax.jit(guarded)(x), jax.jit(plain)(x))
    same(jax.jvp(guarded, (x,), (v,))[1], jax.jvp(plain, (x,), (v,))[1])
    same(jax.grad(guarded)(x), jax.grad(plain)(x))
    same(jax.jit(jax.grad(guarded))(x), jax.jit(jax.grad(plain))(x))
    same(jax.vmap(jax.grad(guarded))(xs), jax.vmap(jax.grad(plain))(xs))
    same(jax.jacfwd(jax.grad(guarded))(x), jax.jacfwd(jax.grad(plain))(x))
    same(jax.jacfwd(jax.jacfwd(guarded))(x), jax.jacfwd(jax.jacfwd(plain))(x))
    for call in (
        lambda: jax.grad(lambda y: jnp.sum(jax.grad(guarded)(y)))(x),
        lambda: jax.jit(jax.jacrev(jax.grad(guarded)))(x),
        lambda: jax.vmap(jax.jacrev(jax.grad(guarded)))(xs),
    ):
        with pytest.raises(TypeError, match=r"refused: use jax\.jacfwd"):
            call()
