"""Transformations through `simulate` and the errors bad input gets."""

from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import variator as V
from jaxnh.profiles import Fourier


TS = jnp.linspace(0.0, 3.0, 31)
MECH = V.mechanism()


def params(J1=0.02, J2=0.05, amp=0.4):
    return V.VariatorParams(J1=J1, J2=J2, U21=Fourier(1.0, sin=[amp], period=2.0), M1=0.3, M2=-0.1)


def final_speed(J2, method="appell"):
    p = params(J2=J2)
    sol = nh.simulate(MECH, p, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, method=method, rtol=1e-10, atol=1e-12)
    return sol.qd[-1, 1]


@pytest.fixture(scope="module")
def jitted():
    return jax.jit(final_speed)


def test_jit_equals_eager(jitted):
    np.testing.assert_allclose(jitted(0.05), final_speed(0.05), rtol=1e-13)


def test_vmap_over_params_equals_loop(jitted):
    J2s = jnp.array([0.03, 0.05, 0.08])
    batched = jax.jit(jax.vmap(final_speed))(J2s)
    looped = jnp.stack([jitted(j) for j in J2s])
    np.testing.assert_allclose(batched, looped, rtol=1e-9)


def test_vmap_over_initial_states():
    p = params()

    def run(w0):
        return nh.simulate(MECH, p, jnp.zeros(2), jnp.stack([w0, w0]), TS, rtol=1e-10, atol=1e-12).q[-1]

    w0s = jnp.array([1.0, 2.0, 3.0])
    out = jax.vmap(run)(w0s)
    for i, w0 in enumerate(np.asarray(w0s)):
        q_ref, _ = V.closed_form(p, TS, w0=float(w0))
        np.testing.assert_allclose(out[i], q_ref[-1], atol=1e-8)


@pytest.mark.parametrize("method", ["appell", "lagrange"])
def test_grad_matches_central_difference(method):
    f = jax.jit(lambda J2: final_speed(J2, method))
    g = jax.grad(lambda J2: final_speed(J2, method))(0.05)
    h = 1e-5
    fd = (f(0.05 + h) - f(0.05 - h)) / (2 * h)
    print(f"{method}: grad {float(g):.10f}, central difference {float(fd):.10f}")
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    assert abs(float(g)) > 1e-3


def test_forward_mode_gradient_with_forward_adjoint():
    def f(J2):
        sol = nh.simulate(
            MECH,
            params(J2=J2),
            jnp.zeros(2),
            jnp.array([2.0, 2.0]),
            TS,
            rtol=1e-10,
            atol=1e-12,
            adjoint=diffrax.ForwardMode(),
        )
        return sol.qd[-1, 1]

    g_fwd = jax.jacfwd(f)(0.05)
    g_rev = jax.grad(final_speed)(0.05)
    np.testing.assert_allclose(g_fwd, g_rev, rtol=1e-8)


# --- bad input ------------------------------------------------------------------


def good() -> dict[str, Any]:
    return dict(mech=MECH, params=params(), q0=jnp.zeros(2), qd0=jnp.array([2.0, 2.0]), ts=TS)


def run(**changes):
    kw = good()
    kw.update(changes)
    return nh.simulate(kw.pop("mech"), kw.pop("params"), kw.pop("q0"), kw.pop("qd0"), kw.pop("ts"), **kw)


def test_wrong_shape_of_kinetic_energy():
    bad = nh.Mechanism(lambda q, qd, t, p: 0.5 * qd**2, constraints=V.constraint)
    with pytest.raises(ValueError, match=r"`kinetic` must return a scalar; got shape \(2,\)"):
        run(mech=bad)


def test_wrong_shape_of_forces():
    bad = nh.Mechanism(V.kinetic, constraints=V.constraint, forces=lambda q, qd, t, p: jnp.zeros(3), independent=(0,))
    with pytest.raises(ValueError, match=r"`forces` must return shape \(2,\); got \(3,\)"):
        run(mech=bad)


def test_more_constraints_than_coordinates():
    bad = nh.Mechanism(V.kinetic, constraints=lambda q, qd, t, p: jnp.zeros(3))
    with pytest.raises(ValueError, match=r"m=3 constraints but there are only s=2 coordinates"):
        run(mech=bad)


def test_mass_matrix_not_positive_definite():
    with pytest.raises(ValueError, match="not positive definite"):
        run(params=params(J1=-0.02))


def test_initial_velocities_violate_constraints():
    with pytest.raises(ValueError, match=r"qd0 violates the nonholonomic constraints(.|\n)*= \[0.5\]"):
        run(qd0=jnp.array([2.0, 2.5]))


@pytest.mark.parametrize("name,value", [("q0", jnp.array([0.0, jnp.nan])), ("qd0", jnp.array([jnp.inf, 1.0]))])
def test_non_finite_state(name, value):
    key = {"q0": "q", "qd0": "qd"}[name]
    with pytest.raises(ValueError, match=f"{key} must be finite"):
        run(**{name: value})


def test_non_finite_params():
    with pytest.raises(ValueError, match=r"params.*J2.*must be finite"):
        run(params=params(J2=jnp.nan))


def test_bad_report_times():
    with pytest.raises(ValueError, match="ts must be strictly increasing"):
        run(ts=jnp.array([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="at least 2 report times"):
        run(ts=jnp.array([0.0]))


def test_bad_method_and_record():
    with pytest.raises(ValueError, match="method must be one of"):
        run(method="euler")
    with pytest.raises(ValueError, match="record entries must be among"):
        run(record=("momentum",))


def test_nonlinear_constraint_needs_flag():
    bad = nh.Mechanism(V.kinetic, constraints=lambda q, qd, t, p: jnp.stack([qd[0] ** 2 - qd[1]]), independent=(0,))
    with pytest.raises(ValueError, match="nonlinear_constraints=True"):
        run(mech=bad, qd0=jnp.array([2.0, 4.0]))


def test_automatic_split_under_vmap_needs_no_hint():
    """The partition is chosen inside the program, per batch member: vmap equals a loop."""
    mech = nh.Mechanism(V.kinetic, constraints=V.constraint, forces=V.torques)
    J2s = jnp.array([0.05, 0.06])
    batched = jax.vmap(lambda J2: run(mech=mech, params=params(J2=J2)).q)(J2s)
    for i, J2 in enumerate(J2s):
        np.testing.assert_allclose(batched[i], run(mech=mech, params=params(J2=J2)).q, rtol=1e-12, atol=1e-12)


def test_step_limit_is_reported_not_garbage():
    with pytest.raises(Exception, match="maximum number of solver steps"):
        run(max_steps=5)
    sol = run(max_steps=5, throw=False)
    assert not bool(sol.success)
    assert "maximum number of solver steps" in sol.message


def test_every_public_name_has_an_api_reference_entry():
    """The strict docs build (docs/hooks.py) refuses a public name that no page documents with
    `::: jaxnh.NAME`; the same check here fails in seconds instead of at the end of a docs build."""
    import pathlib
    import re

    docs = pathlib.Path(__file__).resolve().parents[1] / "docs"
    documented = {n for f in docs.rglob("*.md") for n in re.findall(r"^:::\s+([\w.]+)", f.read_text(), flags=re.M)}
    missing = [
        n
        for n in nh.__all__
        if f"jaxnh.{n}" not in documented and not any(d.startswith(f"jaxnh.{n}.") for d in documented)
    ]
    assert not missing, f"no docs page documents {missing}: add `::: jaxnh.NAME` to a page under docs/api/"


def test_mixed_dtypes_that_break_the_report_times_are_named():
    """float64 report times 10 µs apart at t = 1000 s are equal in float32 (its resolution there is
    61 µs): with a float32 q0 the refusal names the two dtypes, not just "ts must be increasing"."""
    ts = np.linspace(1000.0, 1000.0 + 1e-4, 11)
    with pytest.raises(ValueError, match="float64 and q0 is float32"):
        nh.simulate(MECH, params(), jnp.zeros(2, jnp.float32), jnp.array([2.0, 2.0], jnp.float32), ts)


def _event_solve(J1, cond, **kw):
    p = params(J1=J1)
    sol = nh.simulate(MECH, p, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, event=diffrax.Event(cond), throw=False, **kw)
    return jnp.nansum(sol.q)


def test_derivatives_through_events_are_right_or_refused_by_name():
    """A boolean event condition has no root: its time would get a zero derivative, so any
    derivative through the solve is refused naming the fix; forward mode through diffrax's
    reverse-mode adjoint (the default with events) is refused naming adjoint=diffrax.ForwardMode(),
    which then works and agrees with reverse mode to rounding of the same discrete solve."""

    def boolean(t, y, p, **kw):
        return y[0][0] > 1.0

    def real(t, y, p, **kw):
        return y[0][0] - 1.0

    J1 = jnp.asarray(0.02)
    with pytest.raises(TypeError, match="real-valued function"):
        jax.grad(lambda j: _event_solve(j, boolean))(J1)
    with pytest.raises(TypeError, match="adjoint=diffrax.ForwardMode"):
        jax.jacfwd(lambda j: _event_solve(j, real))(J1)
    fwd = jax.jacfwd(lambda j: _event_solve(j, real, adjoint=diffrax.ForwardMode()))(J1)
    rev = jax.grad(lambda j: _event_solve(j, real))(J1)
    assert np.isfinite(float(fwd)) and abs(float(fwd) - float(rev)) <= 1e-8 * abs(float(rev))


def test_params_that_are_not_a_pytree_are_refused_by_name():
    """A SimpleNamespace or an unregistered dataclass is one opaque leaf to JAX: refused, naming params."""
    import dataclasses
    import types

    @dataclasses.dataclass
    class Plain:
        J1: float

    for p in (types.SimpleNamespace(J1=0.02), Plain(0.02)):
        with pytest.raises(TypeError, match="params: found an object of type"):
            nh.simulate(MECH, p, jnp.zeros(2), jnp.array([2.0, 2.0]), TS)


def test_params_may_hold_strings_and_functions_beside_numbers():
    """Non-numeric leaves (a label, a ratio law as a function) are static: the mechanism's checks
    and the solve see them as they are, and the motion is that of the shipped model with the same
    numbers (two solves at rtol 1e-10 whose steps differ: they agree to the integration error,
    bounded here by 100 rtol)."""

    def T(q, qd, t, p):
        return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)

    def rolling(q, qd, t, p):
        return jnp.stack([p["U21"](t) * qd[0] - qd[1]])

    def torques(q, qd, t, p):
        return jnp.stack([p["M1"], p["M2"]])

    mech = nh.Mechanism(T, constraints=rolling, forces=torques)
    law = params().U21
    p = {"J1": 0.02, "J2": 0.05, "M1": 0.3, "M2": -0.1, "U21": law, "label": "variator, Fourier ratio law"}
    sol = nh.simulate(mech, p, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, rtol=1e-10, atol=1e-12)
    assert sol.status == nh.STATUS.successful
    np.testing.assert_allclose(sol.qd[-1, 1], final_speed(0.05), rtol=100 * 1e-10)


@pytest.mark.parametrize("method", ["lagrange", "appell"])
def test_a_terminating_event_with_each_formulation(method):
    """φ1 reaches 1 rad at t_e: the reports after t_e are NaN, those before finite, status success
    (Lagrange's form has Python flags: the check of the condition's type must not abstract them)."""
    sol = nh.simulate(MECH, params(), jnp.zeros(2), jnp.array([2.0, 2.0]), TS, method=method,
                      event=diffrax.Event(lambda t, y, p, **kw: y[0][0] - 1.0))  # fmt: skip
    finite = np.isfinite(np.asarray(sol.q[:, 0]))
    assert sol.message == "success" and 0 < finite.sum() < len(TS)
    assert np.all(np.asarray(sol.q)[finite, 0] < 1.0)


@pytest.mark.parametrize("adjoint", [None, diffrax.RecursiveCheckpointAdjoint()])
def test_gradient_with_saveat_steps_is_finite_and_right(adjoint):
    """SaveAt(steps=True) leaves rows beyond the last step at inf: they must not turn every gradient
    into NaN. d φ1'(T)/dJ2 against central differences (h = 1e-6: truncation ~h² and the solves'
    rounding ~eps/h, both far below the 1e-6 relative asked here)."""

    def final_rate(J2):
        sol = nh.simulate(MECH, params(J2=J2), jnp.zeros(2), jnp.array([2.0, 2.0]), TS,
                          saveat=diffrax.SaveAt(steps=True), max_steps=256, rtol=1e-10, atol=1e-12,
                          adjoint=adjoint)  # fmt: skip
        last = jnp.max(jnp.where(jnp.isfinite(sol.ts), sol.ts, -1.0))
        return jnp.sum(jnp.where(sol.ts == last, sol.qd[:, 0], 0.0))

    g = float(jax.grad(final_rate)(jnp.asarray(0.05)))
    h = 1e-6
    fd = float((final_rate(0.05 + h) - final_rate(0.05 - h)) / (2 * h))
    assert np.isfinite(g) and abs(g - fd) <= 1e-6 * abs(fd)


def test_backsolve_adjoint_with_step_maps_is_refused_and_plain_lagrange_differentiates():
    with pytest.raises(ValueError, match="BacksolveAdjoint"):
        nh.simulate(
            MECH, params(), jnp.zeros(2), jnp.array([2.0, 2.0]), TS, "appell", adjoint=diffrax.BacksolveAdjoint()
        )
    # Baumgarte's damping of the drift turns into growth e^(α Δt) when the state is integrated back
    with pytest.raises(ValueError, match=r"BacksolveAdjoint\(\) cannot differentiate stabilization='baumgarte'"):
        nh.simulate(
            MECH, params(), jnp.zeros(2), jnp.array([2.0, 2.0]), TS, stabilization="baumgarte",
            adjoint=diffrax.BacksolveAdjoint(),
        )  # fmt: skip

    def final(J2):
        sol = nh.simulate(MECH, params(J2=J2), jnp.zeros(2), jnp.array([2.0, 2.0]), TS, method="lagrange",
                          rtol=1e-10, atol=1e-12, adjoint=diffrax.BacksolveAdjoint())  # fmt: skip
        return sol.qd[-1, 0]

    g, h = float(jax.grad(final)(jnp.asarray(0.05))), 1e-6
    fd = float((final(0.05 + h) - final(0.05 - h)) / (2 * h))
    # backsolve integrates the adjoint equation backwards at the same tolerances: 1e-5 relative
    assert abs(g - fd) <= 1e-5 * abs(fd)
