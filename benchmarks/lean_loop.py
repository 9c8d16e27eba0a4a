"""The integration loop itself: diffrax, jaxnh's lean loop, a bare `lax.while_loop`, numba and SciPy.

Issue 16's case: the variator with w0 = 10 rad/s, U21 = 1.5 + 0.5 sin 2t, J1 = 0.02,
J2 = 0.05 kg·m², M1 = 0.3, M2 = −0.1 N·m, over 10 s with 101 report times; the
reference is the quadrature closed form (`jaxnh.models.variator.closed_form`). The
error of a run is the largest absolute error of (phi1, phi2, phi1') over the report
times.

Every contender integrates the same right-hand side, eq. (9) written by hand (state
(phi1, phi2, phi1')), so the loops are compared and not the fields; one more row runs
jaxnh's derived Appell field in the lean loop. Contenders:

* diffrax `diffeqsolve` with diffrax.Tsit5, diffrax.Dopri8 and jaxnh's unrolled
  DOP853 (`jaxnh.solvers.DOP853`, the lean loop's tableau), `SaveAt(ts=...)`,
  `PIDController`;
* `jaxnh._lean.lean_solve` (Tsit5 and DOP853 tableaus), reports by the method's
  interpolant ("interp") or by stepping onto each report time ("step");
* a bare `lax.while_loop` with the same tableaus written minimally (stages unrolled,
  integral controller, stepping onto report times, start step 0.01): the reference of
  the "within 2×" target;
* numba (optional: the row is skipped when numba is not installed) with the same
  tableaus and loop as the bare JAX one: the "limit" row;
* SciPy `solve_ivp(method="DOP853")` with `t_eval` (its dense output).

For each contender the tolerance is the loosest rtol on a grid of 1/8 decade
(atol = rtol/100) whose run reaches error ≤ 1e-8; times are medians of CPU times over
interleaved rounds (benchmarks/common.py). The batch is `jit(vmap(...))` over 1000
initial speeds w0 ∈ [9.5, 10.5] at the same tolerance; its error is checked against
the closed form on 8 of the members. Fixed costs (trace = `jit(f).lower`, compile =
`.compile()`, and the number of HLO instructions of the compiled program) are
measured in a fresh process per contender. With a GPU present the lean loop and
diffrax also run the batch there ("GPU" rows).

    python -m benchmarks.lean_loop [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import json
import math
import re
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import jaxnh.solvers as S
from jaxnh import profiles
from jaxnh._lean import lean_solve
from jaxnh.models import variator as V

from . import problems as PB


TARGET_ERROR = 1e-8
W0 = 10.0
BATCH = 1000
CPU = jax.devices("cpu")[0]

# --------------------------------------------------------------------------- the case


def case_params() -> V.VariatorParams:
    """Issue 16's variator: U21 = 1.5 + 0.5 sin 2t (period π s), default inertias and torques."""
    return V.VariatorParams(
        J1=0.02, J2=0.05, U21=profiles.Fourier(1.5, cos=[0.0], sin=[0.5], period=math.pi), M1=0.3, M2=-0.1
    )


P = case_params()
TS = jnp.linspace(0.0, 10.0, 101)
TS_NP = np.asarray(TS)


def reference(w0: float = W0) -> np.ndarray:
    """Closed form as the state (phi1, phi2, phi1') at the report times, shape (101, 3)."""
    q, qd = V.closed_form(P, TS, w0=w0)
    return np.concatenate([np.asarray(q), np.asarray(qd)[:, :1]], axis=1)


def y0_of(w0):
    return jnp.stack([jnp.zeros_like(w0), jnp.zeros_like(w0), w0])


def eq9(t, y, p):
    """Eq. (9) by hand on the flat state (phi1, phi2, phi1')."""
    U, dU = p.U21(t), p.U21.derivative(t)
    w = y[2]
    return jnp.stack([w, U * w, (p.M1(t) + U * p.M2(t) - p.J2 * U * dU * w) / (p.J1 + p.J2 * U**2)])


def appell_field():
    """jaxnh's derived Appell vector field on the raveled state ((phi1, phi2), (phi1',)), as
    `simulate` integrates it (flattened to scalar operations: `jaxnh._scalarize`)."""
    from jaxnh._scalarize import scalarized
    from jaxnh.equations import formulation

    q0, qd0 = jnp.zeros(2), jnp.array([W0, 1.5 * W0])
    form = formulation(V.mechanism(), "appell", q0, qd0, TS[0], P, (0,))
    _, unravel = ravel_pytree(form.state(q0, qd0, TS[0], P))

    def vf(t, y, p):
        return ravel_pytree(scalarized(form.vector_field)(t, unravel(y), p))[0]

    return vf


# --------------------------------------------------------------------------- bare loop (JAX)

TABLEAUS = {
    "tsit5": dict(c=S._T5_C[:6], a=S._T5_A, b=S._T5_B, e=S._T5_E, q=5),
    "dop853": dict(c=S._C[:12], a={i: S._A[i] for i in range(2, 13)}, b=S._B, e=S._ER, e3=S._E3, q=8),
}


def _comb(coeffs, ks):
    out = None
    for j, c in coeffs.items():
        if c != 0.0:
            out = c * ks[j] if out is None else out + c * ks[j]
    return out


def bare_solve(f, y0, p, ts, rtol, atol, tab: str, max_steps: int = 100_000):
    """The same tableau as one minimal `lax.while_loop`: stages unrolled, RMS error norm,
    integral controller (0.9 err^(-1/q), factor in [0.2, 10]), steps clipped onto each
    report time, first step 0.01. Returns (ys, num_steps)."""
    T = TABLEAUS[tab]
    s = len(T["c"])

    def body(c):
        t, y, f0, dt, k, ys, n = c
        target = ts[k]
        t1 = jnp.minimum(t + dt, target)
        h = t1 - t
        ks = {1: f0}
        for i in range(2, s + 1):
            ks[i] = f(t + T["c"][i - 1] * h, y + h * _comb(T["a"][i], ks), p)
        y1 = y + h * _comb(T["b"], ks)
        ks[s + 1] = f(t1, y1, p)
        if tab == "dop853":
            e5, e3 = h * _comb(T["e"], ks), h * _comb(T["e3"], ks)
            d = e5 * e5 + 0.01 * e3 * e3
            err = jnp.where(d > 0, e5 * jnp.abs(e5) / jnp.sqrt(jnp.where(d > 0, d, 1.0)), 0.0)
        else:
            err = h * _comb(T["e"], ks)
        e = jnp.sqrt(jnp.mean((err / (atol + rtol * jnp.maximum(jnp.abs(y), jnp.abs(y1)))) ** 2))
        ok = e < 1
        fac = jnp.clip(0.9 * e ** (-1.0 / T["q"]), jnp.where(ok, 1.0, 0.2), jnp.where(ok, 10.0, 0.9))
        hit = ok & (t1 == target)
        dt_new = jnp.where(hit, jnp.maximum(h * fac, dt), h * fac)
        ys = jnp.where(hit, ys.at[k].set(y1), ys)
        return (
            jnp.where(ok, t1, t),
            jnp.where(ok, y1, y),
            jnp.where(ok, ks[s + 1], f0),
            dt_new,
            jnp.where(hit, k + 1, k),
            ys,
            n + 1,
        )

    ys = jnp.zeros((ts.shape[0], y0.shape[0]), y0.dtype).at[0].set(y0)
    c = (ts[0], y0, f(ts[0], y0, p), jnp.asarray(0.01, y0.dtype), 1, ys, 0)
    out = jax.lax.while_loop(lambda c: (c[4] < ts.shape[0]) & (c[6] < max_steps), body, c)
    return out[5], out[6]


# --------------------------------------------------------------------------- numba (optional)


def numba_solver():
    """(solve(tab, y0, rtol, atol) -> (ys, steps), compile seconds) or None without numba."""
    try:
        import numba
    except ImportError:
        return None
    cs = np.asarray(P.U21.cos, float)
    sn = np.asarray(P.U21.sin, float)
    kk = 2 * np.pi * np.arange(1, cs.size + 1) / float(P.U21.period)
    par = np.array([float(P.J1), float(P.J2), float(P.M1.value), float(P.M2.value), float(P.U21.mean)])

    @numba.njit(cache=False, fastmath=False)
    def rhs(t, y, out, par, cs, sn, kk):
        U = par[4]
        dU = 0.0
        for i in range(kk.size):
            c, s = math.cos(kk[i] * t), math.sin(kk[i] * t)
            U += cs[i] * c + sn[i] * s
            dU += kk[i] * (sn[i] * c - cs[i] * s)
        w = y[2]
        out[0] = w
        out[1] = U * w
        out[2] = (par[2] + U * par[3] - par[1] * U * dU * w) / (par[0] + par[1] * U * U)

    @numba.njit(cache=False, fastmath=False)
    def solve(ptr, col, val, b, c, e1, e2, kind, q, y0, ts, rtol, atol, par, cs, sn, kk):
        n, s, r = y0.size, c.size, ts.size
        K = np.empty((s + 1, n))
        ys = np.zeros((r, n))
        ys[0] = y0
        y = y0.copy()
        y1 = np.empty(n)
        tmp = np.empty(n)
        t = ts[0]
        rhs(t, y, K[0], par, cs, sn, kk)
        dt = 0.01
        k = 1
        steps = 0
        while k < r and steps < 100000:
            target = ts[k]
            t1 = min(t + dt, target)
            h = t1 - t
            for i in range(1, s):
                for j in range(n):
                    acc = 0.0
                    for m in range(ptr[i], ptr[i + 1]):  # nonzero a_il only
                        acc += val[m] * K[col[m], j]
                    tmp[j] = y[j] + h * acc
                rhs(t + c[i] * h, tmp, K[i], par, cs, sn, kk)
            for j in range(n):
                acc = 0.0
                for l in range(s):
                    acc += b[l] * K[l, j]
                y1[j] = y[j] + h * acc
            rhs(t1, y1, K[s], par, cs, sn, kk)
            tot = 0.0
            for j in range(n):
                a5 = 0.0
                a3 = 0.0
                for l in range(s + 1):
                    a5 += e1[l] * K[l, j]
                    a3 += e2[l] * K[l, j]
                a5 *= h
                a3 *= h
                if kind == 1:
                    d = a5 * a5 + 0.01 * a3 * a3
                    ej = a5 * abs(a5) / math.sqrt(d) if d > 0 else 0.0
                else:
                    ej = a5
                sc = atol + rtol * max(abs(y[j]), abs(y1[j]))
                tot += (ej / sc) ** 2
            e = math.sqrt(tot / n)
            ok = e < 1.0
            fac = 0.9 * e ** (-1.0 / q) if e > 0 else 10.0
            fac = min(max(fac, 1.0 if ok else 0.2), 10.0 if ok else 0.9)
            hit = ok and t1 == target
            if ok:
                t = t1
                y[:] = y1
                K[0] = K[s]
                if hit:
                    ys[k] = y
                    k += 1
            dt = max(h * fac, dt) if hit else h * fac
            steps += 1
        return ys, steps

    def dense(tab):
        T = TABLEAUS[tab]
        s = len(T["c"])
        A = np.zeros((s, s))
        for i, row in T["a"].items():
            for j, v in row.items():
                A[i - 1, j - 1] = v
        ptr, col, val = [0], [], []  # the stage matrix in compressed rows (its zeros skipped)
        for i in range(s):
            for j in range(i):
                if A[i, j] != 0.0:
                    col.append(j)
                    val.append(A[i, j])
            ptr.append(len(col))
        b = np.array([T["b"].get(j, 0.0) for j in range(1, s + 1)])
        e1 = np.array([T["e"].get(j, 0.0) for j in range(1, s + 2)])
        e2 = np.array([T.get("e3", {}).get(j, 0.0) for j in range(1, s + 2)])
        return (
            np.asarray(ptr, np.int64),
            np.asarray(col, np.int64),
            np.asarray(val, float),
            b,
            np.asarray(T["c"], float),
            e1,
            e2,
            1 if tab == "dop853" else 0,
            float(T["q"]),
        )

    mats = {tab: dense(tab) for tab in TABLEAUS}

    def run(tab, y0, rtol, atol):
        return solve(*mats[tab], np.asarray(y0, float), TS_NP, rtol, atol, par, cs, sn, kk)

    return run


# --------------------------------------------------------------------------- contenders

DIFFRAX = {"diffrax Tsit5": diffrax.Tsit5, "diffrax Dopri8": diffrax.Dopri8, "diffrax + jaxnh DOP853": S.DOP853}


def jax_contenders(quick: bool) -> dict:
    """name -> f(w0, rtol, atol) -> (ys (101, 3), num_steps); all traceable, vmappable over w0."""
    out = {}
    for name, solver in DIFFRAX.items():
        if quick and name == "diffrax Dopri8":
            continue

        def f(w0, rtol, atol, solver=solver):
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(eq9),
                solver(),
                TS[0],
                TS[-1],
                None,
                y0_of(w0),
                args=P,
                saveat=diffrax.SaveAt(ts=TS),
                max_steps=100_000,
                throw=False,
                stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            )
            return sol.ys, sol.stats["num_steps"]

        out[name] = f
    for tab in ("tsit5", "dop853"):
        for report in ("interpolate", "step"):

            def f(w0, rtol, atol, tab=tab, report=report):
                s = lean_solve(eq9, y0_of(w0), P, TS, method=tab, rtol=rtol, atol=atol, report=report)
                return s.ys, s.stats["num_steps"]

            out[f"lean {tab} ({'interp' if report == 'interpolate' else 'step'})"] = f

        def f(w0, rtol, atol, tab=tab):
            return bare_solve(eq9, y0_of(w0), P, TS, rtol, atol, tab)

        out[f"bare while_loop {tab}"] = f
    vf = appell_field()

    def f(w0, rtol, atol):
        s = lean_solve(vf, y0_of(w0), P, TS, method="dop853", rtol=rtol, atol=atol, report="step")
        return s.ys, s.stats["num_steps"]

    out["lean dop853 (step), jaxnh appell field"] = f
    return out


def options_of(name: str):
    """XLA options for a contender: jaxnh's loops (the lean loop, diffrax with jaxnh's tableau) are
    compiled as `simulate` compiles them (`jaxnh._export.SIMULATE_OPTIONS`); the bare loop and
    diffrax alone as a user's own `jax.jit` would."""
    from jaxnh._export import SIMULATE_OPTIONS

    return dict(SIMULATE_OPTIONS) if name.startswith("lean") or "jaxnh" in name else None


def error_of(ys, ref) -> float:
    ys = np.asarray(ys)
    return float(np.max(np.abs(ys - ref))) if np.all(np.isfinite(ys)) else float("inf")


GRID = [10.0 ** (-e / 8) for e in range(5 * 8, 13 * 8 + 1)]  # rtol 1e-5 ... 1e-13, 1/8 decade


def match(run, ref) -> dict:
    """The loosest grid rtol whose run reaches error ≤ TARGET_ERROR (run(rtol) -> (ys, steps))."""
    for rtol in GRID:
        ys, steps = run(rtol)
        err = error_of(ys, ref)
        if err <= TARGET_ERROR:
            return dict(rtol=rtol, atol=rtol / 100, error=err, steps=int(steps))
    return dict(rtol=None, error=None, steps=None)


def repeat(fn, seconds=0.02):
    """A callable running fn enough times to last about `seconds`, and that count."""
    _, cpu, _ = C.timed(fn)
    m = max(1, int(seconds / max(cpu, 1e-6)))
    return (lambda: [fn() for _ in range(m)]), m


def measure(quick: bool) -> dict:
    ref = reference()
    rounds = 5 if quick else 11
    res = dict(
        case=dict(
            w0=W0,
            U21="1.5 + 0.5 sin 2t",
            J1=0.02,
            J2=0.05,
            M1=0.3,
            M2=-0.1,
            horizon=10.0,
            report_times=101,
            target_error=TARGET_ERROR,
            batch=BATCH,
        )
    )
    single, calls = {}, {}
    with jax.default_device(CPU):
        for name, f in jax_contenders(quick).items():
            g = jax.jit(f)
            compiled = g.lower(C.f64(W0), C.f64(1e-8), C.f64(1e-10)).compile(options_of(name))
            m = match(lambda rtol: compiled(C.f64(W0), C.f64(rtol), C.f64(rtol / 100)), ref)
            C.log(f"[lean_loop] {name}: {m}")
            single[name] = m
            if m["rtol"] is not None:
                args = (C.f64(W0), C.f64(m["rtol"]), C.f64(m["atol"]))
                calls[name] = repeat(lambda c=compiled, a=args: C.block(c(*a)))
    nb = numba_solver()
    if nb is not None:
        for tab in ("tsit5", "dop853"):
            name = f"numba {tab} (limit)"
            _, cpu_first, _ = C.timed(lambda: nb(tab, np.array([0.0, 0.0, W0]), 1e-8, 1e-10))
            m = match(lambda rtol: nb(tab, np.array([0.0, 0.0, W0]), rtol, rtol / 100), ref)
            if tab == "tsit5":  # the first call JIT-compiles the solver shared by both tableaus
                m["compile_cpu"] = cpu_first
            C.log(f"[lean_loop] {name}: {m}")
            single[name] = m
            y0_np = np.array([0.0, 0.0, W0])  # NumPy: no JAX dispatch inside the timed call
            calls[name] = repeat(lambda tab=tab, m=m, y0_np=y0_np: nb(tab, y0_np, m["rtol"], m["atol"]))
    else:
        C.log("[lean_loop] numba not installed: the limit rows are skipped (pip install numba)")
    f_np, _ = PB.eq9_numpy(P)
    y0np = np.array([0.0, 0.0, W0])

    def scipy_run(rtol):
        sol = C.scipy_solve(f_np, y0np, TS_NP, "DOP853", rtol, rtol / 100)
        return (sol.y.T if sol.success else np.full((101, 3), np.nan)), (sol.nfev - 1) // 12

    m = match(scipy_run, ref)
    m["steps_note"] = "(nfev - 1) / 12"
    single["SciPy DOP853"] = m
    C.log(f"[lean_loop] SciPy DOP853: {m}")
    calls["SciPy DOP853"] = repeat(lambda: scipy_run(m["rtol"]), seconds=0.05)

    times = C.interleave({k: v[0] for k, v in calls.items()}, rounds=rounds)
    for k, (fn, mult) in calls.items():
        single[k]["time"] = C.median(times[k]["cpu"]) / mult
        single[k]["wall"] = C.median(times[k]["wall"]) / mult
        single[k]["per_step"] = single[k]["time"] / single[k]["steps"] if single[k]["steps"] else None
    sc = times["SciPy DOP853"]["cpu"]
    for k in calls:
        single[k]["scipy_over"] = C.paired_ratio(
            [x / calls["SciPy DOP853"][1] for x in sc], [x / calls[k][1] for x in times[k]["cpu"]]
        )
    res["single"] = single

    # ---- batch of 1000 ------------------------------------------------------------
    rng = np.random.RandomState(0)
    w0s = jnp.asarray(9.5 + rng.rand(BATCH))
    check = rng.choice(BATCH, 8, replace=False)
    refs = {int(i): reference(float(w0s[i])) for i in check}
    batch = {}
    devices = [("CPU", CPU)] + [("GPU", d) for d in jax.devices() if d.platform == "gpu"][:1]
    for dev_name, dev in devices:
        with jax.default_device(dev):
            bcalls = {}
            for name, f in jax_contenders(quick).items():
                if single[name]["rtol"] is None or (dev_name == "GPU" and "bare" in name):
                    continue
                g = jax.jit(jax.vmap(f, in_axes=(0, None, None)))
                rt = single[name]["rtol"]
                args = (jax.device_put(w0s, dev), C.f64(rt), C.f64(rt / 100))
                compiled = g.lower(*args).compile(options_of(name))
                ys, steps = C.block(compiled(*args))
                err = max(error_of(ys[i], refs[i]) for i in refs)
                key = name if dev_name == "CPU" else f"{name} [GPU]"
                batch[key] = dict(
                    rtol=rt, error=err, max_steps=int(np.max(steps)), mean_steps=float(np.mean(steps)), device=str(dev)
                )
                bcalls[key] = lambda c=compiled, a=args: C.block(c(*a))
                C.log(f"[lean_loop] batch {key}: error {err:.2e}, steps max {int(np.max(steps))}")
            if dev_name == "CPU" and nb is not None:
                for tab in ("tsit5", "dop853"):
                    name = f"numba {tab} (limit)"
                    rt = single[name]["rtol"]
                    w = np.asarray(w0s)

                    def loop(tab=tab, rt=rt, w=w):
                        return [nb(tab, np.array([0.0, 0.0, x]), rt, rt / 100) for x in w]

                    outs = loop()
                    err = max(error_of(outs[i][0], refs[i]) for i in refs)
                    batch[name] = dict(rtol=rt, error=err, max_steps=int(max(o[1] for o in outs)), device="cpu (loop)")
                    bcalls[name] = loop
            bt = C.interleave(bcalls, rounds=3 if quick else 5)
            for k in bcalls:
                batch[k]["time"] = C.median(bt[k]["cpu"] if "GPU" not in k else bt[k]["wall"])
                batch[k]["per_trajectory"] = batch[k]["time"] / BATCH
                batch[k]["scipy_over"] = single["SciPy DOP853"]["time"] / batch[k]["per_trajectory"]
    res["batch"] = batch

    # ---- report density: interpolant against stepping onto report times -----------
    density = []
    with jax.default_device(CPU):
        for nrep in (11, 101, 1001) if not quick else (11, 1001):
            ts = jnp.linspace(0.0, 10.0, nrep)
            q, qd = V.closed_form(P, ts, w0=W0)
            ref_n = np.concatenate([np.asarray(q), np.asarray(qd)[:, :1]], axis=1)
            dcalls = {}
            for tab in ("tsit5", "dop853"):
                for report in ("interpolate", "step"):
                    g = jax.jit(
                        lambda w0, tab=tab, report=report, ts=ts: lean_solve(
                            eq9, y0_of(w0), P, ts, method=tab, rtol=1e-10, atol=1e-12, report=report
                        )
                    )
                    c = g.lower(C.f64(W0)).compile()
                    sol = c(C.f64(W0))
                    row = dict(
                        report_times=nrep,
                        method=tab,
                        report=report,
                        steps=int(sol.stats["num_steps"]),
                        error=error_of(sol.ys, ref_n),
                    )
                    density.append(row)
                    dcalls[len(density) - 1] = repeat(lambda c=c: C.block(c(C.f64(W0))))
            dt = C.interleave({k: v[0] for k, v in dcalls.items()}, rounds=3 if quick else 7)
            for i, (fn, mult) in dcalls.items():
                density[i]["time"] = C.median(dt[i]["cpu"]) / mult
            C.log(f"[lean_loop] report density {nrep}: {density[-4:]}")
    res["density"] = density

    # ---- fixed costs, fresh processes ---------------------------------------------
    fixed = {}
    for name in jax_contenders(quick):
        out = subprocess.run(
            [sys.executable, "-m", "benchmarks.lean_loop", "--fixed-cost", name],
            capture_output=True,
            text=True,
            cwd=str(C.HERE.parent),
            timeout=600,
        )
        try:
            fixed[name] = json.loads(out.stdout.strip().splitlines()[-1])
        except (IndexError, json.JSONDecodeError):
            fixed[name] = dict(error=out.stderr[-500:])
        C.log(f"[lean_loop] fixed cost {name}: {fixed[name]}")
    res["fixed"] = fixed
    return res


def hlo_instructions(compiled) -> int:
    """Instructions of the optimised HLO module, all computations (fusion bodies included)."""
    return len(re.findall(r"^\s+(?:ROOT )?%?\S+ = ", compiled.as_text(), flags=re.M))


def fixed_cost(name: str) -> dict:
    """Trace (lower) and compile CPU seconds of one contender in this (fresh) process."""
    with jax.default_device(CPU):
        f = jax_contenders(False)[name]
        args = (C.f64(W0), C.f64(1e-8), C.f64(1e-10))
        lowered, t_lower, w_lower = C.timed(lambda: jax.jit(f).lower(*args))
        compiled, t_comp, w_comp = C.timed(lambda: lowered.compile())
        text = lowered.as_text().lower()
        return dict(
            trace=t_lower,
            compile=t_comp,
            trace_wall=w_lower,
            compile_wall=w_comp,
            hlo_instructions=hlo_instructions(compiled),
            callbacks="callback" in text,
        )


# --------------------------------------------------------------------------- report


def _fmt_t(s):
    if s is None:
        return "—"
    return f"{s * 1e3:.3g} ms" if s >= 1e-3 else f"{s * 1e6:.3g} µs"


def table(header, rows) -> str:
    """A Markdown table."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def section(R: dict | None) -> list:
    """RESULTS.md lines of this benchmark (called by benchmarks/report.py)."""
    if not R:
        return []
    c = R["case"]
    bare = {tab: R["single"].get(f"bare while_loop {tab}", {}).get("per_step") for tab in ("tsit5", "dop853")}
    L = [
        "## The integration loop (issue 16)",
        "",
        f"Variator, w0 = {c['w0']:g} rad/s, U21 = {c['U21']}, {c['horizon']:g} s, {c['report_times']} report times; "
        f"error = max |(phi1, phi2, phi1') − closed form| over the report times; every contender at the loosest "
        f"rtol (1/8-decade grid, atol = rtol/100) reaching error ≤ {c['target_error']:g}. Eq. (9) by hand in every "
        "row except the last JAX one. CPU times, medians over interleaved rounds "
        "(`python -m benchmarks.lean_loop`). Per step: time / step attempts. The bare loop is the reference of "
        "the ‘within 2×’ target (same tableau); numba is the limit. jaxnh's loops (the lean loop, diffrax with "
        "jaxnh's DOP853) are compiled with the XLA options `simulate` uses (`jaxnh._export.SIMULATE_OPTIONS`), "
        "diffrax alone and the bare loop with JAX's defaults, as a user's own `jax.jit` would.",
        "",
    ]
    S_, B_ = R["single"], R["batch"]

    def row(goal, label, value, ok, fmt):
        if value is None:
            return [label, goal, "—", "—"]
        return [label, goal, fmt(value), "yes" if ok(value) else "no"]

    t = []
    for tab in ("dop853", "tsit5"):
        for mode in ("step", "interp"):
            a, b = S_.get(f"lean {tab} ({mode})", {}), S_.get(f"bare while_loop {tab}", {})
            v = a["per_step"] / b["per_step"] if a.get("per_step") and b.get("per_step") else None
            t.append(
                row(
                    "≤ 2×",
                    f"step cost, lean {tab} ({mode}) / bare while_loop {tab}",
                    v,
                    lambda x: x <= 2,
                    lambda x: f"{x:.2f}×",
                )
            )
    for name in ("lean dop853 (step)", "lean dop853 (step), jaxnh appell field"):
        v = S_.get(name, {}).get("scipy_over")
        t.append(row("≥ 25×", f"one trajectory, SciPy DOP853 / {name}", v, lambda x: x >= 25, lambda x: f"{x:.1f}×"))
        v = B_.get(name, {}).get("scipy_over")
        t.append(
            row(
                "≥ 150×",
                f"batch of {c['batch']}, SciPy DOP853 / {name} per trajectory",
                v,
                lambda x: x >= 150,
                lambda x: f"{x:.0f}×",
            )
        )
    lim = S_.get("numba dop853 (limit)", {}).get("per_step")
    t.append(
        [
            "limit row: numba DOP853 per step",
            "present",
            _fmt_t(lim) if lim else "numba not installed",
            "yes" if lim else "no",
        ]
    )
    gpu = [k for k in B_ if "GPU" in k]
    t.append(["GPU row", "when a GPU is present", ", ".join(gpu) if gpu else "no GPU here", "—"])
    L += [
        table(["issue 16 target", "goal", "measured", "met"], t),
        "",
        "The figures of every row follow, then the choice of report mode and the fixed costs.",
        "",
        "### One trajectory",
        "",
    ]
    rows = []
    for name, r in R["single"].items():
        tab = (
            "dop853"
            if ("dop853" in name.lower() or "DOP853" in name)
            else ("tsit5" if "tsit5" in name.lower() else None)
        )
        vs_bare = (r["per_step"] / bare[tab]) if (tab and bare.get(tab) and r.get("per_step")) else None
        rows.append(
            [
                name,
                f"{r['rtol']:.2g}" if r.get("rtol") else "—",
                f"{r['error']:.2g}" if r.get("error") else "—",
                str(r.get("steps", "—")),
                _fmt_t(r.get("time")),
                _fmt_t(r.get("per_step")),
                f"{vs_bare:.2f}×" if vs_bare else "—",
                f"{r['scipy_over']:.1f}×" if r.get("scipy_over") else "—",
            ]
        )
    L += [
        table(
            [
                "contender",
                "rtol",
                "error",
                "steps",
                "time",
                "per step",
                "per step / bare loop",
                "SciPy DOP853 time / this",
            ],
            rows,
        ),
        "",
    ]
    L += [f"### Batch of {c['batch']} (`jit(vmap)`, w0 ∈ [9.5, 10.5])", ""]
    rows = []
    for name, r in R["batch"].items():
        rows.append(
            [
                name,
                f"{r['rtol']:.2g}",
                f"{r['error']:.2g}",
                str(r["max_steps"]),
                _fmt_t(r.get("time")),
                _fmt_t(r.get("per_trajectory")),
                f"{r['scipy_over']:.0f}×" if r.get("scipy_over") else "—",
            ]
        )
    L += [
        table(
            [
                "contender",
                "rtol",
                "error (8 members)",
                "max steps",
                "batch time",
                "per trajectory",
                "SciPy DOP853 single / this per trajectory",
            ],
            rows,
        ),
        "",
    ]
    if not any("GPU" in k for k in R["batch"]):
        L += ["No GPU on this machine: the GPU rows appear when `jax.devices()` has one (same command).", ""]
    if R.get("density"):
        L += [
            "### Reports: the method's interpolant or stepping onto each report time",
            "",
            "Lean loop, eq. (9), rtol 1e-10, atol 1e-12, the same 10 s with 11, 101 or 1001 report times "
            '(`report="interpolate"` | `"step"`).',
            "",
        ]
        L += [
            table(
                ["report times", "method", "report", "steps", "error", "time"],
                [
                    [
                        str(d["report_times"]),
                        d["method"],
                        d["report"],
                        str(d["steps"]),
                        f"{d['error']:.2g}",
                        _fmt_t(d.get("time")),
                    ]
                    for d in R["density"]
                ],
            ),
            "",
        ]
    L += ["### Fixed costs (fresh process per contender)", ""]
    rows = []
    for name, r in R["fixed"].items():
        if "trace" in r:
            rows.append(
                [
                    name,
                    f"{r['trace']:.2f} s",
                    f"{r['compile']:.2f} s",
                    str(r["hlo_instructions"]),
                    "yes" if r["callbacks"] else "no",
                ]
            )
        else:
            rows.append([name, "failed", "", "", ""])
    for name, r in R["single"].items():
        if "compile_cpu" in r:
            note = f"{r['compile_cpu']:.2f} s (numba JIT of the solver both numba rows share, first call)"
            rows.append([name, "—", note, "—", "no"])
    L += [
        table(["contender", "trace (CPU)", "compile (CPU)", "HLO instructions (compiled)", "host callbacks"], rows),
        "",
    ]
    return L


def controllers() -> list:
    """Steps to reach error 1e-8 (and 1e-6) on the case for integral control (diffrax's default,
    pcoeff = 0, icoeff = 1) and two PI settings, lean loop with the interpolant."""
    ref = reference()
    rows = []
    for tab in ("tsit5", "dop853"):
        for pc, ic in ((0.0, 1.0), (0.3, 0.4), (0.2, 0.3)):
            f = jax.jit(
                lambda w0, rtol, pc=pc, ic=ic, tab=tab: lean_solve(
                    eq9,
                    y0_of(w0),
                    P,
                    TS,
                    method=tab,
                    rtol=rtol,
                    atol=rtol / 100,
                    report="interpolate",
                    pcoeff=pc,
                    icoeff=ic,
                )
            )
            row = dict(method=tab, pcoeff=pc, icoeff=ic)
            for target in (1e-6, 1e-8):
                for rtol in GRID:
                    s = f(C.f64(W0), C.f64(rtol))
                    err = error_of(s.ys, ref)
                    if err <= target:
                        row[f"steps@{target:g}"] = int(s.stats["num_steps"])
                        row[f"rejected@{target:g}"] = int(s.stats["num_rejected_steps"])
                        break
            rows.append(row)
            C.log(row)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer rounds, no diffrax Dopri8")
    ap.add_argument("--fixed-cost", help=argparse.SUPPRESS)
    ap.add_argument("--controllers", action="store_true", help="only compare integral and PI step control (steps)")
    a = ap.parse_args(argv)
    if a.controllers:
        controllers()
        return
    if a.fixed_cost:
        print(json.dumps(fixed_cost(a.fixed_cost)))
        return
    res = measure(a.quick)
    C.save("lean_loop", res)
    print("\n".join(section(res)))


if __name__ == "__main__":
    main()
