"""Defaults chosen by measurement (issue 4): the solver per tolerance, the unrolled
Tsit5, the automatic derivative mode (forward sensitivities), the small pivoted
solve and the remembered shape checks."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh._solve.sensitivity import choose_adjoint, FORWARD_MAX_PARAMETERS, ForwardSensitivity
from jaxnh._solve.simulate import (
    default_solver,
    DOP853_BELOW_RTOL,
    DOPRI8_BELOW_RTOL_LOOPED,
    UNROLL_MAX_OPERATIONS,
    vector_field_operations,
)
from jaxnh.linalg import solve_square
from jaxnh.models import variator as V
from jaxnh.solvers import UnrolledTsit5 as Tsit5


MECH = V.mechanism()
P = V.default_params()
TS = jnp.linspace(0.0, 2.0, 21)
Q0 = jnp.zeros(2)


def qd0(p, w=1.0):
    return jnp.stack([w, w * p.U21(0.0)])


def test_default_solver_by_tolerance_and_size():
    loose, tight = 10 * DOP853_BELOW_RTOL, DOP853_BELOW_RTOL / 10
    assert isinstance(default_solver(loose, method="appell"), Tsit5)
    assert isinstance(default_solver(loose, UNROLL_MAX_OPERATIONS, "appell"), Tsit5)
    assert isinstance(default_solver(tight, method="appell"), diffrax.Dopri8)
    assert isinstance(default_solver(tight, 10**5, "appell"), diffrax.Dopri8)
    # small fields: the same choice in every form
    for method in ("lagrange", "appell", "substituted"):
        assert isinstance(default_solver(loose, 10, method), Tsit5)
        assert isinstance(default_solver(tight, 10, method), diffrax.Dopri8)
    # large vector fields: diffrax's looped Tsit5 only at loose tolerances, Dopri8 below
    looser, mid = 10 * DOPRI8_BELOW_RTOL_LOOPED, DOPRI8_BELOW_RTOL_LOOPED / 10
    assert DOPRI8_BELOW_RTOL_LOOPED > DOP853_BELOW_RTOL
    for method in ("lagrange", "appell"):
        assert isinstance(default_solver(looser, UNROLL_MAX_OPERATIONS + 1, method), diffrax.Tsit5)
        assert isinstance(default_solver(mid, UNROLL_MAX_OPERATIONS + 1, method), diffrax.Dopri8)
    assert isinstance(default_solver(mid, method="appell"), Tsit5)


def test_vector_field_size_is_counted_under_jit():
    """The variator's Appell vector field is small (unrolled solver); counting works on traced
    values too, so the choice is the same under jit."""
    form = nh.equations.formulation(MECH, "appell", Q0, qd0(P), 0.0, P, (0,))
    y0 = form.state(Q0, qd0(P), 0.0, P)
    n = vector_field_operations(form, 0.0, y0, P)
    assert 20 < n <= UNROLL_MAX_OPERATIONS
    assert jax.jit(lambda p: jnp.asarray(vector_field_operations(form, 0.0, y0, p)))(P) == n


def test_default_solver_is_chosen_inside_the_compiled_program():
    """solver=None is resolved while tracing (no Python work per call): under jit the
    result equals the eager one, and the unrolled Tsit5 is what the variator gets."""
    f = lambda p: nh.simulate(MECH, p, Q0, qd0(p), TS, rtol=1e-6, atol=1e-8).q  # noqa: E731
    np.testing.assert_array_equal(jax.jit(f)(P), f(P))
    form = nh.equations.formulation(MECH, "appell", Q0, qd0(P), 0.0, P)
    n = vector_field_operations(form, 0.0, form.state(Q0, qd0(P), 0.0, P), P)
    assert isinstance(default_solver(1e-6, n, "appell"), Tsit5)


@pytest.mark.parametrize("rtol", [1e-6, 1e-11])
def test_default_solve_matches_closed_form(rtol):
    sol = nh.simulate(MECH, P, Q0, qd0(P), TS, rtol=rtol, atol=rtol / 100)
    q_ref, qd_ref = V.closed_form(P, TS, w0=1.0)
    assert np.max(np.abs(sol.q - q_ref)) < 2e3 * rtol
    assert int(sol.stats["rhs_evaluations"]) > 0


def test_unrolled_tsit5_takes_diffrax_tsit5_steps():
    def vf(t, y, a):
        w = 1.0 + 0.5 * t
        return {"x": -w * y["v"], "v": w * y["x"] + 0.1 * jnp.sin(y["x"])}

    y0 = {"x": jnp.array([1.0, 0.2, 0.3, -0.4, 0.5]), "v": jnp.zeros(5)}
    ts = jnp.linspace(0.0, 6.0, 25)
    out = [
        diffrax.diffeqsolve(
            diffrax.ODETerm(vf),
            s,
            0.0,
            6.0,
            None,
            y0,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-7, atol=1e-9),
        )
        for s in (diffrax.Tsit5(), Tsit5())
    ]
    assert int(out[0].stats["num_steps"]) == int(out[1].stats["num_steps"])
    ys = [o.ys for o in out]
    assert ys[0] is not None and ys[1] is not None
    for k in ("x", "v"):
        np.testing.assert_allclose(ys[1][k], ys[0][k], rtol=0, atol=1e-12)


def test_auto_adjoint_by_parameter_count():
    assert isinstance(choose_adjoint(None, P, Q0, Q0), ForwardSensitivity)
    many = {"w": jnp.zeros(FORWARD_MAX_PARAMETERS + 1)}
    assert isinstance(choose_adjoint(None, many, Q0, Q0), diffrax.RecursiveCheckpointAdjoint)
    assert isinstance(choose_adjoint(None, P, Q0, Q0, dense=True), diffrax.RecursiveCheckpointAdjoint)


def _loss(theta, w, static, adjoint):
    p = eqx.combine(theta, static)
    # an explicit solver: the same diffrax loop for every adjoint (the default would run the
    # forward solves on the lean loop, whose steps land on the report times)
    sol = nh.simulate(MECH, p, Q0, qd0(p, w), TS, "appell", adjoint=adjoint, independent=(0,), solver=Tsit5())
    return jnp.sum(sol.q**2) + jnp.sum(sol.qd**2)


@pytest.mark.extended
def test_forward_sensitivities_equal_reverse_mode_in_every_mode():
    """grad (under vmap) and jacfwd by forward sensitivities equal reverse mode.

    Without sensitivity error control both differentiate the same discrete solution
    (same steps), so they agree to rounding, far below the solver tolerance: rtol
    1e-8 is a loose bound on that. (The default, with the sensitivities in the error
    control, takes other steps: `test_default_gradient_matches_reverse_mode_to_tolerance`.)
    """
    theta, static = eqx.partition(P, nh.profiles.trainable(P))
    ws = jnp.array([1.0, 1.1])
    grad_rev = eqx.filter_jit(jax.grad(_loss, argnums=(0, 1)))
    g_rev = [grad_rev(theta, w, static, diffrax.RecursiveCheckpointAdjoint()) for w in ws]
    # default adjoint (None → forward sensitivities, P ≤ FORWARD_MAX_PARAMETERS), batched over w
    same_steps = ForwardSensitivity(error_control=False)
    g_auto = jax.vmap(jax.grad(_loss, argnums=(0, 1)), in_axes=(None, 0, None, None))(theta, ws, static, same_steps)
    g_fwd = jax.jacfwd(_loss, argnums=(0, 1))(theta, ws[0], static, same_steps)
    cases = [(jax.tree_util.tree_map(lambda x, i=i: x[i], g_auto), g_rev[i]) for i in range(2)] + [(g_fwd, g_rev[0])]
    for g, ref in cases:
        for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(ref)):
            np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-8 * float(jnp.max(jnp.abs(b))))
    assert float(jnp.abs(g_rev[0][1])) > 0  # the initial speed is differentiated too


@pytest.mark.slow
def test_forward_sensitivities_reach_arrays_inside_the_formulation():
    """The Baumgarte rate lives in the formulation, not in params: still differentiated.

    The motion stays on the constraints, so this derivative is tiny (≈ 4e-9 with
    Tsit5 at rtol 1e-6; it measures the solver's drift): a finite difference cannot
    resolve it; reverse mode through the same steps can.
    """

    def loss(rate, adjoint):
        sol = nh.simulate(
            MECH,
            P,
            Q0,
            qd0(P),
            TS,
            method="lagrange",
            stabilization="baumgarte",
            baumgarte_rate=rate,
            adjoint=adjoint,
            rtol=1e-6,
            atol=1e-8,
            solver=diffrax.Tsit5(),
        )
        return jnp.sum(sol.qd**2)

    a = jax.grad(loss)(3.0, ForwardSensitivity(error_control=False))
    b = jax.grad(loss)(3.0, diffrax.RecursiveCheckpointAdjoint())
    assert float(jnp.abs(b)) > 0
    np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-12)


@pytest.mark.slow
def test_default_gradient_matches_reverse_mode_to_tolerance():
    """With the sensitivities in the error control (the default) the steps differ from
    the plain solve's; both gradients approximate the exact one to the tolerance."""
    theta, static = eqx.partition(P, nh.profiles.trainable(P))
    g = jax.grad(_loss, argnums=(0, 1))(theta, 1.0, static, None)
    ref = jax.grad(_loss, argnums=(0, 1))(theta, 1.0, static, diffrax.RecursiveCheckpointAdjoint())
    for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * float(jnp.max(jnp.abs(b))))


def test_forward_sensitivities_refuse_report_time_derivatives():
    def loss(T):
        return jnp.sum(
            nh.simulate(
                MECH, P, Q0, qd0(P), jnp.linspace(0.0, T, 5), "appell", independent=(0,), adjoint=ForwardSensitivity()
            ).q
        )

    with pytest.raises(NotImplementedError, match="report times"):
        jax.grad(loss)(1.0)


def test_solve_square_pivots_and_differentiates():
    A = jnp.array([[0.0, 1.0, 2.0], [1.0, 1e-12, 3.0], [4.0, 5.0, 0.0]])  # needs row exchanges
    b = jnp.array([[1.0, 0.5], [2.0, -1.0], [3.0, 0.0]])
    np.testing.assert_allclose(solve_square(A, b), np.linalg.solve(np.asarray(A), np.asarray(b)), rtol=1e-12)
    As = A + 0.1 * jax.random.normal(jax.random.PRNGKey(0), (8, 3, 3))
    xs = jax.vmap(solve_square, in_axes=(0, None))(As, b[:, 0])
    np.testing.assert_allclose(
        xs, np.linalg.solve(np.asarray(As), np.asarray(b[:, 0])[None, :, None])[..., 0], rtol=1e-10
    )
    g = jax.grad(lambda a: jnp.sum(solve_square(a, b[:, 0]) ** 2))(A)
    g_ref = jax.grad(lambda a: jnp.sum(jnp.linalg.solve(a, b[:, 0]) ** 2))(A)
    np.testing.assert_allclose(g, g_ref, rtol=1e-9)


def test_shape_checks_are_remembered():
    calls = []

    def T(q, qd, t, p):
        calls.append(1)
        return V.kinetic(q, qd, t, p)

    mech = nh.Mechanism(T, constraints=V.constraint, forces=V.torques, independent=(0,))
    mech.check_shapes(Q0, qd0(P), 0.0, P)
    n = len(calls)
    mech.check_shapes(Q0, qd0(P), 0.0, P)
    assert len(calls) == n
    with pytest.raises(ValueError, match="qd must have the shape of q"):
        mech.check_shapes(Q0, jnp.zeros(3), 0.0, P)
