"""float32: every formulation and stabilisation runs and keeps the dtype it is given;
its accuracy against the (float64) closed form is measured, not hidden.

With 64-bit mode on (jaxnh's default), float32 is chosen by passing float32 arrays:
q0, qd0, ts and every floating leaf of params. The accuracy floor is set by the
tolerance `simulate` accepts (rtol ≥ 10 eps ≈ 1.2e-6) and by rounding in the state
(|q| grows, so the absolute resolution of an angle is eps·|q|). The sweep of error
against rtol is in benchmarks/STABILITY.md.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import variator as V


F32 = jnp.float32
MECH = V.mechanism()
TS = jnp.linspace(0.0, 3.0, 61)
W0 = 2.0


def to32(tree):
    """Every floating array leaf cast to float32."""
    return jax.tree.map(lambda x: x.astype(F32) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x, tree)


def initial(p):
    return jnp.zeros(2, F32), (W0 * jnp.stack([jnp.ones((), F32), p.U21(jnp.zeros((), F32))])).astype(F32)


@pytest.fixture(scope="module")
def reference():
    """The closed form in float64 at TS (compiled once)."""
    ts = np.asarray(TS, dtype=np.float64)
    return jax.jit(lambda p: V.closed_form(p, ts, w0=W0))


CASES = [("appell", None), ("lagrange", None), ("lagrange", "baumgarte"), ("lagrange", "projection")]


@pytest.fixture(scope="module")
def runs(reference):
    p64 = V.default_params()
    p32 = to32(p64)
    q_ref, qd_ref = (np.asarray(x) for x in reference(p64))
    out = {}
    for method, stab in CASES:
        record = ("energy", "residual") + (("multipliers",) if method != "substituted" else ())
        sol = nh.simulate(
            MECH,
            p32,
            *initial(p32),
            TS.astype(F32),
            method=method,
            stabilization=stab,
            rtol=1e-5,
            atol=1e-6,
            record=record,
        )
        out[(method, stab)] = dict(
            sol=sol,
            err_q=np.max(np.abs(np.asarray(sol.q, np.float64) - q_ref)) / np.max(np.abs(q_ref)),
            err_qd=np.max(np.abs(np.asarray(sol.qd, np.float64) - qd_ref)) / np.max(np.abs(qd_ref)),
            res=np.max(np.abs(np.asarray(sol.residual, np.float64))),
        )
    return out


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(str(x) for x in c))
def test_float32_keeps_its_dtype(runs, case):
    sol = runs[case]["sol"]
    assert bool(sol.success), sol.message
    for name in ("ts", "q", "qd", "energy", "residual", "multipliers"):
        x = getattr(sol, name)
        assert x.dtype == F32, (name, x.dtype)
        assert np.all(np.isfinite(np.asarray(x))), name


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(str(x) for x in c))
def test_float32_accuracy_against_closed_form(runs, case):
    r = runs[case]
    print(f"{case}: relative error q {r['err_q']:.1e}, qd {r['err_qd']:.1e}, residual {r['res']:.1e}")
    # rtol 1e-5 over 3 s: measured relative errors 2e-6 … 2e-5; 1e-4 is the bound a
    # float32 user can rely on at this tolerance (and 1e4× below a formulation error).
    assert r["err_q"] < 1e-4 and r["err_qd"] < 1e-4, r


def test_float32_constraint_drift_and_its_control(runs):
    """At float32 tolerances Lagrange's velocity constraint drifts visibly (measured
    ≈ 1e-3 rad/s of 2–4 rad/s at rtol 1e-5); Baumgarte bounds it, projection and
    Appell hold it to float32 rounding."""
    res = {k: r["res"] for k, r in runs.items()}
    scale = 4.0  # |U21 phi1'| ≲ 4 rad/s
    eps = float(jnp.finfo(F32).eps)
    assert res[("appell", None)] < 10 * eps * scale
    assert res[("lagrange", "projection")] < 10 * eps * scale
    assert res[("lagrange", "baumgarte")] < res[("lagrange", None)]
    assert res[("lagrange", None)] < 1e-2  # drift, but bounded by the tolerance × steps


def test_rtol_below_float32_resolution_is_refused():
    p32 = to32(V.default_params())
    with pytest.raises(ValueError, match=r"rtol=1e-07 is below what float32 can resolve.*float64"):
        nh.simulate(MECH, p32, *initial(p32), TS.astype(F32), rtol=1e-7)


def test_float32_accelerations_and_consistent_velocities():
    p64 = V.default_params()
    p32 = to32(p64)
    q, qd, t = jnp.array([0.3, -1.2]), jnp.array([1.5, 0.7]), 0.8

    @jax.jit
    def everything(p, q, qd, t):
        v = nh.consistent_velocities(MECH, q, qd, t, p)
        return [v] + [
            x
            for m in ("lagrange", "appell", "substituted")
            for x in nh.accelerations(MECH, q, v, t, p, method=m)
            if x is not None
        ]

    out64 = everything(p64, q, qd, jnp.asarray(t))
    out32 = everything(p32, q.astype(F32), qd.astype(F32), jnp.asarray(t, F32))
    for a, b in zip(out32, out64):
        assert a.dtype == F32
        # a handful of float32 operations on O(1) numbers: a few eps
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b), rtol=1e-5, atol=1e-5)


def test_float32_gradient_and_traced_non_finite_input(reference):
    """jax.grad through a float32 solve matches the float64 closed form's derivative;
    a NaN parameter inside the transformation raises (throw=True), not a NaN gradient."""
    p64 = V.default_params()

    def final_speed32(J2):
        p = to32(V.VariatorParams(J1=p64.J1, J2=J2, U21=p64.U21, M1=p64.M1, M2=p64.M2))
        sol = nh.simulate(MECH, p, *initial(p), TS.astype(F32), rtol=1e-5, atol=1e-6, independent=(0,))
        return sol.qd[-1, 0]

    grad32 = jax.jit(jax.grad(final_speed32))
    g32 = grad32(jnp.asarray(0.05, F32))
    assert g32.dtype == F32

    def final_speed64(J2):
        p = V.VariatorParams(J1=p64.J1, J2=J2, U21=p64.U21, M1=p64.M1, M2=p64.M2)
        return reference(p)[1][-1, 0]

    h = 1e-6
    g64 = (final_speed64(0.05 + h) - final_speed64(0.05 - h)) / (2 * h)
    print(f"d phi1'(3 s)/d J2: float32 {float(g32):.6f}, float64 closed form {float(g64):.6f}")
    # the float32 solve's relative error is ~1e-5 (above); its derivative is computed
    # by the same float32 steps, so 1e-3 relative covers it
    np.testing.assert_allclose(float(g32), float(g64), rtol=1e-3)
    with pytest.raises(Exception, match="NaN or inf"):
        jax.block_until_ready(grad32(jnp.asarray(jnp.nan, F32)))


@pytest.mark.parametrize("ratio", [1e-6, 1e6])
def test_float32_extreme_inertia_ratio_is_accepted(ratio):
    p = to32(V.VariatorParams(J1=0.05 * ratio, J2=0.05, U21=V.default_params().U21, M1=0.0, M2=0.0))
    sol = nh.simulate(MECH, p, *initial(p), TS.astype(F32), rtol=1e-5, atol=1e-6, record=("energy",))
    E = np.asarray(sol.energy, np.float64)
    assert bool(sol.success)
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-4  # no torques: T is conserved
