"""The lean integration loop (jaxnh._lean.lean_solve) against diffrax, closed forms and itself.

Reference values: diffrax with the same tableau (jaxnh.solvers) and controller
must take the very same steps (agreement to rounding); closed forms (exponential,
harmonic oscillator, the variator's quadrature `closed_form`) bound the error by
a small multiple of the tolerance; fixed-step runs give the order of the method
and of its dense output.
"""

from typing import cast

import diffrax
import jax
import jax.export
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from jaxnh import _lean
from jaxnh._lean import lean_solve, LeanSolution
from jaxnh.models import variator as V
from jaxnh.solvers import DOP853, Tsit5


METHODS = {"tsit5": Tsit5, "dop853": DOP853}


def oscillator(t, y, w2):
    """x'' = -w2 x as (x, v); x = cos(w t) from (1, 0)."""
    return jnp.stack([y[1], -w2 * y[0]])


TS = jnp.linspace(0.0, 10.0, 11)
Y0 = jnp.array([1.0, 0.0])


def _lean_osc(method, report, dt0=None):
    return jax.jit(
        lambda y0, w2, rtol, atol: lean_solve(
            oscillator, y0, w2, TS, method=method, rtol=rtol, atol=atol, report=report, dt0=dt0
        )
    )


# one compiled function per (method, report), shared by the tests below
OSC = {(m, r): _lean_osc(m, r) for m in METHODS for r in ("interpolate", "step")}
OSC_DT = {m: _lean_osc(m, "interpolate", dt0=0.01) for m in METHODS}


@pytest.mark.parametrize("method", list(METHODS))
def test_same_steps_as_diffrax(method):
    # diffrax 0.7.2's PIDController starts every ODE with dt0 = 0.01 when dt0=None (its initial-step
    # selection sees a WrapTerm, not an ODETerm); with that dt0 given to both, the two loops must take
    # exactly the same steps and agree to rounding.
    d = diffrax.diffeqsolve(
        diffrax.ODETerm(oscillator),
        METHODS[method](),
        0.0,
        10.0,
        0.01,
        Y0,
        args=4.0,
        saveat=diffrax.SaveAt(ts=TS),
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10),
    )
    s = OSC_DT[method](Y0, 4.0, 1e-8, 1e-10)
    assert int(s.status) == 0
    assert int(s.stats["num_steps"]) == int(d.stats["num_steps"])
    assert int(s.stats["num_accepted_steps"]) == int(d.stats["num_accepted_steps"])
    assert d.ys is not None
    np.testing.assert_allclose(s.ys, d.ys, rtol=0, atol=1e-13)


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("report", ["interpolate", "step"])
def test_oscillator_closed_form(method, report):
    for rtol in (1e-6, 1e-10):
        s = OSC[method, report](Y0, 4.0, rtol, rtol / 100)
        assert int(s.status) == 0
        err = np.max(np.abs(np.asarray(s.ys) - np.stack([np.cos(2 * TS), -2 * np.sin(2 * TS)], 1)))
        # global error of a tolerance-controlled solve over 10 periods: a few hundred times rtol at most
        assert err < 300 * rtol, (rtol, err)
        assert err > 0
    st = s.stats
    assert int(st["num_steps"]) == int(st["num_accepted_steps"]) + int(st["num_rejected_steps"])
    # rhs evaluations: 1 (f0) + 1 (initial step) + per attempt (6 or 12) [+ 3 per dense DOP853 step]
    per = 6 if method == "tsit5" else 12
    base = 2 + per * int(st["num_steps"])
    assert base <= int(st["rhs_evaluations"]) <= base + 3 * 10


@pytest.mark.parametrize("method,order", [("tsit5", 5), ("dop853", 8)])
def test_order_of_convergence_fixed_steps(method, order):
    # fixed steps: huge tolerances accept every step and factormax = 1 keeps h = dt0
    T = 2.0

    @jax.jit
    def solve(h):
        ts = jnp.linspace(0.0, T, 9)  # report times on the step grid for h = T/8/2^k
        return lean_solve(
            oscillator, Y0, 4.0, ts, method=method, rtol=1e30, atol=1e30, dt0=h, factormax=1.0, report="step"
        ).ys[-1]

    hs = [T / 16, T / 32, T / 64] if method == "tsit5" else [T / 8, T / 16, T / 32]
    exact = np.array([np.cos(2 * T), -2 * np.sin(2 * T)])
    errs = [np.max(np.abs(np.asarray(solve(h)) - exact)) for h in hs]
    slopes = [np.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(abs(s - order) < 0.6 for s in slopes), (errs, slopes)


@pytest.mark.parametrize("method,order", [("tsit5", 4), ("dop853", 7)])
def test_dense_output_order(method, order):
    # report times in the middle of fixed steps: the error of the continuous extension at
    # s = 0.37 converges at least with its order (global error of the interpolant of order p: h^(p+1) locally)
    T = 0.5 if method == "tsit5" else 3.2  # DOP853 reaches rounding error at steps of 0.1 already

    @jax.jit
    def solve(h):
        t_mid = 0.37 * h
        return lean_solve(
            oscillator, Y0, 4.0, jnp.stack([0.0, t_mid]), method=method, rtol=1e30, atol=1e30, dt0=h, factormax=1.0
        ).ys[-1], t_mid

    errs = []
    hs = [T / 2, T / 4, T / 8]
    for h in hs:
        y, tm = solve(h)
        errs.append(np.max(np.abs(np.asarray(y) - np.array([np.cos(2 * tm), -2 * np.sin(2 * tm)]))))
    slopes = [np.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(s > order + 0.5 for s in slopes), (errs, slopes)


def test_exponential_jvp_and_vmap():
    ts = jnp.linspace(0.0, 2.0, 5)

    def f(t, y, lam):
        return lam * y

    @jax.jit
    def solve(y0, lam):
        return lean_solve(f, y0, lam, ts, method="dop853", rtol=1e-11, atol=1e-13)

    y0 = jnp.array([1.0, -0.5, 2.0])
    lam = -0.8
    exact = np.asarray(y0)[None] * np.exp(lam * np.asarray(ts))[:, None]
    s = solve(y0, lam)
    np.testing.assert_allclose(s.ys, exact, rtol=2e-10, atol=1e-13)

    # forward mode: d y(t) / d lam = t y(t), d y(t) / d y0 = e^(lam t) (applied to a tangent)
    (ys, dys) = jax.jvp(lambda l: solve(y0, l).ys, (lam,), (1.0,))
    np.testing.assert_allclose(dys, np.asarray(ts)[:, None] * exact, rtol=1e-9, atol=1e-12)
    v = jnp.array([0.3, 1.0, -2.0])
    _, dys0 = jax.jvp(lambda a: solve(a, lam).ys, (y0,), (v,))
    np.testing.assert_allclose(dys0, np.asarray(v)[None] * np.exp(lam * np.asarray(ts))[:, None], rtol=1e-9, atol=1e-12)

    # vmap over rates with different step counts: each member equals its own solve, finished ones frozen
    lams = jnp.array([-0.8, 0.4, -6.0, 0.0])
    b = jax.vmap(solve, in_axes=(None, 0))(y0, lams)
    assert b.ys.shape == (4, 5, 3)
    steps = np.asarray(b.stats["num_steps"])
    assert len(set(steps.tolist())) > 1
    for i, l in enumerate(np.asarray(lams)):
        one = solve(y0, float(l))
        np.testing.assert_allclose(b.ys[i], one.ys, rtol=1e-14, atol=1e-15)
        assert int(one.stats["num_steps"]) == steps[i]
    assert np.all(np.asarray(b.status) == 0)


@pytest.mark.parametrize("report", ["interpolate", "step"])
def test_repeated_and_single_report_times(report):
    ts = jnp.array([0.0, 0.0, 0.5, 0.5, 0.5, 0.5, 1.0, 1.0])

    def f(t, y, a):
        return -y

    s = lean_solve(f, jnp.array([1.0]), None, ts, method="tsit5", rtol=1e-10, atol=1e-12, report=report)
    assert int(s.status) == 0
    np.testing.assert_allclose(s.ys[:, 0], np.exp(-np.asarray(ts)), rtol=1e-9)
    one = lean_solve(f, jnp.array([1.0]), None, jnp.array([0.3]), report=report)
    assert int(one.status) == 0 and int(one.stats["num_steps"]) == 0
    np.testing.assert_array_equal(one.ys, [[1.0]])


@pytest.mark.parametrize("method", list(METHODS))
def test_report_times_denser_than_steps(method):
    # 501 report times over a solve that needs ~20-60 natural steps: every step holds several of them
    ts = jnp.linspace(0.0, 5.0, 501)

    def f(t, y, a):
        return -y

    s = lean_solve(f, jnp.array([1.0]), None, ts, method=method, rtol=1e-10, atol=1e-12, report="interpolate")
    assert int(s.status) == 0
    np.testing.assert_allclose(s.ys[:, 0], np.exp(-np.asarray(ts)), rtol=2e-8)
    # at most 2 report times strictly inside a step: at least 500 / 3 steps
    assert int(s.stats["num_accepted_steps"]) >= 167


def test_float32():
    ts = jnp.linspace(0.0, 10.0, 11, dtype=jnp.float32)
    s = jax.jit(lambda y0: lean_solve(oscillator, y0, jnp.float32(4.0), ts, rtol=1e-5, atol=1e-7))(
        Y0.astype(jnp.float32)
    )
    assert s.ys.dtype == jnp.float32
    assert int(s.status) == 0
    err = np.max(np.abs(np.asarray(s.ys, float) - np.stack([np.cos(2 * ts), -2 * np.sin(2 * ts)], 1)))
    assert err < 2e-3  # 300 rtol, as in float64


def test_status_max_steps_and_nonfinite():
    s = OSC["tsit5", "interpolate"](Y0, 4.0, 1e-12, 1e-14)  # many steps needed
    lim = jax.jit(lambda y0: lean_solve(oscillator, y0, 4.0, TS, rtol=1e-12, atol=1e-14, max_steps=20))(Y0)
    assert int(s.status) == 0 and int(s.stats["num_steps"]) > 20
    assert int(lim.status) == 1
    assert int(lim.stats["num_steps"]) == 20
    assert np.all(np.isnan(np.asarray(lim.ys[-1]))) and float(lim.t_final) < 10.0

    def blows_up(t, y, a):  # finite until t = 1, then NaN
        return jnp.where(t < 1.0, -y, jnp.nan)

    bad = jax.jit(lambda y0: lean_solve(blows_up, y0, None, TS, rtol=1e-8, atol=1e-10))(Y0)
    assert int(bad.status) == 2
    assert 0.9 < float(bad.t_final) <= 1.0
    assert np.all(np.isnan(np.asarray(bad.ys[2:])))
    np.testing.assert_allclose(bad.ys[0], Y0)
    assert set(_lean.STATUS_MESSAGES) == {0, 1, 2}


def test_no_host_callbacks_and_exportable():
    f = jax.jit(lambda y0, w2: lean_solve(oscillator, y0, w2, TS, method="dop853", rtol=1e-8, atol=1e-10))
    jaxpr = str(jax.make_jaxpr(f)(Y0, 4.0))
    hlo = f.lower(Y0, 4.0).as_text()
    for text in (jaxpr.lower(), hlo.lower()):
        assert "callback" not in text
    exp = jax.export.export(f)(Y0, 4.0)
    # (jax.export's type hints say that `call` returns an array: here it is the exported LeanSolution)
    s = cast(LeanSolution, exp.call(Y0, 4.0))
    np.testing.assert_array_equal(s.ys, f(Y0, 4.0).ys)
    pytest.importorskip("flatbuffers")  # jax.export's serialisation needs it
    again = jax.export.deserialize(exp.serialize())
    np.testing.assert_array_equal(cast(LeanSolution, again.call(Y0, 4.0)).ys, s.ys)
    # under vmap too (a batched while loop, still no callbacks)
    fb = jax.jit(jax.vmap(lambda w2: lean_solve(oscillator, Y0, w2, TS, rtol=1e-8, atol=1e-10)))
    assert "callback" not in fb.lower(jnp.array([1.0, 4.0])).as_text().lower()


def test_pre_step_reparametrisation():
    # x = s u with u' = -u, s' = 0 (so x = e^-t); pre_step moves the scale into s whenever |u| < 0.5,
    # which changes f = (-u, 0): a stale first stage would give a wrong answer.
    ts = jnp.linspace(0.0, 5.0, 11)

    def f(t, y, a):
        return jnp.stack([-y[0], jnp.zeros_like(y[1])])

    def pre(t, y, a):
        jump = jnp.abs(y[0]) < 0.5
        return jnp.where(jump, jnp.stack([jnp.ones_like(y[0]), y[0] * y[1]]), y), jump

    for method in METHODS:
        s = lean_solve(f, jnp.array([1.0, 1.0]), None, ts, method=method, rtol=1e-10, atol=1e-12, pre_step=pre)
        assert int(s.status) == 0
        x = np.asarray(s.ys[:, 0] * s.ys[:, 1])
        np.testing.assert_allclose(x, np.exp(-np.asarray(ts)), rtol=1e-8)
        assert np.min(np.asarray(s.ys[1:, 1])) < 0.5  # the reparametrisation did happen
        plain = 2 + (6 if method == "tsit5" else 12) * int(s.stats["num_steps"])
        assert int(s.stats["rhs_evaluations"]) > plain  # jumps re-evaluated the first stage


def test_post_step_projection_and_reject():
    # projection onto the energy circle x² + v²/w² = 1, counted in the error estimate
    def proj(t0, y0, t1, y1, w2):
        r = jnp.sqrt(y1[0] ** 2 + y1[1] ** 2 / w2)
        y1p = y1 / r
        return y1p, y1p - y1, False

    s = lean_solve(oscillator, Y0, 4.0, TS, method="tsit5", rtol=1e-8, atol=1e-10, post_step=proj, report="step")
    assert int(s.status) == 0
    energy = np.asarray(s.ys[:, 0] ** 2 + s.ys[:, 1] ** 2 / 4.0)
    np.testing.assert_allclose(energy, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(s.ys[:, 0], np.cos(2 * np.asarray(TS)), atol=3e-6)

    def reject_late(t0, y0, t1, y1, w2):  # refuses every step that ends after t = 3
        return y1, None, t1 > 3.0

    r = lean_solve(oscillator, Y0, 4.0, TS, rtol=1e-8, atol=1e-10, post_step=reject_late)
    assert int(r.status) == 2 and 2.9 < float(r.t_final) <= 3.0


# ----------------------------------------------------------------------------- jaxnh-derived fields


def _variator_field(method):
    from jaxnh.equations import formulation

    p = V.VariatorParams(
        J1=0.02,
        J2=0.05,
        U21=__import__("jaxnh").profiles.Fourier(1.5, cos=[0.0], sin=[0.5], period=np.pi),
        M1=0.3,
        M2=-0.1,
    )
    w0 = 10.0
    ts = jnp.linspace(0.0, 10.0, 101)
    q0, qd0 = jnp.zeros(2), jnp.array([w0, 1.5 * w0])
    form = formulation(V.mechanism(), method, q0, qd0, ts[0], p, (0,) if method != "lagrange" else None)
    y0_tree = form.state(q0, qd0, ts[0], p)
    y0, unravel = ravel_pytree(y0_tree)

    def vf(t, y, params):
        return ravel_pytree(form.vector_field(t, unravel(y), params))[0]

    return form, p, ts, y0, unravel, vf, w0


@pytest.mark.parametrize("method", ["appell", "lagrange"])
def test_variator_closed_form(method):
    form, p, ts, y0, unravel, vf, w0 = _variator_field(method)
    q_ref, qd_ref = V.closed_form(p, ts, w0=w0)
    solve = jax.jit(lambda y0, p: lean_solve(vf, y0, p, ts, method="dop853", rtol=1e-10, atol=1e-12))
    s = solve(y0, p)
    assert int(s.status) == 0
    q, qd = jax.vmap(lambda y, t: form.unpack(unravel(y), t, p))(s.ys, ts)
    err = max(np.max(np.abs(np.asarray(q) - np.asarray(q_ref))), np.max(np.abs(np.asarray(qd) - np.asarray(qd_ref))))
    # phi ~ 150 rad over the run: 1e-10 relative per step accumulates to ~1e-8 absolute
    assert err < 1e-7, err


@pytest.mark.slow
def test_variator_same_as_diffrax_with_tangents():
    form, p, ts, y0, unravel, vf, w0 = _variator_field("appell")
    # report times 1 s apart: in "interpolate" mode a step may hold at most 2 report times strictly
    # inside it, a limit that 0.1 s apart would bind on a few steps (and change them from diffrax's)
    ts = jnp.linspace(0.0, 10.0, 11)
    d = diffrax.diffeqsolve(
        diffrax.ODETerm(vf),
        DOP853(),
        ts[0],
        ts[-1],
        0.01,
        y0,
        args=p,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
    )
    s2 = lean_solve(vf, y0, p, ts, method="dop853", rtol=1e-10, atol=1e-12, dt0=0.01, report="interpolate")
    assert int(s2.stats["num_steps"]) == int(d.stats["num_steps"])
    assert d.ys is not None
    np.testing.assert_allclose(s2.ys, d.ys, rtol=1e-13, atol=1e-12)

    # forward sensitivity of the trajectory to J1 through the same loop, against diffrax's forward
    # mode on the same steps (same discrete scheme, so the same derivative to rounding)
    def lean_ys(J1):
        q = V.VariatorParams(J1, p.J2, p.U21, p.M1, p.M2)
        return lean_solve(vf, y0, q, ts, method="dop853", rtol=1e-10, atol=1e-12, dt0=0.01, report="interpolate").ys

    def diffrax_ys(J1):
        q = V.VariatorParams(J1, p.J2, p.U21, p.M1, p.M2)
        return diffrax.diffeqsolve(
            diffrax.ODETerm(vf),
            DOP853(),
            ts[0],
            ts[-1],
            0.01,
            y0,
            args=q,
            saveat=diffrax.SaveAt(ts=ts),
            adjoint=diffrax.ForwardMode(),
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
        ).ys

    one = jnp.ones_like(p.J1)
    _, d_lean = jax.jvp(lean_ys, (p.J1,), (one,))
    _, d_diffrax = jax.jvp(diffrax_ys, (p.J1,), (one,))
    assert np.max(np.abs(np.asarray(d_lean))) > 1.0  # phi depends strongly on J1
    np.testing.assert_allclose(d_lean, d_diffrax, rtol=1e-10, atol=1e-9)
