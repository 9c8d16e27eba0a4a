"""The size study: a car pulling N trailers (s = N + 3, m = N + 1; benchmarks/mechanisms/chain.py).

1. First answers, fresh processes (every core, no compilation cache, the
   user's defaults): `import jaxnh` + the first `simulate` against SymPy's whole
   pipeline (import, `KanesMethod` derivation, `lambdify`, `solve_ivp` RK45 at
   the same tolerances), 2 ≤ N ≤ 8.
2. Steady solves, in this process (after compilation): a plain `simulate`
   call against the lambdified NumPy right-hand side in `solve_ivp` and
   against the SymPy equations printed as JAX source in `diffrax.Tsit5`
   ("by hand in JAX"), 2 ≤ N ≤ 8.
3. Growth: first answers for N = 1 … 32 of `method="appell"`,
   `"lagrange"` (the default) and of a first gradient (`jax.grad` of the final coordinates'
   sum with respect to every parameter), with the fitted exponent of
   t ∝ N^k (of the time after the import).

Errors: against Lagrange's equations with multipliers written out by hand in
NumPy (`chain.lagrange_numpy`; it agrees with SymPy's Kane equations to 1e-13)
solved by SciPy's DOP853 at rtol 1e-12; a gradient against a central
difference of that reference along a random direction. A fresh process that
takes more than `common.MAX_RSS_GB` of memory is stopped and reported.

    python -m benchmarks.size [--quick] [--growth N ...]
"""

from __future__ import annotations

import argparse
import time

from . import common as C


C.pin()  # before JAX starts

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402

from .mechanisms import chain as CH  # noqa: E402


JAXNH_CHILD = """
import jax, jax.numpy as jnp, numpy as np
import jaxnh as nh
{cache}
from benchmarks.mechanisms import chain as CH
{imported}
N = {N}
p = CH.params(N)
q0, qd0 = jnp.array({q0}), jnp.array({qd0})
mech = CH.mechanism(N)
if "{kind}" == "gradient":
    g = jax.grad(lambda p: jnp.sum(nh.simulate(mech, p, q0, qd0, CH.report_times()).q[-1]))(p)
    OUT["grad"] = np.asarray(CH.param_vector(g))
else:
    try:
        sol = nh.simulate(mech, p, q0, qd0, CH.report_times(), method="{kind}")
        OUT.update(q=np.asarray(sol.q), qd=np.asarray(sol.qd), steps=int(sol.stats["num_steps"]))
    except nh.SimulationError as e:
        OUT["message"] = f"{{type(e).__name__}}: {{e}}"
"""

SYMPY_CHILD = """
import numpy as np
{pipeline}
{imported}
rhs, _ = numpy_rhs({N})
s = solve(rhs, np.array({y0}), np.array({P}), np.linspace(0.0, {T}, {n}), {rtol}, {atol})
OUT.update(y=s.y.T, nfev=s.nfev, message=s.message)
"""


DEFAULT = "lagrange"  # simulate's default formulation: the one compared with SymPy's pipeline


class Case:
    """Everything about one N: initial state, SymPy's right-hand sides, the reference."""

    def __init__(self, N: int, ns: dict | None):
        self.N, self.p = N, CH.params(N)
        self.q0, self.qd0 = CH.initial_state(N, self.p)
        self.ts = CH.report_times()
        self.y0 = CH.kane_state(self.q0, self.qd0)
        self.P = np.asarray(CH.param_vector(self.p))
        if N <= 8 and ns is not None:  # SymPy's peers (its derivation grows fast: 5 min of CPU at N = 16)
            self.np_rhs, _ = ns["numpy_rhs"](N)
            self.hand = CH.load_source(CH.jax_source(N, ns))
        self.q_ref, self.qd_ref = CH.reference(N, self.p, self.q0, self.qd0, self.ts)

    def loss(self, P) -> float:
        """The gradient's loss, sum of the final coordinates, from the reference."""
        return float(np.sum(CH.reference(self.N, CH.param_dict(self.N, P), self.q0, self.qd0, self.ts)[0][-1]))

    def child(self, kind: str, cache: bool = False) -> str:
        if kind == "sympy":
            return SYMPY_CHILD.format(
                imported=C.IMPORTED,
                pipeline=CH.SYMPY_PIPELINE,
                N=self.N,
                y0=list(self.y0),
                P=list(self.P),
                T=CH.T_END,
                n=CH.N_REPORT,
                rtol=C.RTOL,
                atol=C.ATOL,
            )
        return JAXNH_CHILD.format(
            imported=C.IMPORTED,
            N=self.N,
            q0=list(map(float, self.q0)),
            qd0=list(map(float, self.qd0)),
            kind=kind,
            cache="nh.enable_compilation_cache()" if cache else "",
        )

    def error(self, kind: str, out: dict) -> float:
        if kind == "gradient":
            rng = np.random.default_rng(self.N)
            # b and L move the axles, so the fixed qd0 would break the knife edges: left out of the direction
            keep = np.concatenate([np.full(np.size(self.p[k]), k not in ("b", "L")) for k in CH.KEYS])
            d = self.P * rng.choice([-1.0, 1.0], self.P.size) * keep
            eps = 1e-4
            fd = (self.loss(self.P + eps * d) - self.loss(self.P - eps * d)) / (2 * eps)
            return abs(float(np.asarray(out["grad"]) @ d) - fd) / max(abs(fd), 1e-300)
        if "message" in out and kind != "sympy":
            return float("nan")
        if kind == "sympy":
            q, qd = CH.kane_unpack(np.asarray(out["y"]))
        else:
            q, qd = np.asarray(out["q"]), np.asarray(out["qd"])
        if q.shape != self.q_ref.shape or not np.all(np.isfinite(q)):
            return float("nan")
        return C.max_error(q, qd, self.q_ref, self.qd_ref)


def first_answers(cases: dict, plan: list, repeats: dict) -> dict:
    """plan: [(N, kind)], each run repeats[(N, kind)] times in fresh processes, interleaved."""
    rows = {
        f"{N} {k}": dict(N=N, kind=k, wall=[], cpu=[], after_import=[], cpu_after_import=[], error=None, note="")
        for N, k in plan
    }
    for r in range(max(repeats.values())):
        for N, kind in plan:
            if r >= repeats[(N, kind)]:
                continue
            row = rows[f"{N} {kind}"]
            env = {"JAXNH_CACHE_DIR": C.cache_dirs()[0]}
            try:
                out = C.fresh(cases[N].child(kind), env)
            except RuntimeError as e:
                row["note"] = str(e).strip().splitlines()[-1][:300]
                C.log(f"[size] N={N} {kind}: FAILED {row['note']}")
                continue
            row["wall"].append(out["wall"])
            row["cpu"].append(out["cpu"])
            row["after_import"].append(out["wall"] - out["import"])
            row["cpu_after_import"].append(out["cpu"] - out["import_cpu"])
            row["peak_rss_gb"] = max(row.get("peak_rss_gb", 0.0), out["peak_rss_gb"])
            if row["error"] is None:
                row["error"] = cases[N].error(kind, out)
                msg = str(out.get("message", ""))
                if msg and "success" not in msg.lower():
                    row["note"] = msg[:300]
            C.log(f"[size] N={N} {kind}: {out['wall']:.2f} s wall, {out['cpu']:.2f} s CPU, error {row['error']:.1e}")
    for row in rows.values():
        for k in ("wall", "cpu", "after_import", "cpu_after_import"):
            row[f"{k}_median"] = C.median(row[k]) if row[k] else None
    return rows


def steady(cases: dict, ns_cmp, quick: bool) -> dict:
    out = {}
    for N in ns_cmp:
        c = cases[N]
        mech = CH.mechanism(N)
        P = jnp.asarray(c.P)

        @jax.jit
        def hand(P, c=c):
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(c.hand),
                diffrax.Tsit5(),
                c.ts[0],
                c.ts[-1],
                None,
                jnp.asarray(c.y0),
                args=P,
                saveat=diffrax.SaveAt(ts=c.ts),
                stepsize_controller=diffrax.PIDController(rtol=C.RTOL, atol=C.ATOL),
            )
            return sol.ys, sol.stats["num_steps"]

        ts_np = np.asarray(c.ts)
        calls = {
            "jaxnh": lambda c=c, mech=mech: jax.block_until_ready(nh.simulate(mech, c.p, c.q0, c.qd0, c.ts)),
            "SciPy": lambda c=c: ns_solve(c.np_rhs, c.y0, c.P, ts_np, C.RTOL, C.ATOL),
            "hand JAX": lambda P=P, hand=hand: jax.block_until_ready(hand(P)),
        }
        row = {}
        for k, fn in calls.items():
            res = fn()
            if k == "jaxnh":
                q, qd, steps = res.q, res.qd, float(res.stats["num_steps"])
            elif k == "SciPy":
                (q, qd), steps = CH.kane_unpack(res.y.T), res.nfev / 6
            else:
                (q, qd), steps = CH.kane_unpack(np.asarray(res[0])), float(res[1])
            row[k] = dict(error=C.max_error(q, qd, c.q_ref, c.qd_ref), steps=steps)
        many = {k: C.repeat(fn, 0.05) for k, fn in calls.items()}
        T = C.interleave({k: m for k, (m, _) in many.items()}, rounds=5 if quick else 7, budget=10 if quick else 60)
        for k, (_, n) in many.items():
            row[k].update(cpu=C.median(np.asarray(T[k]["cpu"]) / n), rounds=len(T[k]["cpu"]))
        row["SciPy / jaxnh"] = C.paired_ratio(
            np.asarray(T["SciPy"]["cpu"]) / many["SciPy"][1], np.asarray(T["jaxnh"]["cpu"]) / many["jaxnh"][1]
        )
        row["jaxnh / hand JAX"] = C.paired_ratio(
            np.asarray(T["jaxnh"]["cpu"]) / many["jaxnh"][1], np.asarray(T["hand JAX"]["cpu"]) / many["hand JAX"][1]
        )
        C.log(f"[size] steady N={N}: {row}")
        out[str(N)] = row
    return out


def _ok(err) -> bool:
    return err is not None and bool(np.isfinite(err))


def ns_solve(rhs, y0, P, ts, rtol, atol):
    from scipy.integrate import solve_ivp

    return solve_ivp(rhs, (ts[0], ts[-1]), y0, t_eval=ts, rtol=rtol, atol=atol, args=(P,))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N = 2, 4 compared, growth from N = 1 to 4, one repeat")
    ap.add_argument("--repeats", type=int, default=None, help="fresh processes per target point (default 5, quick 1)")
    ap.add_argument(
        "--growth",
        type=int,
        nargs="+",
        metavar="N",
        help="only the first answers of both formulations for these N (no SymPy, no steady solves)",
    )
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    if a.growth:
        R = a.repeats or 1
        cases = {N: Case(N, None) for N in a.growth}
        plan = [(N, k) for N in a.growth for k in ("lagrange", "appell")]
        fa = first_answers(cases, plan, {nk: R for nk in plan})
        for key, row in fa.items():
            C.log(
                f"[size] {key}: after import {row['after_import_median']} s wall, error {row['error']}, "
                f"peak {row.get('peak_rss_gb')} GB"
            )
        C.save("size_growth", dict(first_answers=fa, repeats=R, seconds=time.perf_counter() - t0))
        return
    ns_cmp = (2, 4) if a.quick else (2, 3, 4, 5, 6, 7, 8)
    ns_grow = (1, 4) if a.quick else (1, 2, 4, 8, 16, 32)
    big = () if a.quick else (16,)
    R = a.repeats or (1 if a.quick else 5)
    r_grow = max(1, min(R, 3))
    ns = CH.sympy_namespace()
    cases = {N: Case(N, ns) for N in sorted(set(ns_cmp) | set(ns_grow))}
    C.log(f"[size] references ready ({time.perf_counter() - t0:.0f} s)")
    repeats = {}
    for N in ns_cmp:
        repeats[(N, DEFAULT)] = repeats[(N, "sympy")] = R
    for N in ns_grow:
        for k in ("appell", "lagrange", "gradient"):
            repeats.setdefault((N, k), R if N in big else r_grow)
    plan = sorted(repeats, key=lambda nk: (nk[0], nk[1]))
    fa = first_answers(cases, plan, repeats)
    st = steady(cases, ns_cmp, a.quick)
    growth = {}
    for k in ("appell", "lagrange", "gradient"):
        rows = [fa[f"{N} {k}"] for N in ns_grow]  # answers only: a failed solve is left out of the fit
        pts = [(r["N"], r["cpu_after_import_median"]) for r in rows if r["cpu_after_import_median"] and _ok(r["error"])]
        if len(pts) >= 2:
            growth[k] = dict(exponent=C.growth_exponent(*zip(*pts)), points=pts)
    C.log(f"[size] growth: {growth}")
    C.save(
        "size",
        dict(
            first_answers=fa,
            steady=st,
            growth=growth,
            default=DEFAULT,
            ns_compare=ns_cmp,
            ns_growth=ns_grow,
            repeats=R,
            rtol=C.RTOL,
            atol=C.ATOL,
            quick=a.quick,
            seconds=time.perf_counter() - t0,
        ),
    )


if __name__ == "__main__":
    main()
