"""Size and cost of one vector-field evaluation, per formulation (issue 16, item 3).

For the variator (and the generic s = 10, m = 3 mechanism of benchmarks/problems.py),
each formulation's vector field as `simulate` integrates it — "lagrange", "appell",
"substituted": `formulation(...).vector_field(t, y, params)` flattened to scalar
operations when it is small (`jaxnh._scalarize`; for the variator also "appell, not
flattened", the same field as traced) — and the hand-written one (eq. (9) for the
variator; Lagrange's equations written out with a dense solve for the generic
mechanism) is measured alone:

* **jaxpr eqns**: equations of its jaxpr (what JAX traces);
* **StableHLO ops**: operations of the lowered module (what XLA is given);
* **HLO instructions**: instructions of the optimised, compiled module, fusion bodies
  included (what XLA makes of it), and **kernels**: run-time instructions of its
  entry computation (fusions, library calls and other unfused instructions: each
  has a fixed launch cost on the CPU runtime);
* **per evaluation**: CPU time of one evaluation, the field compiled in a
  `lax.fori_loop` whose every iteration perturbs t and y (so nothing is hoisted),
  and per state in a `vmap` batch of 1000 states;
* **per step**: CPU time per step of a whole solve in the lean loop
  (`jaxnh._lean.lean_solve`, DOP853, rtol 1e-10) with that field, and the ratio to the
  hand-written field at equal steps (issue 16's target: derived ≤ 1.3× eq. (9)).

    python -m benchmarks.field_size [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import re

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxnh._lean import lean_solve
from jaxnh._scalarize import scalarized
from jaxnh.equations import formulation

from . import problems as PB


_FREE = {"parameter", "tuple", "get-tuple-element", "bitcast", "constant"}


def hlo_instructions(text: str) -> int:
    return len(re.findall(r"^\s+(?:ROOT )?%?\S+ = ", text, flags=re.M))


def entry_kernels(text: str) -> int:
    entry = text[text.index("ENTRY") :]
    entry = entry[: entry.index("\n}")]
    return sum(1 for op in re.findall(r"=\s*\S+\s+([a-z][a-z0-9-]*)\(", entry) if op not in _FREE)


def stablehlo_ops(text: str) -> int:
    return len(re.findall(r"^\s+(?:%\S+(?::\d+)?\s*=\s*)?\"?stablehlo\.", text, flags=re.M))


def fields(problem: str):
    """name -> (flat field f(t, y, p), y0 flat, params), and the report times of the solve."""
    if problem == "variator":
        v = PB.variator()
        mech, p, q0, qd0, ind, ts = v.mech, v.params, v.q0, v.qd0, (0,), v.ts
        hand_state = PB.eq9_state(v)
        hand = PB.eq9_jax
        methods = ("lagrange", "appell", "substituted")
    else:
        g = PB.generic(T=10.0, n=101)
        mech, p, q0, qd0, ind, ts = g.mech, g.params, g.q0, g.qd0, g.independent, g.ts
        hand_state = (g.q0, g.qd0)
        hand = PB.generic_rhs_jax
        methods = ("lagrange", "appell")
    out = {}
    for method in methods:
        form = formulation(mech, method, q0, qd0, ts[0], p, None if method == "lagrange" else ind)
        y0, unravel = ravel_pytree(form.state(q0, qd0, ts[0], p))
        # as simulate integrates it: flattened to scalar operations when small (jaxnh._scalarize)
        for name, vf in ((method, scalarized(form.vector_field)), (f"{method}, not flattened", form.vector_field)):
            if name.endswith("not flattened") and method != "appell":
                continue
            out[name] = (
                (lambda vf, unravel: lambda t, y, p: ravel_pytree(vf(t, unravel(y), p))[0])(vf, unravel),
                y0,
                p,
            )
    y0, unravel = ravel_pytree(hand_state)
    out["hand"] = ((lambda unravel: lambda t, y, p: ravel_pytree(hand(t, unravel(y), p))[0])(unravel), y0, p)
    return out, ts


def field_loop(f, y, p, n):
    t = C.f64(0.3)

    def body(i, acc):
        dy = f(t + i * 1e-9, y + 1e-30 * acc, p)
        return acc + 1e-30 * dy

    g = jax.jit(lambda y, p: jax.lax.fori_loop(0, n, body, jnp.zeros_like(y)))
    c = g.lower(y, p).compile()
    return lambda: C.block(c(y, p))


def batch_call(f, y, p, n=1000):
    ys = y[None] * (1 + 1e-3 * jnp.arange(n)[:, None] / n)
    tt = 0.3 + 1e-3 * jnp.arange(n) / n
    g = jax.jit(jax.vmap(lambda t, y: f(t, y, p)))
    c = g.lower(tt, ys).compile()
    return lambda: C.block(c(tt, ys))


def measure(problem: str, quick: bool) -> dict:
    fs, ts = fields(problem)
    rows = {}
    calls = {}
    n_eval = 20_000 if problem == "variator" else 2_000
    for name, (f, y0, p) in fs.items():
        t = C.f64(0.3)
        jaxpr = jax.make_jaxpr(f)(t, y0, p)
        lowered = jax.jit(f).lower(t, y0, p)
        compiled = lowered.compile()
        text = compiled.as_text()
        rows[name] = dict(
            state=int(y0.shape[0]),
            jaxpr_eqns=len(jaxpr.jaxpr.eqns),
            stablehlo_ops=stablehlo_ops(lowered.as_text()),
            hlo_instructions=hlo_instructions(text),
            kernels=entry_kernels(text),
        )
        solve = jax.jit(lambda y0, p, f=f: lean_solve(f, y0, p, ts, method="dop853", rtol=1e-10, atol=1e-12))
        sc = solve.lower(y0, p).compile()
        sol = sc(y0, p)
        rows[name]["solve_steps"] = int(sol.stats["num_steps"])
        rows[name]["solve_status"] = int(sol.status)
        rows[name]["solve_hlo_instructions"] = hlo_instructions(sc.as_text())
        calls[f"{name}/field"] = (field_loop(f, y0, p, n_eval), n_eval)
        calls[f"{name}/batch"] = (batch_call(f, y0, p), 1000)
        calls[f"{name}/solve"] = (lambda sc=sc, y0=y0, p=p: C.block(sc(y0, p)), rows[name]["solve_steps"])
        C.log(f"[field_size] {problem} {name}: {rows[name]}")
    times = C.interleave({k: v[0] for k, v in calls.items()}, rounds=5 if quick else 11)
    for name in rows:
        rows[name]["per_eval"] = C.median(times[f"{name}/field"]["cpu"]) / calls[f"{name}/field"][1]
        rows[name]["per_eval_batch"] = C.median(times[f"{name}/batch"]["cpu"]) / 1000
        rows[name]["per_step"] = C.median(times[f"{name}/solve"]["cpu"]) / rows[name]["solve_steps"]
        for kind in ("field", "batch", "solve"):
            num = np.asarray(times[f"{name}/{kind}"]["cpu"]) / calls[f"{name}/{kind}"][1]
            den = np.asarray(times[f"hand/{kind}"]["cpu"]) / calls[f"hand/{kind}"][1]
            rows[name][f"{kind}_over_hand"] = float(np.median(num / den))
    return rows


def table(header, rows) -> str:
    """A Markdown table."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def section(R: dict | None) -> list:
    """RESULTS.md lines (called by benchmarks/report.py)."""
    if not R:
        return []
    L = [
        "## Size and cost of a vector field, per formulation (issue 16, item 3)",
        "",
        "One evaluation of each formulation's vector field, compiled alone: jaxpr equations, StableHLO operations "
        "of the lowered module, HLO instructions of the optimised module (fusion bodies included) and run-time "
        "kernels of its entry computation; CPU time per evaluation (in a `fori_loop` that perturbs t and y) and "
        "per state in a `vmap` batch of 1000; per step of a whole lean-loop solve (DOP853, rtol 1e-10; a step is "
        "12 evaluations plus the loop). Ratios to the hand-written field are medians of per-round ratios; "
        "`python -m benchmarks.field_size`. The target of issue 16 is derived ≤ 1.3× hand-written at equal steps "
        '(last column). "substituted" is the paper\'s wrong eq. (16): a different ODE.',
        "",
    ]
    for problem, rows in R["problems"].items():
        L += [f"### {problem}", ""]
        tr = []
        for name, r in rows.items():
            tr.append(
                [
                    name,
                    str(r["state"]),
                    str(r["jaxpr_eqns"]),
                    str(r["stablehlo_ops"]),
                    str(r["hlo_instructions"]),
                    str(r["kernels"]),
                    f"{r['per_eval'] * 1e9:.0f} ns",
                    f"{r['field_over_hand']:.2f}×",
                    f"{r['per_eval_batch'] * 1e9:.1f} ns",
                    f"{r['batch_over_hand']:.2f}×",
                    str(r["solve_hlo_instructions"]),
                    str(r["solve_steps"]),
                    f"{r['per_step'] * 1e6:.2f} µs",
                    f"{r['solve_over_hand']:.2f}×",
                ]
            )
        L += [
            table(
                [
                    "field",
                    "state size",
                    "jaxpr eqns",
                    "StableHLO ops",
                    "HLO instr.",
                    "kernels",
                    "per eval",
                    "/ hand",
                    "per eval (batch 1000)",
                    "/ hand",
                    "solve HLO instr.",
                    "solve steps",
                    "per step",
                    "/ hand",
                ],
                tr,
            ),
            "",
        ]
    return L


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="variator only, fewer rounds")
    a = ap.parse_args(argv)
    res = {"problems": {}}
    for problem in ("variator",) if a.quick else ("variator", "generic"):
        res["problems"][problem] = measure(problem, a.quick)
    C.save("field_size", res)
    print("\n".join(section(res)))


if __name__ == "__main__":
    main()
