"""Figures and benchmarks/RESULTS.md from the JSON files in benchmarks/results/.

Every number in RESULTS.md is computed here from those files; nothing is
typed by hand. Run after the benchmarks (run_all does):

    python -m benchmarks.report
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import math
import os

import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxnh._simulate import (  # noqa: E402
    default_solver,
    DOP853_BELOW_RTOL,
    DOPRI8_BELOW_RTOL_LOOPED,
    UNROLL_MAX_OPERATIONS,
    vector_field_operations,
)


_OPS: dict = {}


def operations(problem: str, method: str = "appell") -> int:
    """Size (JAX operations) of the vector field of a work-precision problem in one
    formulation: what `simulate(solver=None)` passes to `default_solver`."""
    if (problem, method) not in _OPS:
        from jaxnh.equations import formulation

        from . import problems as PB

        v = PB.variator() if problem == "variator" else PB.generic()
        ind = (0,) if problem == "variator" else v.independent
        form = formulation(v.mech, method, v.q0, v.qd0, 0.0, v.params, ind)
        _OPS[problem, method] = vector_field_operations(form, 0.0, form.state(v.q0, v.qd0, 0.0, v.params), v.params)
    return _OPS[problem, method]


def gmean(values) -> float:
    """Geometric mean (of slowdown ratios)."""
    return math.exp(sum(math.log(x) for x in values) / len(values))


def wp_formulations(R):
    """(work-precision run, formulation) for every formulation a run of R holds, variator first."""
    for k in ("wp_variator", "wp_generic"):
        wp = R.get(k)
        if not wp:
            continue
        cv = _curves(wp)
        for method in ("appell", "lagrange"):
            if any(n.startswith(method + "/") for n in cv):
                yield wp, method


def default_key(problem: str, method: str = "appell"):
    """rtol -> the SOLVERS label `simulate(solver=None, method=method)` uses on `problem`."""
    ops = operations(problem, method)
    return lambda r: C.solver_key(default_solver(r, ops, method))


SOLVER_COLORS = {
    "Tsit5": "tab:blue",
    "Tsit5u": "tab:cyan",
    "Dopri5": "tab:green",
    "Dopri8": "tab:olive",
    "DOP853": "tab:red",
    "Kvaerno5": "tab:purple",
    "RK45": "tab:gray",
    "LSODA": "tab:brown",
    "Radau": "tab:pink",
}
METHOD_STYLE = {"appell": ("-", "o"), "lagrange": ("--", "s"), "hand": (":", "^"), "numpy": ("-.", "x")}


def fmt_t(s) -> str:
    if s is None or (isinstance(s, float) and not math.isfinite(s)):
        return "—"
    return f"{s * 1e3:.3g} ms" if s >= 1e-3 else f"{s * 1e6:.3g} µs"


def fmt_x(r) -> str:
    return "—" if r is None or not math.isfinite(r) else f"{r:.2f}×"


def _curves(wp):
    curves = {}
    for p in wp["points"]:
        curves.setdefault(p["name"], []).append(p)
    for v in curves.values():
        v.sort(key=lambda p: -p["rtol"])
    return curves


def _label(name: str, hand_label: str) -> str:
    kind, solver = name.split("/")
    who = {"appell": "jaxnh appell", "lagrange": "jaxnh lagrange", "hand": hand_label, "scipy": "SciPy"}[kind]
    return f"{who}, {solver if kind == 'scipy' else C.SOLVER_LABELS.get(solver, solver)}"


def time_at(curves, name, err):
    if name not in curves:
        return None
    return C.time_at_error([(p["error"], p["time"]) for p in curves[name]], err)


# --------------------------------------------------------------------------- figures


def _plot_curve(ax, pts, name, label, y="error", **kw):
    kind, solver = name.split("/")
    ls, mk = METHOD_STYLE["numpy" if kind == "scipy" else kind]
    xs = [p["time"] for p in pts] if y == "error" else [p["rtol"] for p in pts]
    ys = [p["error"] for p in pts] if y == "error" else [p["step_cost"] * 1e6 for p in pts]
    ax.loglog(xs, ys, ls=ls, marker=mk, ms=4, lw=1.4, color=SOLVER_COLORS.get(solver, "k"), label=label, **kw)


def fig_wp(wp, path):
    """Three panels: (a) solvers (jaxnh appell in each solver, SciPy); (b) formulations (appell, lagrange,
    hand-written) in the two default solvers and diffrax Tsit5; (c) cost per step against rtol."""
    curves = _curves(wp)
    fig, axes = plt.subplots(1, 3, figsize=(19, 6.4), gridspec_kw=dict(width_ratios=[1.25, 1.25, 1]))
    ax, bx, cx = axes
    for name, pts in curves.items():
        kind, solver = name.split("/")
        if kind in ("appell", "scipy"):
            _plot_curve(ax, pts, name, ("SciPy " + solver) if kind == "scipy" else C.SOLVER_LABELS.get(solver, solver))
        if solver in ("Tsit5", "Tsit5u", "DOP853") and kind != "scipy":
            _plot_curve(bx, pts, name, _label(name, "by hand"))
        if kind == "appell" and pts[0].get("step_cost"):
            _plot_curve(cx, pts, name, C.SOLVER_LABELS.get(solver, solver), y="step")
    ax.set_title('(a) solvers: jaxnh "appell" (solid) vs SciPy solve_ivp\non a NumPy RHS (dash-dot)')
    bx.set_title("(b) formulations: appell (solid), lagrange (dashed),\nhand-written equations (dotted)")
    cx.set_title("(c) CPU time per step, jaxnh appell\n(includes the fixed per-call cost)")
    for x in (ax, bx):
        x.set_xlabel("run time per solve (s; process CPU time, median)")
        x.set_ylabel("max abs error over the report times")
        x.axhline(1e-8, color="k", lw=0.6, ls=":")
    cx.set_xlabel("rtol (atol = rtol/100)")
    cx.set_ylabel("µs per step")
    cx.invert_xaxis()
    for x in axes:
        x.grid(True, which="major", alpha=0.3)
        x.legend(fontsize=8, loc="best")
    fig.suptitle(
        f"Work-precision, {wp['problem']} ({wp['horizon']:g} s, {wp['n_report']} report times); "
        f"rtol {max(wp['tols']):g} … {min(wp['tols']):g}; reference: {wp['reference']}",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fig_throughput(tp, path, scipy_time=None):
    fig, ax = plt.subplots(figsize=(8, 5.2))
    groups = {}
    for r in tp["rows"]:
        groups.setdefault((r["kind"], r["solver"]), []).append(r)
    for (kind, solver), rows in groups.items():
        rows.sort(key=lambda r: r["batch"])
        ls, mk = METHOD_STYLE[kind]
        who = "eq. (9) by hand" if kind == "hand" else f"jaxnh {kind}"
        ax.loglog(
            [r["batch"] for r in rows],
            [r["per_trajectory"] for r in rows],
            ls=ls,
            marker=mk,
            lw=1.5,
            color=SOLVER_COLORS.get(solver, "k"),
            label=f"{who}, {C.SOLVER_LABELS.get(solver, solver)}",
        )
    if scipy_time:
        ax.axhline(scipy_time, color="tab:gray", ls="-.", lw=1.2, label="SciPy DOP853, one trajectory at error 1e-8")
        ax.axhline(scipy_time / 150, color="k", ls=":", lw=0.8, label="target: SciPy DOP853 / 150")
    ax.set_xlabel("batch size (jax.vmap)")
    ax.set_ylabel("CPU time per trajectory (s)")
    ax.set_title(f"Batch throughput, variator over 10 s, rtol {tp['rtol']:g} (error ≈ 1e-8)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fig_gradients(gr, path):
    fig, ax = plt.subplots(figsize=(8, 5.2))
    rows = sorted(gr["rows"], key=lambda r: (r["P"], r["only_inertias"]))
    modes = list(dict.fromkeys(k for r in rows for k in r["ratio"] if k != "forward solve"))
    for m in modes:
        pts = [(r["P"], r["ratio"][m]) for r in rows if m in r["ratio"]]
        if pts:
            auto = m.startswith("auto")
            ax.plot(
                *zip(*pts),
                marker="o",
                label=m,
                ls="--" if auto else "-",
                lw=3 if auto else 1.4,
                color="k" if auto else None,
                alpha=0.6 if auto else 1.0,
                zorder=3 if auto else 2,
            )
    ax.axhline(3.0, color="tab:red", lw=0.9, ls=":", label="target 3×")
    if gr.get("forward_max_parameters"):
        ax.axvline(
            gr["forward_max_parameters"],
            color="gray",
            lw=0.9,
            ls="-.",
            label=f"FORWARD_MAX_PARAMETERS = {gr['forward_max_parameters']} (counts q0, qd0 too)",
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("number of differentiated parameters P")
    ax.set_ylabel("gradient CPU time / forward solve CPU time")
    ax.set_title(
        f"Gradient of a trajectory loss, variator, {C.SOLVER_LABELS.get(gr['solver'], gr['solver'])}, "
        f"rtol {gr['rtol']:g}"
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------- tables and targets


def table(header, rows) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def wp_section(wp, title) -> list:
    curves = _curves(wp)
    lines = [
        f"### {title}",
        "",
        f"Reference: {wp['reference']}. Horizon {wp['horizon']:g} s, "
        f"{wp['n_report']} report times; sweep rtol {max(wp['tols']):g} … {min(wp['tols']):g}, atol = rtol/100. "
        f"Figure: `figures/wp_{wp['problem']}.png`.",
        "",
    ]
    errs = [1e-4, 1e-6, 1e-8, 1e-10]
    rows = []
    for name in curves:
        comp = wp["compile"].get(name)
        best = min(curves[name], key=lambda p: p["error"])
        rows.append(
            [_label(name, wp["hand_label"])]
            + [fmt_t(time_at(curves, name, e)) for e in errs]
            + [f"{best['error']:.1e}", f"{comp['cpu']:.1f} s" if comp else "—"]
        )
    lines.append(
        table(["contender"] + [f"time at error {e:g}" for e in errs] + ["smallest error", "compile (CPU)"], rows)
    )
    lines += [
        "",
        "Time at a given error is interpolated log-log between the two sweep points that bracket it "
        "(— when none do). Raw points, wall times and step counts: `results/wp_" + wp["problem"] + ".json`.",
        "",
    ]
    return lines


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def targets(R) -> tuple[list, dict]:
    """Rows (target, goal, measured, met) and the headline numbers."""
    rows, head = [], {}
    ov, wpv, tp, gr, ct = (R.get(k) for k in ("overhead", "wp_variator", "throughput", "gradients", "compile_time"))
    if ov:
        for r in ov["rhs_cost"]:
            if r["problem"] != "variator":
                continue
            a, l_ = r["ratio"]["appell"], r["ratio"]["lagrange"]
            rows.append(
                [
                    f"1. appell vs eq. (9) by hand, {C.SOLVER_LABELS[r['solver']]}, compiled solve",
                    "≤ 1.2×",
                    fmt_x(a),
                    "yes" if a <= 1.2 else f"no (+{(a / 1.2 - 1) * 100:.0f} %)",
                ]
            )
            rows.append(
                [
                    f"1. lagrange vs eq. (9) by hand, {C.SOLVER_LABELS[r['solver']]}, compiled solve",
                    "≤ 1.5×",
                    fmt_x(l_),
                    "yes" if l_ <= 1.5 else f"no (+{(l_ / 1.5 - 1) * 100:.0f} %)",
                ]
            )
            head[f"appell_over_hand_{r['solver']}"] = a
            head[f"lagrange_over_hand_{r['solver']}"] = l_
    if wpv:
        cv = _curves(wpv)
        sc = {
            s: _median([p["step_cost"] for p in cv.get(f"appell/{s}", [])])
            for s in ("Tsit5", "Tsit5u", "DOP853", "Dopri8")
        }
        if sc["DOP853"] and sc["Tsit5"]:
            r = sc["DOP853"] / sc["Tsit5"]
            rows.append(
                [
                    "2. DOP853 step / diffrax Tsit5 step (appell, variator, median over rtol)",
                    "≤ 2×",
                    fmt_x(r),
                    "yes" if r <= 2 else f"no (+{(r / 2 - 1) * 100:.0f} %)",
                ]
            )
            head["dop853_step_over_tsit5"] = r
        for e in (1e-10, 1e-11):
            td = time_at(cv, "appell/DOP853", e)
            others = {s: time_at(cv, f"appell/{s}", e) for s in ("Tsit5", "Dopri8")}
            if td is None or any(v is None for v in others.values()):
                rows.append(
                    [
                        f"2. DOP853 faster than Tsit5 and Dopri8 at error {e:g} (appell, variator)",
                        "faster",
                        "not bracketed",
                        "—",
                    ]
                )
                continue
            ok = all(td < v for v in others.values())
            rows.append(
                [
                    f"2. DOP853 faster than Tsit5 and Dopri8 at error {e:g} (appell, variator)",
                    "faster",
                    f"DOP853 {fmt_t(td)}; Tsit5 {fmt_t(others['Tsit5'])}; Dopri8 {fmt_t(others['Dopri8'])}",
                    "yes" if ok else "no",
                ]
            )
        ts_sc = time_at(cv, "scipy/DOP853", 1e-8)
        jax_best = {n: time_at(cv, n, 1e-8) for n in cv if n.startswith("appell/")}
        jax_best = {k: v for k, v in jax_best.items() if v is not None}
        if ts_sc and jax_best:
            bn = min(jax_best, key=jax_best.get)
            r = ts_sc / jax_best[bn]
            rows.append(
                [
                    f"3. SciPy DOP853 / jaxnh ({bn}), single trajectory at error 1e-8, compiled solve",
                    "≥ 25×",
                    fmt_x(r),
                    "yes" if r >= 25 else f"no ({r / 25 * 100:.0f} % of it)",
                ]
            )
            head["scipy_over_jaxnh_single"] = r
            head["scipy_dop853_at_1e-8"] = ts_sc
        if ts_sc and tp:
            big = [x for x in tp["rows"] if x["batch"] >= 1000 and x["kind"] != "hand"]
            if big:
                b = min(big, key=lambda x: x["per_trajectory"])
                r = ts_sc / b["per_trajectory"]
                rows.append(
                    [
                        f"3. SciPy DOP853 / jaxnh batched ({b['solver']}, batch {b['batch']}, error "
                        f"{b['error_member0']:.0e}), per trajectory",
                        "≥ 150×",
                        fmt_x(r),
                        "yes" if r >= 150 else f"no ({r / 150 * 100:.0f} % of it)",
                    ]
                )
                head["scipy_over_jaxnh_batch"] = r
    if gr:
        for r in sorted(gr["rows"], key=lambda r: r["P"]):
            a = r["ratio"]["auto (simulate default)"]
            cur = r["ratio"]["reverse RecursiveCheckpoint"]
            rows.append(
                [
                    f"4. gradient / forward, P = {r['P']} (auto → {r['auto']}; today's default {fmt_x(cur)})",
                    "≤ 3×",
                    fmt_x(a),
                    "yes" if a <= 3 else f"no (+{(a / 3 - 1) * 100:.0f} %)",
                ]
            )
    if ct:
        for r in ct["rows"]:
            if "error" in r or not r["kind"].startswith("simulate"):
                continue
            c = r["compile"]["cpu"]
            rows.append(
                [
                    f"5. first-call compile: {r['label']} (CPU; wall {r['compile']['wall']:.1f} s)",
                    "≤ 1.5 s",
                    f"{c:.2f} s",
                    "yes" if c <= 1.5 else f"no (+{(c / 1.5 - 1) * 100:.0f} %)",
                ]
            )
    for wp, method in wp_formulations(R):
        for label, pick in (
            ("previous default diffrax Tsit5", lambda r: "Tsit5"),
            ("default_solver(rtol)", default_key(wp["problem"], method)),
        ):
            slow = default_slowdown(wp, pick, method)
            if slow:
                v = list(slow.values())
                worst, mean = max(v), gmean(v)
                rows.append(
                    [
                        f"6. {wp['problem']} {method}: {label} vs the fastest {method} solver at the same "
                        f"error, over rtol {max(slow):g} … {min(slow):g} (mean / worst)",
                        "≈ 1×",
                        f"{fmt_x(mean)} / {fmt_x(worst)}",
                        "yes" if worst <= 1.15 else ("on average" if mean <= 1.15 else "no"),
                    ]
                )
    return rows, head


def default_slowdown(wp, pick, method: str = "appell") -> dict:
    """rtol -> time of the solver `pick(rtol)` picks / time of the fastest explicit solver of the same
    formulation (`method`) at the error it reaches."""
    cv = _curves(wp)
    out = {}
    for r in wp["tols"]:
        key = f"{method}/{pick(r)}"
        pts = [p for p in cv.get(key, []) if p["rtol"] == r]
        if not pts:
            continue
        e, t = pts[0]["error"], pts[0]["time"]
        best = [time_at(cv, n, e) for n in cv if n.startswith(method + "/") and not n.endswith("Kvaerno5")]
        best = [b for b in best if b is not None] + [t]
        out[r] = t / min(best)
    return out


def default_section(R) -> list:
    L = []
    for wp, method in wp_formulations(R):
        cv = _curves(wp)
        today = default_slowdown(wp, lambda r: "Tsit5", method)
        pick = default_key(wp["problem"], method)
        prop = default_slowdown(wp, pick, method)
        rows = []
        for r in wp["tols"]:
            pts = {
                n: next((p for p in v if p["rtol"] == r), None)
                for n, v in cv.items()
                if n.startswith(method + "/") and not n.endswith("Kvaerno5")
            }
            mine = pts.get(f"{method}/{pick(r)}")
            if mine is None:
                continue
            fastest = min(
                ((n, time_at(cv, n, mine["error"])) for n in pts if pts[n] is not None),
                key=lambda x: x[1] if x[1] is not None else 1e9,
                default=(None, None),
            )
            rows.append(
                [f"{r:g}", pick(r), fmt_x(prop.get(r)), fmt_x(today.get(r)), (fastest[0] or "—").split("/")[-1]]
            )
        L += [
            f"**{wp['problem']}, {method}** (vector field: {operations(wp['problem'], method)} operations)",
            "",
            table(
                [
                    "rtol",
                    "default_solver(rtol)",
                    "its time / fastest at that error",
                    "diffrax Tsit5 (previous default) / fastest",
                    f"fastest {method} solver",
                ],
                rows,
            ),
            "",
        ]
    return L


THRESHOLD_CANDIDATES = [10.0**-k for k in range(3, 12)]


def threshold_scan(R) -> tuple[list, dict]:
    """For each candidate switch point θ (Dopri8 for rtol < θ, the 5th-order solver above): the slowdown of
    that rule against the fastest solver of the same formulation at the error reached, geometric mean and
    worst over the sweep, for each (problem, formulation) the work-precision runs hold, grouped by the
    5th-order solver `default_solver` uses there (unrolled Tsit5u, or diffrax's looped Tsit5). Returns
    (header and table rows, {5th-order solver: {θ: geometric-mean slowdown over its group}})."""
    cases = [(wp, method, default_key(wp["problem"], method)(1.0)) for wp, method in wp_formulations(R)]
    rows, score = [], {}
    current = {"Tsit5u": DOP853_BELOW_RTOL, "Tsit5": DOPRI8_BELOW_RTOL_LOOPED}
    for th in THRESHOLD_CANDIDATES:
        row = [f"{th:g}"]
        for wp, method, low in cases:
            sl = default_slowdown(wp, lambda r, th=th, low=low: "Dopri8" if r < th else low, method)
            v = [x for x in sl.values() if x is not None and math.isfinite(x)]
            if not v:
                row += ["—"]
                continue
            score.setdefault(low, {}).setdefault(th, []).extend(math.log(x) for x in v)
            mark = " ◀" if current.get(low) == th else ""
            row += [f"{fmt_x(gmean(v))} / {fmt_x(max(v))}{mark}"]
        rows.append(row)
    header = ["θ"] + [f"{wp['problem']} {method} (above θ: {low})" for wp, method, low in cases]
    means = {low: {th: math.exp(sum(v) / len(v)) for th, v in d.items()} for low, d in score.items()}
    return [header] + rows, means


def fmt_ns(s) -> str:
    return f"{s * 1e9:.3g} ns" if s < 1e-6 else fmt_t(s)


def kernel_slope(row) -> float:
    """Least-squares slope of the Tsit5u step time on the kernels per step, s per kernel."""
    keys = [k for k in row["step_kernels"] if f"{k}/Tsit5u" in row["step"]]
    x = np.array([row["step_kernels"][k] for k in keys], float)
    y = np.array([row["step"][f"{k}/Tsit5u"] for k in keys])
    return float(np.polyfit(x, y, 1)[0])


def field_cost_section(fc) -> list:
    """Where the time of a step goes (benchmarks/field_cost.py)."""
    L = [
        "### Where a step's time goes",
        "",
        "`benchmarks/field_cost.py`: one vector-field evaluation compiled alone (repeated in a loop at new (t, y) "
        "each time), the XLA CPU kernels it compiles to, and one step of a compiled solve at rtol 1e-8 over a long "
        'horizon. "kernels per step" counts the run-time instructions of the unrolled Tsit5\'s step loop body; '
        f"a Tsit5 step evaluates the field {fc['stages_per_step']} times. The trivial field is an oscillator with "
        "the same state layout: the integration loop with next to nothing to evaluate.",
        "",
    ]
    for row in fc["rows"]:
        solvers = [s for s in ("Tsit5u", "Tsit5") if f"hand/{s}" in row["step"]]
        rows = []
        for k in ("appell", "lagrange", "hand", "trivial"):
            field = row["field"].get(k)
            step = row["step"][f"{k}/Tsit5u"]
            rows.append(
                [
                    k,
                    fmt_ns(field) if field is not None else "—",
                    str(sum(row["kernels"][k].values())) if k in row["kernels"] else "—",
                    str(row["step_kernels"][k]),
                    fmt_t(step),
                    f"{fc['stages_per_step'] * field / step:.0%}" if field is not None else "—",
                ]
                + ([fmt_t(row["step"][f"{k}/Tsit5"])] if "Tsit5" in solvers else [])
            )
        slope = kernel_slope(row)
        L += [
            f"**{row['problem']}**",
            "",
            table(
                [
                    "field",
                    "one evaluation",
                    "kernels per evaluation",
                    "kernels per Tsit5u step",
                    "Tsit5u step",
                    "field's share of the step",
                ]
                + ["diffrax Tsit5 step"] * ("Tsit5" in solvers),
                rows,
            ),
            "",
            f"Least-squares slope of the Tsit5u step time on the kernels per step: {slope * 1e9:.0f} ns per kernel "
            "(a launch cost where the field's share is small; where it is large the slope also carries the "
            "field's arithmetic).",
            "",
        ]
    return L


def build(R) -> tuple[str, dict]:
    m = next(
        (R[k]["machine"] for k in ("wp_variator", "overhead", "gradients", "throughput", "compile_time") if R.get(k)),
        C.machine(),
    )
    L = [
        "# jaxnh performance benchmarks (issue 4)",
        "",
        "Regenerate everything (JSON, figures, this file) with `make bench` (= `python -m benchmarks.run_all`, "
        "20–60 minutes on this 2-core machine, by its load); `make bench-quick` "
        "(= `JAXNH_BENCH_OUT=benchmarks/quick python -m benchmarks.run_all --quick`) is the short version, "
        "written to `benchmarks/quick/` so it does not overwrite these results. Every number below is written by "
        "`benchmarks/report.py` from the `results/*.json` files beside this file.",
        "",
        "## Machine and method",
        "",
        f"* CPU: {m['cpu']}, {m['cores']} cores; {m['platform']}",
        f"* Python {m['python']}, jax {m['jax']} (jaxlib {m['jaxlib']}), diffrax {m['diffrax']}, equinox "
        f"{m['equinox']}, numpy {m['numpy']}, scipy {m['scipy']}, jaxnh {m['jaxnh']}; devices {m['devices']}",
        f"* Load average when the runs started: {', '.join(f'{x:.1f}' for x in m['load_average'])} "
        f"(the machine is shared); date {m['date']}",
        f"* jaxnh revision: {m.get('jaxnh_revision', 'unknown')}",
        f"* Each benchmark process pinned to one core (core {m.get('pinned_cpu')} for this file's header) and XLA "
        f"flags `{m.get('xla_flags', '')}`: XLA's spinning thread pool otherwise inflated and scattered CPU times "
        "(see `benchmarks/common.py`)",
        "* Times are **process CPU time** (`time.process_time`), median over interleaved rounds after "
        "compilation; wall-clock medians are in the JSON files. On this shared machine wall time mostly "
        "measured waiting for a core (a 3.5 ms solve took 3.3–20 ms of wall time, 3.3–3.7 ms of CPU time). "
        "Ratios are medians of per-round ratios of contenders timed in the same round. Compile times are "
        "`jit(...).lower(...).compile()`, CPU and wall; first-call times come from fresh processes.",
        '* "Compiled solve" is `simulate`\'s jitted inner function `jaxnh._simulate._integrate` with the '
        'tolerances traced (one compilation per contender); "through simulate" is a plain `nh.simulate(...)` '
        "call, whose argument checks run in Python on every call.",
        "",
    ]
    rows, head = targets(R)
    L += ["## Targets", "", table(["target", "goal", "measured", "met"], rows), ""]
    if R.get("wp_variator") or R.get("wp_generic"):
        L += [
            "## Default solver",
            "",
            "`jaxnh._simulate.default_solver(rtol, operations, method)`: for a vector "
            f"field of at most `UNROLL_MAX_OPERATIONS` = {UNROLL_MAX_OPERATIONS} JAX operations in the appell "
            "(or substituted) form, jaxnh's unrolled Tsit5 (Tsit5u), and diffrax Dopri8 for rtol < "
            f"`DOP853_BELOW_RTOL` = {DOP853_BELOW_RTOL:g}; for larger vector fields and for lagrange, diffrax's "
            f"Tsit5, and Dopri8 for rtol < `DOPRI8_BELOW_RTOL_LOOPED` = {DOPRI8_BELOW_RTOL_LOOPED:g}. For each "
            "sweep tolerance: the solver it picks, and how much slower it is than the fastest solver of the same "
            "formulation at the error it reaches (times interpolated on the work-precision curves).",
            "",
        ] + default_section(R)
        rows, best = threshold_scan(R)
        current = {
            "Tsit5u": ("DOP853_BELOW_RTOL", DOP853_BELOW_RTOL),
            "Tsit5": ("DOPRI8_BELOW_RTOL_LOOPED", DOPRI8_BELOW_RTOL_LOOPED),
        }
        verdict = []
        for low, m in best.items():
            th = min(m, key=m.get)
            name, now = current[low]
            same = (
                " (the same)"
                if th == now
                else (
                    f" (mean slowdown {m[now]:.3f}× against {m[th]:.3f}×: within 1 %)"
                    if m.get(now, 9) <= 1.01 * m[th]
                    else " (differs: see the closing note of issue 4)"
                )
            )
            verdict.append(
                f"above θ {C.SOLVER_LABELS.get(low, low)}: smallest mean slowdown at θ = {th:g}; "
                f"`{name}` is {now:g}" + same
            )
            head[f"best_threshold_{low}"] = th
        L += [
            "**Where to switch.** Each candidate switch point θ (Dopri8 for rtol < θ, the 5th-order solver "
            "`default_solver` uses above it), its slowdown against the fastest solver of the same formulation "
            "at the error reached: geometric mean / worst over the sweep; ◀ marks the threshold in use.",
            "",
            table(rows[0], rows[1:]),
            "",
            "; ".join(verdict) + ".",
            "",
        ]
    if R.get("wp_variator") or R.get("wp_generic"):
        L += ["## Work-precision", ""]
        if R.get("wp_variator"):
            L += wp_section(R["wp_variator"], "Variator (s = 2, m = 1), against the closed form")
        if R.get("wp_generic"):
            L += wp_section(R["wp_generic"], "Generic mechanism (s = 10, m = 3)")
    ov = R.get("overhead")
    if ov:
        L += [
            "## Cost of automatic derivation",
            "",
            "Same solver, tolerance (rtol 1e-8, atol 1e-10) and report times; ratios to the hand-written equations "
            "(eq. (9) for the variator, Lagrange's equations written out for the generic mechanism).",
            "",
        ]
        rows = []
        for r in ov["rhs_cost"]:
            rows.append(
                [
                    r["problem"],
                    f"{r['horizon']:g} s",
                    C.SOLVER_LABELS[r["solver"]],
                    fmt_t(r["time"]["hand"]),
                    fmt_x(r["ratio"]["appell"]),
                    fmt_x(r["ratio"]["lagrange"]),
                    fmt_x(r["ratio"].get("appell jit(simulate)")),
                    fmt_x(r["ratio"].get("appell through simulate")),
                    fmt_t(r["simulate_overhead"]["appell"]),
                    f"{r['compile']['hand']['cpu']:.1f} / {r['compile']['appell']['cpu']:.1f} / "
                    f"{r['compile']['lagrange']['cpu']:.1f} s",
                ]
            )
        L += [
            table(
                [
                    "problem",
                    "horizon",
                    "solver",
                    "hand-written",
                    "appell / hand",
                    "lagrange / hand",
                    "appell jit(simulate) / hand",
                    "appell through simulate / hand",
                    "simulate's per-call cost",
                    "compile hand / appell / lagrange (CPU)",
                ],
                rows,
            ),
            "",
        ]
        if ov.get("records"):
            L += [
                "### Pay for what you ask: recorded quantities",
                "",
                "Compiled solve in DOP853 at rtol 1e-8 with 1001 report times; time relative to `record=()`.",
                "",
            ]
            keys = list(ov["records"][0]["ratio"])
            L += [
                table(
                    ["problem", "method", "record=() time"] + keys,
                    [
                        [r["problem"], r["method"], fmt_t(r["time"]["nothing"])] + [fmt_x(r["ratio"][k]) for k in keys]
                        for r in ov["records"]
                    ],
                ),
                "",
            ]
        if ov.get("rheonomic"):
            L += [
                "### Pay for what you ask: time-invariant against rheonomic",
                "",
                "Generic mechanism, DOP853, rtol 1e-8: time per step (the step counts differ).",
                "",
            ]
            L += [
                table(
                    [
                        "mechanism",
                        "steps (appell/lagrange/hand)",
                        "appell per step",
                        "lagrange per step",
                        "hand per step",
                        "appell / hand",
                        "lagrange / hand",
                    ],
                    [
                        [
                            "rheonomic" if r["rheonomic"] else "time-invariant",
                            f"{r['steps']['appell']}/{r['steps']['lagrange']}/{r['steps']['hand']}",
                            fmt_t(r["step_time"]["appell"]),
                            fmt_t(r["step_time"]["lagrange"]),
                            fmt_t(r["step_time"]["hand"]),
                            fmt_x(r["ratio"]["appell"]),
                            fmt_x(r["ratio"]["lagrange"]),
                        ]
                        for r in ov["rheonomic"]
                    ],
                ),
                "",
            ]
    fc = R.get("field_cost")
    if fc:
        L += field_cost_section(fc)
    tp = R.get("throughput")
    if tp:
        L += [
            "## Batch throughput",
            "",
            f"Variator, rtol {tp['rtol']:g}, `jit(vmap(...))`; figure "
            "`figures/throughput.png`. Per-trajectory time = batch time / batch size.",
            "",
        ]
        L += [
            table(
                [
                    "contender",
                    "batch",
                    "per trajectory (CPU)",
                    "per trajectory (wall)",
                    "max steps in batch",
                    "error (member 0)",
                    "compile (CPU)",
                ],
                [
                    [
                        f"{r['kind']}, {C.SOLVER_LABELS[r['solver']]}",
                        r["batch"],
                        fmt_t(r["per_trajectory"]),
                        fmt_t(r["per_trajectory_wall"]),
                        r["max_steps_in_batch"],
                        f"{r['error_member0']:.1e}",
                        f"{r['compile']['cpu']:.1f} s",
                    ]
                    for r in tp["rows"]
                ],
            ),
            "",
        ]
    gr = R.get("gradients")
    if gr:
        L += [
            "## Gradients",
            "",
            f"Variator, {C.SOLVER_LABELS[gr['solver']]}, rtol {gr['rtol']:g}: time of the "
            "gradient of a trajectory loss divided by the time of the loss (one forward solve), median of "
            "per-round ratios; figure `figures/gradients.png`. All modes agree to the relative difference "
            "shown (they differentiate the same discrete solution).",
            "",
        ]
        modes = list(dict.fromkeys(k for r in gr["rows"] for k in r["ratio"] if k != "forward solve"))
        L += [
            table(
                ["P", "forward solve"] + modes + ["max rel. difference to reverse", "compile (CPU) RC / FS"],
                [
                    [r["P"], fmt_t(r["time"]["forward solve"])]
                    + [fmt_x(r["ratio"].get(k)) for k in modes]
                    + [
                        f"{max(r['relative_difference_to_reverse'].values()):.0e}",
                        f"{r['compile']['reverse RecursiveCheckpoint']['cpu']:.1f} / "
                        f"{r['compile']['ForwardSensitivity']['cpu']:.1f} s",
                    ]
                    for r in sorted(gr["rows"], key=lambda r: r["P"])
                ],
            ),
            "",
        ]
    ct = R.get("compile_time")
    if ct:
        L += [
            "## First-call time (fresh process)",
            "",
            table(
                [
                    "scenario",
                    "import",
                    "first call (CPU / wall)",
                    "second call (CPU)",
                    "compile = first − second (CPU / wall)",
                ],
                [
                    [
                        r["label"],
                        f"{r['import_s']:.1f} s",
                        f"{r['first']['cpu']:.2f} / {r['first']['wall']:.2f} s",
                        fmt_t(r["second"]["cpu"]),
                        f"{r['compile']['cpu']:.2f} / {r['compile']['wall']:.2f} s",
                    ]
                    for r in ct["rows"]
                    if "error" not in r
                ],
            ),
            "",
        ]
    from . import cache_effect, field_size, lean_loop, suite_time  # issue 16: first answers, loop, field, suite

    L += cache_effect.section(R.get("first_answer"))
    L += lean_loop.section(R.get("lean_loop"))
    L += field_size.section(R.get("field_size"))
    L += suite_time.section(R.get("suite_time"))
    others = [(p, C.HERE / p) for p in ("STABILITY.md", "CALIBRATION.md", "SWEEP.md")]
    present = [p for p, path in others if path.exists()]
    if present:
        L += [
            "## Other benchmark reports",
            "",
            "Written by their own scripts (run by `run_all` when present): "
            + ", ".join(f"[{p}]({os.path.relpath(C.HERE / p, C.OUT)})" for p in present)
            + ".",
            "",
        ]
    return "\n".join(L) + "\n", head


def main():
    names = (
        "wp_variator",
        "wp_generic",
        "overhead",
        "field_cost",
        "throughput",
        "gradients",
        "compile_time",
        "lean_loop",
        "field_size",
        "first_answer",
        "suite_time",
    )
    R = {k: C.load(k) for k in names}
    C.FIGURES.mkdir(parents=True, exist_ok=True)
    for k in ("wp_variator", "wp_generic"):
        if R.get(k):
            fig_wp(R[k], C.FIGURES / f"{k.replace('wp_', 'wp_')}.png")
    if R.get("throughput"):
        scipy_t = time_at(_curves(R["wp_variator"]), "scipy/DOP853", 1e-8) if R.get("wp_variator") else None
        fig_throughput(R["throughput"], C.FIGURES / "throughput.png", scipy_t)
    if R.get("gradients"):
        fig_gradients(R["gradients"], C.FIGURES / "gradients.png")
    text, head = build(R)
    (C.OUT / "RESULTS.md").write_text(text)
    C.save("headline", dict(head))
    C.log(f"[report] wrote {C.OUT / 'RESULTS.md'}")
    for k, v in head.items():
        C.log(f"  {k}: {v:.3g}")


if __name__ == "__main__":
    main()
