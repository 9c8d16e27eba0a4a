"""What automatic derivation and the extras cost: jaxnh against hand-written equations.

1. Right-hand-side cost (issue 4, target 1): a long run (the variator over
   400 s; the generic mechanism over 100 s) at rtol 1e-8, jaxnh "appell" and
   "lagrange" against the hand-written equations in the same solver. Long
   runs make the per-call cost of `simulate` (argument checks in Python)
   negligible next to the solve; it is reported separately: "compiled solve"
   is `simulate`'s jitted inner function, "through simulate" a plain
   `nh.simulate(...)` call, "jit(simulate)" `simulate` wrapped in `jax.jit`.
2. Pay for what you ask: `record=()` against recording multipliers, energy,
   residuals (1001 report times).
3. Time-invariant against rheonomic: the generic mechanism with and without
   explicit time dependence; time per step of jaxnh and of the hand-written
   equations.

    python -m benchmarks.overhead [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import time

import jax
import numpy as np

import jaxnh as nh

from . import problems as PB


def _compile(fn, params, y0):
    R, A = C.f64(1e-8), C.f64(1e-10)  # made once: creating a device scalar costs ~0.1 ms per call
    compiled, secs = C.compile_aot(fn, params, y0, R, A)
    return (lambda: jax.block_until_ready(compiled(params, y0, R, A))), secs, compiled


def rhs_cost(problem: str, solvers, rounds: int, simulate_calls: bool = True) -> list:
    if problem == "variator":
        v = PB.variator(T=400.0, n=401)
        mech, p, ts, q0, qd0, ind = v.mech, v.params, v.ts, v.q0, v.qd0, (0,)
        hand_vf, hand_unpack, hand_y0 = PB.eq9_jax, PB.eq9_unpack, PB.eq9_state(v)
    else:
        g = PB.generic(T=100.0, n=401)
        mech, p, ts, q0, qd0, ind = g.mech, g.params, g.ts, g.q0, g.qd0, g.independent
        hand_vf, hand_unpack, hand_y0 = PB.generic_rhs_jax, (lambda ys, ts, p: ys), (g.q0, g.qd0)
    rows = []
    for sname in solvers:
        calls, compile_s, steps = {}, {}, {}
        for method in ("appell", "lagrange"):
            fn, y0 = C.jaxnh_solver_fn(
                mech, method, q0, qd0, p, ts, C.SOLVERS[sname](), independent=ind if method == "appell" else None
            )
            calls[method], compile_s[method], comp = _compile(fn, p, y0)
            steps[method] = int(comp(p, y0, C.f64(1e-8), C.f64(1e-10))[2])
        fn = C.hand_solver_fn(hand_vf, hand_unpack, ts, C.SOLVERS[sname]())
        calls["hand"], compile_s["hand"], comp = _compile(fn, p, hand_y0)
        steps["hand"] = int(comp(p, hand_y0, C.f64(1e-8), C.f64(1e-10))[2])
        for method in ("appell", "lagrange") if simulate_calls else ():
            kw = dict(
                method=method,
                solver=C.SOLVERS[sname](),
                rtol=1e-8,
                atol=1e-10,
                independent=ind if method == "appell" else None,
            )
            calls[f"{method} through simulate"] = lambda kw=kw: jax.block_until_ready(
                nh.simulate(mech, p, q0, qd0, ts, **kw).q
            )
            jf = jax.jit(lambda p_, q0_, qd0_, kw=kw: nh.simulate(mech, p_, q0_, qd0_, ts, **kw).q)
            _, cpu, wall = C.timed(lambda jf=jf: jax.block_until_ready(jf(p, q0, qd0)))
            compile_s[f"{method} jit(simulate)"] = {"cpu": cpu, "wall": wall}
            calls[f"{method} jit(simulate)"] = lambda jf=jf: jax.block_until_ready(jf(p, q0, qd0))
            _, cpu, wall = C.timed(calls[f"{method} through simulate"])  # first call: checks + compile
            compile_s[f"{method} through simulate"] = {"cpu": cpu, "wall": wall}
        times = C.interleave(calls, rounds=rounds)
        cpu = {k: v["cpu"] for k, v in times.items()}
        row = dict(
            problem=problem,
            solver=sname,
            horizon=float(ts[-1]),
            steps=steps,
            compile=compile_s,
            time={k: C.median(v) for k, v in cpu.items()},
            time_wall={k: C.median(v["wall"]) for k, v in times.items()},
            ratio={k: C.paired_ratio(cpu[k], cpu["hand"]) for k in cpu if k != "hand"},
            simulate_overhead={
                m: C.median(np.asarray(cpu[f"{m} through simulate"]) - np.asarray(cpu[m]))
                for m in ("appell", "lagrange")
                if f"{m} through simulate" in cpu
            },
        )
        rows.append(row)
        C.log(
            f"  {problem}/{sname}: appell/hand {row['ratio']['appell']:.2f}x  lagrange/hand "
            f"{row['ratio']['lagrange']:.2f}x  (hand {row['time']['hand'] * 1e3:.2f} ms)"
        )
    return rows


RECORDS = [(), ("multipliers",), ("energy",), ("residual",), ("multipliers", "energy", "residual")]
QUICK_RECORDS = [(), ("multipliers", "energy", "residual")]


def records(rounds: int, quick: bool) -> list:
    rows = []
    v = PB.variator(T=10.0, n=1001)
    g = PB.generic(T=10.0, n=1001)
    probs = [("variator", v.mech, v.params, v.ts, v.q0, v.qd0, (0,))]
    if not quick:
        probs.append(("generic", g.mech, g.params, g.ts, g.q0, g.qd0, g.independent))
    for name, mech, p, ts, q0, qd0, ind in probs:
        for method in ("appell",) if quick else ("appell", "lagrange"):
            calls, compile_s = {}, {}
            for rec in QUICK_RECORDS if quick else RECORDS:
                fn, y0 = C.jaxnh_solver_fn(
                    mech,
                    method,
                    q0,
                    qd0,
                    p,
                    ts,
                    C.SOLVERS["DOP853"](),
                    record=rec,
                    independent=ind if method == "appell" else None,
                )
                key = "+".join(rec) or "nothing"
                calls[key], compile_s[key], _ = _compile(fn, p, y0)
            times = C.interleave(calls, rounds=rounds)
            cpu = {k: t["cpu"] for k, t in times.items()}
            row = dict(
                problem=name,
                method=method,
                n_report=int(ts.shape[0]),
                compile=compile_s,
                time={k: C.median(t) for k, t in cpu.items()},
                ratio={k: C.paired_ratio(cpu[k], cpu["nothing"]) for k in cpu},
            )
            rows.append(row)
            C.log(f"  record {name}/{method}: " + "  ".join(f"{k} {r:.3f}x" for k, r in row["ratio"].items()))
    return rows


def rheonomic(rounds: int) -> list:
    rows = []
    for rh in (False, True):
        g = PB.generic(T=20.0, n=201, rheonomic=rh)
        calls, steps, compile_s = {}, {}, {}
        for method in ("appell", "lagrange"):
            fn, y0 = C.jaxnh_solver_fn(
                g.mech,
                method,
                g.q0,
                g.qd0,
                g.params,
                g.ts,
                C.SOLVERS["DOP853"](),
                independent=g.independent if method == "appell" else None,
            )
            calls[method], compile_s[method], comp = _compile(fn, g.params, y0)
            steps[method] = int(comp(g.params, y0, C.f64(1e-8), C.f64(1e-10))[2])
        fn = C.hand_solver_fn(PB.generic_rhs_jax, lambda ys, ts, p: ys, g.ts, C.SOLVERS["DOP853"]())
        calls["hand"], compile_s["hand"], comp = _compile(fn, g.params, (g.q0, g.qd0))
        steps["hand"] = int(comp(g.params, (g.q0, g.qd0), C.f64(1e-8), C.f64(1e-10))[2])
        times = C.interleave(calls, rounds=rounds)
        cpu = {k: t["cpu"] for k, t in times.items()}
        row = dict(
            rheonomic=rh,
            steps=steps,
            compile=compile_s,
            step_time={k: C.median(t) / steps[k] for k, t in cpu.items()},
            ratio={k: C.paired_ratio(cpu[k], cpu["hand"]) for k in ("appell", "lagrange")},
        )
        rows.append(row)
        C.log(
            f"  {'rheonomic' if rh else 'time-invariant'}: per step "
            + "  ".join(f"{k} {t * 1e6:.1f} us" for k, t in row["step_time"].items())
        )
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="variator only, jaxnh Tsit5, fewer records and rounds")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rounds = 5 if a.quick else 9
    out = dict(quick=a.quick)
    out["rhs_cost"] = rhs_cost("variator", ["Tsit5u"] if a.quick else ["Tsit5", "Tsit5u", "DOP853"], rounds)
    if not a.quick:
        out["rhs_cost"] += rhs_cost("generic", ["Tsit5u", "DOP853"], rounds)
    out["records"] = records(rounds, a.quick)
    out["rheonomic"] = [] if a.quick else rheonomic(rounds)
    out["seconds"] = time.perf_counter() - t0
    C.log(f"[overhead] wrote {C.save('overhead', out)} in {out['seconds']:.0f} s")


if __name__ == "__main__":
    main()
