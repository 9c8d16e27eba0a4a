"""Work-precision diagrams: max error over the report times against run time.

Contenders, on one problem, over a tolerance sweep rtol = 1e-3 … 1e-12
(atol = rtol/100):
* jaxnh "appell" and "lagrange" in diffrax/jaxnh solvers (compiled solve:
  `simulate`'s jitted inner function, tolerances traced so each contender
  compiles once);
* the hand-written right-hand side (eq. (9) for the variator; Lagrange's
  equations written out for the generic mechanism) in the same solvers — the
  cost of deriving the equations automatically;
* an implicit solver (Kvaerno5) at a few tolerances;
* SciPy `solve_ivp` (RK45, DOP853, LSODA, Radau) on a hand-written NumPy
  right-hand side.

Errors: against the closed form (variator) or a reference solve (generic:
SciPy DOP853 at rtol 2.5e-14 on the NumPy right-hand side, checked against
jaxnh "appell" in DOP853 at rtol 1e-13). Time: median over interleaved rounds
after compilation; compile time reported separately.

    python -m benchmarks.work_precision [--problem variator|generic|both] [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import time

import jax
import numpy as np

from . import problems as PB


FULL_TOLS = [10.0**-k for k in range(3, 14)]
QUICK_TOLS = [1e-4, 1e-7, 1e-10, 1e-13]
IMPLICIT_TOLS = [1e-4, 1e-6, 1e-8]
SCIPY_MIN_RTOL = 2.5e-14


GENERIC_TOLS = [1e-3, 1e-4, 1e-6, 1e-8, 1e-9, 1e-10, 1e-12]


def _config(quick: bool, problem: str = "variator"):
    if quick:
        return dict(
            tols=QUICK_TOLS,
            solvers=["Tsit5", "DOP853"],
            methods=("appell",),
            implicit=False,
            scipy=["DOP853"],
            rounds=5,
            budget=1.0,
        )
    # the generic mechanism costs 10–100× more per solve and 3–8× more to compile: fewer points and rounds
    generic = problem == "generic"
    return dict(
        tols=GENERIC_TOLS if generic else FULL_TOLS,
        solvers=["Tsit5", "Tsit5u", "Dopri5", "Dopri8", "DOP853"],
        methods=("appell", "lagrange"),
        implicit=True,
        scipy=["RK45", "DOP853", "LSODA", "Radau"],
        rounds=7 if generic else 11,
        budget=3.0,
    )


def _problem(name: str):
    """Everything a sweep needs: jaxnh inputs, hand-written forms, reference."""
    if name == "variator":
        v = PB.variator()
        f_np, unpack_np = PB.eq9_numpy(v.params)
        y0_np = np.array([0.0, 0.0, float(v.qd0[0])])
        return dict(
            mech=v.mech,
            params=v.params,
            ts=v.ts,
            q0=v.q0,
            qd0=v.qd0,
            independent=(0,),
            hand_vf=PB.eq9_jax,
            hand_unpack=PB.eq9_unpack,
            hand_y0=PB.eq9_state(v),
            np_f=f_np,
            np_y0=y0_np,
            np_unpack=lambda sol: unpack_np(sol.y.T, sol.t),
            q_ref=np.asarray(v.q_ref),
            qd_ref=np.asarray(v.qd_ref),
            reference="closed form (Gauss-Legendre quadrature)",
            hand_label="eq. (9) by hand",
        )
    g = PB.generic()
    s = g.q0.shape[0]
    f_np = PB.generic_rhs_numpy(g.params)
    y0_np = np.concatenate([np.asarray(g.q0), np.asarray(g.qd0)])
    ref = C.scipy_solve(f_np, y0_np, g.ts, "DOP853", SCIPY_MIN_RTOL, 1e-16)
    q_ref, qd_ref = ref.y.T[:, :s], ref.y.T[:, s:]
    # cross-check the reference against jaxnh itself (independent derivation)
    fn, y0 = C.jaxnh_solver_fn(g.mech, "appell", g.q0, g.qd0, g.params, g.ts, C.DOP853(), independent=g.independent)
    q, qd, _, _ = fn(g.params, y0, C.f64(1e-13), C.f64(1e-15))
    agreement = C.max_error(q, qd, q_ref, qd_ref)
    return dict(
        mech=g.mech,
        params=g.params,
        ts=g.ts,
        q0=g.q0,
        qd0=g.qd0,
        independent=g.independent,
        hand_vf=PB.generic_rhs_jax,
        hand_unpack=lambda ys, ts, p: ys,
        hand_y0=(g.q0, g.qd0),
        np_f=f_np,
        np_y0=y0_np,
        np_unpack=lambda sol: (sol.y.T[:, :s], sol.y.T[:, s:]),
        q_ref=q_ref,
        qd_ref=qd_ref,
        hand_label="Lagrange by hand (dense KKT solve)",
        reference=f"SciPy DOP853 rtol {SCIPY_MIN_RTOL:g}, atol 1e-16 (agrees with jaxnh appell DOP853 "
        f"rtol 1e-13 to {agreement:.1e})",
    )


def run(problem: str, quick: bool) -> dict:
    cfg = _config(quick, problem)
    t_start = time.perf_counter()
    P = _problem(problem)
    C.log(f"[work_precision:{problem}] reference: {P['reference']}")
    contenders = {}  # name -> dict(kind, method, solver, call(rtol, atol) -> (q, qd, steps))
    compile_s = {}

    def add_jax(name, kind, method, solver_name, fn, y0, tols):
        args = (P["params"], y0, C.f64(1e-8), C.f64(1e-10))
        compiled, secs = C.compile_aot(fn, *args)
        compile_s[name] = secs
        contenders[name] = dict(
            kind=kind,
            method=method,
            solver=solver_name,
            tols=tols,
            call=lambda r, a, R, A, c=compiled, y0=y0: c(P["params"], y0, R, A),
        )
        C.log(f"  compiled {name:<28s} {secs['cpu']:6.2f} s cpu, {secs['wall']:6.2f} s wall")

    for sname in cfg["solvers"]:
        for method in cfg["methods"]:
            fn, y0 = C.jaxnh_solver_fn(
                P["mech"],
                method,
                P["q0"],
                P["qd0"],
                P["params"],
                P["ts"],
                C.SOLVERS[sname](),
                independent=P["independent"] if method == "appell" else None,
            )
            add_jax(f"{method}/{sname}", "jaxnh", method, sname, fn, y0, cfg["tols"])
        fn = C.hand_solver_fn(P["hand_vf"], P["hand_unpack"], P["ts"], C.SOLVERS[sname]())
        add_jax(f"hand/{sname}", "hand", "hand", sname, fn, P["hand_y0"], cfg["tols"])
    if cfg["implicit"]:
        for method in ("appell",):
            fn, y0 = C.jaxnh_solver_fn(
                P["mech"],
                method,
                P["q0"],
                P["qd0"],
                P["params"],
                P["ts"],
                C.SOLVERS["Kvaerno5"](),
                independent=P["independent"],
            )
            add_jax(f"{method}/Kvaerno5", "jaxnh", method, "Kvaerno5", fn, y0, IMPLICIT_TOLS)
        fn = C.hand_solver_fn(P["hand_vf"], P["hand_unpack"], P["ts"], C.SOLVERS["Kvaerno5"]())
        add_jax("hand/Kvaerno5", "hand", "hand", "Kvaerno5", fn, P["hand_y0"], IMPLICIT_TOLS)
    for m in cfg["scipy"]:

        def call(r, a, R, A, m=m):
            sol = C.scipy_solve(P["np_f"], P["np_y0"], P["ts"], m, max(r, SCIPY_MIN_RTOL), a)
            if not sol.success:
                nan = np.full_like(P["q_ref"], np.nan)
                return nan, nan, sol.nfev
            q, qd = P["np_unpack"](sol)
            return q, qd, sol.nfev

        tols = [t for t in cfg["tols"] if not (m == "Radau" and t < 1e-10) and t >= 1e-13]  # Radau: seconds below
        contenders[f"scipy/{m}"] = dict(kind="scipy", method="numpy", solver=m, tols=tols, call=call)

    points = []
    for rtol in cfg["tols"]:
        r, a = C.tol_pair(rtol)
        R, A = C.f64(r), C.f64(a)  # made once: creating a device scalar costs ~0.1 ms per call
        calls, meta = {}, {}
        for name, c in contenders.items():
            if rtol not in c["tols"]:
                continue
            q, qd, steps, *_ = jax.block_until_ready(c["call"](r, a, R, A))  # warm-up, and the error
            meta[name] = (C.max_error(q, qd, P["q_ref"], P["qd_ref"]), int(np.asarray(steps)))
            calls[name] = lambda f=c["call"]: jax.block_until_ready(f(r, a, R, A))
        heavy = {k for k in calls if k.startswith("scipy/")}
        times = _interleave_heavy(calls, heavy, cfg["rounds"], cfg["budget"])
        for name, tt in times.items():
            c = contenders[name]
            err, steps = meta[name]
            t = C.median(tt["cpu"])
            points.append(
                dict(
                    name=name,
                    kind=c["kind"],
                    method=c["method"],
                    solver=c["solver"],
                    rtol=r,
                    atol=a,
                    error=err,
                    time=t,
                    time_wall=C.median(tt["wall"]),
                    times=tt,
                    steps=steps,
                    step_cost=t / steps if c["kind"] != "scipy" and steps else None,
                    compile=compile_s.get(name),
                )
            )
        C.log(
            f"  rtol {r:.0e}: "
            + "  ".join(
                f"{n}={C.median(t['cpu']) * 1e3:.2f}ms/{meta[n][0]:.0e}"
                for n, t in times.items()
                if n.endswith(("DOP853", "Tsit5u"))
            )
        )
    return dict(
        problem=problem,
        quick=quick,
        reference=P["reference"],
        hand_label=P["hand_label"],
        tols=cfg["tols"],
        compile=compile_s,
        points=points,
        seconds=time.perf_counter() - t_start,
        n_report=int(P["ts"].shape[0]),
        horizon=float(P["ts"][-1]),
    )


def _interleave_heavy(calls, heavy, rounds, budget):
    """Rounds over every contender; the slow ones (SciPy) only until `budget` s of theirs is spent (≥ 3 calls)."""
    times = {k: {"cpu": [], "wall": []} for k in calls}
    spent = 0.0
    for r in range(rounds):
        for k, fn in calls.items():
            if k in heavy and r >= 3 and spent > budget:
                continue
            _, cpu, wall = C.timed(fn)
            times[k]["cpu"].append(cpu)
            times[k]["wall"].append(wall)
            if k in heavy:
                spent += wall
    return times


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", choices=["variator", "generic", "both"], default="both")
    ap.add_argument(
        "--quick", action="store_true", help="variator only, appell and hand in Tsit5 and DOP853, 4 tolerances"
    )
    a = ap.parse_args(argv)
    probs = ["variator", "generic"] if a.problem == "both" else [a.problem]
    if a.quick and a.problem == "both":
        probs = ["variator"]
    for prob in probs:
        out = run(prob, a.quick)
        C.log(f"[work_precision:{prob}] wrote {C.save(f'wp_{prob}', out)} in {out['seconds']:.0f} s")


if __name__ == "__main__":
    main()
