"""Write RESULTS.md and its figures from the studies' results/*.json (run by benchmarks.run_all).

python -m benchmarks.report
"""

from __future__ import annotations

import numpy as np

from . import common as C


STUDIES = ("headline", "size", "first_answer", "precision", "friction", "speeds")
RECORDS = {  # reports their own scripts write (not run by run_all); each says its command and revision at its top
    "RELIABILITY.md": "no silent wrong answers: outcomes of many fuzzed cases (`python -m benchmarks.reliability`)",
    "STABILITY.md": "long runs, constraint drift, float32 (`python -m benchmarks.stability`)",
    "BICYCLE.md": "cost of the Whipple bicycle's linearisation, jaxnh vs SymPy (`python -m benchmarks.bicycle_cost`)",
    "CALIBRATION.md": "coverage of the fit's 95 % intervals (`python -m benchmarks.calibration`)",
    "EXPERIMENT.md": "experiment design: predicted vs realised precision (`python -m benchmarks.experiment_design`)",
    "FIT_COST.md": "cost of `jaxnh fit` on the embedded record (`python -m benchmarks.fit_cost`)",
    "MODEL_ERROR.md": "fits when the truth lies outside the model class (`python -m benchmarks.model_error`)",
    "SWEEP.md": "batched sweeps and design gradients (`python -m benchmarks.sweep_bench`)",
}

HOW_TO_READ = (
    "How to read it: in-process times are process CPU time (the machine is shared; CPU time is what a call "
    "costs on an idle core, wall time also counts waiting for one), medians over interleaved rounds, each "
    "benchmark process pinned to one core; a ratio is the median of per-round ratios of contenders timed in the "
    "same round. Fresh-process times run with every core and the user's settings; their targets are judged on "
    "CPU time. Every time comes with the error reached against a closed form or a tight-tolerance reference."
)
FIRST_ANSWERS = (
    "Fresh processes with every core and the user's XLA settings, from before the first import to the answer "
    "on the host, medians of {repeats} (`python -m benchmarks.first_answer`). *cold*: a default process, no "
    "compilation cache. *cache, first / second*: `jaxnh.enable_compilation_cache()` right after the import with "
    "`JAXNH_CACHE_DIR` an empty temporary folder, then a second process reading it; for the hand-written "
    "program JAX's cache pointed at another empty folder (`JAX_COMPILATION_CACHE_DIR`, every program written). "
    "The hand-written programs: eq. (9) and SymPy's Kane equations printed as JAX, `diffrax.Tsit5`, jitted, "
    "same tolerances."
)


def t(s) -> str:
    """A duration in s, µs … s."""
    if s is None or not np.isfinite(s):
        return "—"
    for unit, f in (("s", 1.0), ("ms", 1e-3), ("µs", 1e-6)):
        if s >= f or unit == "µs":
            v = s / f
            return f"{v:.3g} {unit}" if v < 100 else f"{v:.0f} {unit}"
    return "—"


def e(x) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.1e}"


def table(header, rows) -> list:
    return (
        ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
        + [""]
    )


def met(ok) -> str:
    return "—" if ok is None else ("yes" if ok else "**no**")


def stamp(results: dict) -> list:
    m = C.machine()
    digests = {r["machine"]["digest"] for r in results.values()}
    measured = digests.pop() if len(digests) == 1 else "mixed"  # a mixed record is always stale
    starts = sorted((r["machine"]["date"], r["machine"]["load_average"]) for r in results.values())
    lines = [
        f"> **Revision** `{m['revision']}`"
        + (" with uncommitted changes in jaxnh/" if m["uncommitted"] else "")
        + f"; source digest of jaxnh/: `{measured}`; measured {starts[0][0] if starts else m['date']}"
        + f" to {m['date']}; CPU {m['cpu']} ({m['cores']} cores), load average "
        + ", ".join(f"{la[0]:.1f}" for _, la in starts)
        + " at the start of each study"
        + f"; Python {m['python']}, "
        + ", ".join(f"{k} {v}" for k, v in m["versions"].items())
        + ".",
        "> `python -m benchmarks.run_all --stale` (or `benchmarks.common.stale()`) says whether jaxnh/ has changed "
        "since: the digest is a hash of the executable code of every jaxnh/**/*.py (comments, docstrings and "
        "signature hints left out).",
    ]
    if measured != m["digest"]:
        lines.append("> **Warning:** jaxnh/ changed while the studies ran or since: this record is stale; rerun.")
    if any(r.get("quick") for r in results.values()):
        lines.append("> **Quick run** (`--quick`): fewer points and repeats; not the record.")
    return lines + [""]


def headline_names():
    from .headline import FIELD, HAND, PLAIN

    return PLAIN, HAND, FIELD


def headline(R) -> tuple[list, list]:
    rows, r = R["rows"], R["ratios"]
    P, H, F = headline_names()
    targets = [
        [
            "`simulate` (defaults) / eq. (9) by hand in diffrax Tsit5, same tolerance, variator",
            "≤ 1.0×, error ≤ hand's",
            f"{r['simulate / hand']:.2f}×",
            f"{e(rows[P]['error'])} vs {e(rows[H]['error'])}",
            met(r["simulate / hand"] <= 1.0 and rows[P]["error"] <= rows[H]["error"]),
        ],
        [
            "Appell field (`nh.ode`) in diffrax Tsit5 / hand field, per step",
            "≤ 1.3×",
            f"{r['field per step / hand per step']:.2f}×",
            f"{e(rows[F]['error'])} vs {e(rows[H]['error'])}",
            met(r["field per step / hand per step"] <= 1.3),
        ],
    ]
    if "overhead" in R:  # (results written before it was measured have none)
        targets.append(
            [
                "`simulate` called eagerly: its own cost per call over `jit(simulate)` with the same arguments, "
                "variator",
                "≤ 0.3 ms",
                t(R["overhead"]),
                "same solve",
                met(R["overhead"] <= 3e-4),
            ]
        )
    out = [
        "## The variator: hand-written, SciPy and the limit",
        "",
        f"The README's variator with every contender at rtol {R['rtol']:g}, atol {R['atol']:g}; errors against the "
        "closed form (largest over the 101 report times, coordinates and velocities). CPU time per call, median over "
        f"interleaved rounds after the first (compiling) call, whose CPU time is in the last column (`python -m "
        "benchmarks.headline`).",
        "",
    ]
    body = [
        [
            k,
            t(v["cpu"]),
            t(v["wall"]),
            e(v.get("error")),
            f"{v['steps']:.0f}" if "steps" in v else "—",
            t(v.get("per_step")),
            t(v["first_call_cpu"]),
        ]
        for k, v in rows.items()
    ]
    out += table(["contender", "CPU per call", "wall", "error", "steps", "per step", "first call (CPU)"], body)
    out += [
        "Ratios (medians of per-round ratios): "
        + "; ".join(f"{k} {v:.2f}×" for k, v in r.items())
        + f". The batch has {R['batch']} trajectories (J1 varied ±20 %)."
        + (
            f" A plain call's own cost (median per-round excess over `jit(simulate)` with every input an argument): "
            f"{t(R['overhead'])}."
            if "overhead" in R
            else ""
        ),
        "",
    ]
    return targets, out


def size(R) -> tuple[list, list, dict]:
    fa, st = R["first_answers"], R["steady"]
    ncmp, ngrow = R["ns_compare"], R["ns_growth"]

    default = R.get("default", "appell")  # simulate's default formulation when measured

    def row(N, k):
        return fa.get(f"{N} {k}", {})

    ratios = {
        N: C.paired_ratio(row(N, default)["cpu"], row(N, "sympy")["cpu"])
        for N in ncmp
        if row(N, default).get("cpu") and row(N, "sympy").get("cpu")
    }
    worst = max(ratios.items(), key=lambda kv: kv[1]) if ratios else (None, np.nan)
    sp = {N: st[str(N)]["SciPy / jaxnh"] for N in ncmp if str(N) in st}
    low = min(sp.items(), key=lambda kv: kv[1]) if sp else (None, np.nan)
    errs_j = [row(N, default).get("error") for N in ncmp]
    errs_s = [row(N, "sympy").get("error") for N in ncmp]
    targets = [
        [
            f"car + N trailers, first answer in a fresh process: jaxnh / SymPy's pipeline, N = {ncmp[0]}…{ncmp[-1]}",
            "< 1× at every N",
            f"worst {worst[1]:.2f}× (N = {worst[0]})",
            f"≤ {e(np.nanmax(np.asarray(errs_j, float)))} vs ≤ {e(np.nanmax(np.asarray(errs_s, float)))}",
            met(bool(ratios) and worst[1] < 1.0),
        ],
        [
            f"same, steady solve: SciPy with lambdified NumPy / jaxnh, N = {ncmp[0]}…{ncmp[-1]}",
            "≥ 50×",
            f"lowest {low[1]:.1f}× (N = {low[0]})",
            "as above",
            met(bool(sp) and low[1] >= 50),
        ],
    ]
    a16, g16 = row(16, default), row(16, "gradient")
    if a16.get("cpu"):
        targets.append(
            [
                "car + 16 trailers, first answer (CPU; wall in brackets)",
                "≤ 10 s",
                f"{a16['cpu_median']:.1f} s ({a16['wall_median']:.1f} s)",
                e(a16.get("error")),
                met(a16["cpu_median"] <= 10),
            ]
        )
    if a16.get("cpu") and g16.get("cpu"):
        gr = C.paired_ratio(g16["cpu"], a16["cpu"])
        targets.append(
            [
                "car + 16 trailers, first gradient / first answer",
                "≤ 2×",
                f"{gr:.2f}×",
                f"gradient {e(g16.get('error'))} (relative)",
                met(gr <= 2),
            ]
        )
    gro = R["growth"]
    if gro:
        targets.append(
            [
                f"growth of the first answer (after the import) with N = {ngrow[0]}…{ngrow[-1]}: t ∝ N^k",
                "—",
                ", ".join(f"{k} k = {v['exponent']:.2f}" for k, v in gro.items()),
                "see the table",
                "—",
            ]
        )
    out = [
        "## The size study: a car pulling N trailers",
        "",
        "A car (a rigid body on one knife-edge axle) pulling N trailers, each on its own knife-edge axle: s = N + 3 "
        "coordinates, m = N + 1 constraints, rheonomic drive (`benchmarks/mechanisms/chain.py`). jaxnh's mechanism is "
        "written as the docs show (positions by cumulative sums, velocities by `jax.jvp` inside T); SymPy's is written "
        'with `sympy.physics.mechanics` and `KanesMethod`; "hand JAX" is SymPy\'s result printed as JAX source. Every '
        f"solve at rtol {R['rtol']:g}, atol {R['atol']:g}; errors against Lagrange's equations written out by "
        "hand in NumPy (they agree with SymPy's to 1e-13) solved by SciPy's DOP853 at rtol 1e-12 "
        "(`python -m benchmarks.size`).",
        "",
        "### First answers against SymPy's pipeline",
        "",
        "Fresh processes, every core, no compilation cache, medians of "
        f"{R['repeats']}: from before the first import to the answer on the host (jaxnh: import, the first "
        "`simulate`; SymPy: import, derivation, `lambdify`, `solve_ivp` RK45). CPU time, wall time in brackets.",
        "",
    ]
    body = []
    for N in ncmp:
        j, s = row(N, default), row(N, "sympy")
        body.append(
            [
                N,
                f"{t(j.get('cpu_median'))} ({t(j.get('wall_median'))})",
                e(j.get("error")),
                f"{t(s.get('cpu_median'))} ({t(s.get('wall_median'))})",
                e(s.get("error")),
                f"{ratios[N]:.2f}×" if N in ratios else "—",
            ]
        )
    out += table(["N", "jaxnh", "error", "SymPy + SciPy", "error", "jaxnh / SymPy"], body)
    out += [
        "### Steady solves",
        "",
        "After compilation, in one process on one core: CPU time per solve, medians of interleaved rounds.",
        "",
    ]
    body = []
    for N in ncmp:
        if str(N) not in st:
            continue
        r_ = st[str(N)]
        body.append(
            [N]
            + [
                f"{t(r_[k]['cpu'])} ({e(r_[k]['error'])}, {r_[k]['steps']:.0f} steps)"
                for k in ("jaxnh", "SciPy", "hand JAX")
            ]
            + [f"{r_['SciPy / jaxnh']:.1f}×", f"{r_['jaxnh / hand JAX']:.2f}×"]
        )
    out += table(
        [
            "N",
            "jaxnh `simulate` (error, steps)",
            "SciPy RK45, lambdified",
            "hand JAX, diffrax Tsit5",
            "SciPy / jaxnh",
            "jaxnh / hand JAX",
        ],
        body,
    )
    out += [
        "### Compile-time growth",
        "",
        "First answers in fresh processes, as above: CPU time after the import (wall time of the whole process "
        "in brackets), error, peak memory of the process; the gradient is `jax.grad` of the final coordinates' "
        "sum with respect to every parameter (its error: relative, of its product with a random direction of "
        "the parameters that do not move the axles, against a central difference of the reference). Figure: "
        "`figures/chain.png`.",
        "",
    ]
    body = []
    for N in ngrow:
        cells = [N]
        for k in ("appell", "lagrange", "gradient"):
            r_ = row(N, k)
            if r_.get("cpu_after_import_median") is None or r_.get("error") is None or not np.isfinite(r_["error"]):
                took = f" after {t(r_['cpu_after_import_median'])}" if r_.get("cpu_after_import_median") else ""
                cells.append(f"**failed**{took}: " + (r_.get("note") or "not run")[:200].replace("|", "/"))
            else:
                cells.append(
                    f"{t(r_['cpu_after_import_median'])} ({t(r_['wall_median'])}), {e(r_.get('error'))}, "
                    f"{r_.get('peak_rss_gb', float('nan')):.1f} GB"
                    + (f" — {r_['note'][:120]}" if r_.get("note") else "")
                )
        body.append(cells)
    labels = [f"{k} (default)" if k == default else k for k in ("appell", "lagrange")]
    out += table(["N", *labels, "first gradient"], body)
    out += ["Fitted exponents k of t ∝ N^k: " + "; ".join(f"{k} {v['exponent']:.2f}" for k, v in gro.items()) + ".", ""]
    return targets, out, dict(ratios=ratios)


def first_answer(R) -> tuple[list, list]:
    targets = []
    out = ["## First answers", "", FIRST_ANSWERS.format(repeats=R["repeats"]), ""]
    for m, rr in R["rows"].items():
        r = R["ratios"][m]
        targets += [
            [
                f"{m}: first answer, jaxnh / hand-written diffrax program, cold",
                "≤ 1.2×",
                f"{r['cold / hand cold (CPU)']:.2f}× CPU ({r['cold / hand cold']:.2f}× wall)",
                f"{e(rr['jaxnh cold']['error'])} vs {e(rr['hand cold']['error'])}",
                met(r["cold / hand cold (CPU)"] <= 1.2),
            ],
            [
                f"{m}: second process with the cache, jaxnh / hand-written cold",
                "≤ 0.5×",
                f"{r['cache second / hand cold (CPU)']:.2f}× CPU ({r['cache second / hand cold']:.2f}× wall)",
                e(rr["jaxnh cache, second"]["error"]),
                met(r["cache second / hand cold (CPU)"] <= 0.5),
            ],
        ]
        out += [f"**{m}**", ""]
        out += table(
            ["process", "CPU", "wall", "of which the imports (wall)", "error", "cache entries written"],
            [
                [
                    k,
                    t(v["cpu_median"]),
                    t(v["wall_median"]),
                    t(v.get("import_median")),
                    e(v["error"]),
                    v.get("cache_entries", ""),
                ]
                for k, v in rr.items()
            ],
        )
    return targets, out


def precision(R) -> tuple[list, list]:
    rows = R["rows"]
    default = "lagrange" if "mechanisms" in R else "appell"  # (results before the default changed: the ball alone)
    other = "appell" if default == "lagrange" else "lagrange"
    mechanisms = R.get("mechanisms", ["ball"])
    targets, out = [], ["## Work–precision: the default formulation against the other", ""]
    out += [
        f"Each mechanism solved by a plain `simulate` per tolerance (atol = rtol/100), with the default formulation "
        f"({default}) and {other}'s, the default solver; CPU time per call and the largest error over the report "
        "times against an independent reference (`python -m benchmarks.precision`; figure: `figures/wp_ball.png`). "
        "References: "
        + "; ".join(f"{m}: {R.get('references', {}).get(m, 'closed form and a tight reference')}" for m in mechanisms)
        + ".",
        "",
    ]
    for mech in mechanisms:
        mine = {k: r for k, r in rows.items() if r.get("mechanism", "ball") == mech}
        curves = {}
        for r in mine.values():
            curves.setdefault((r["method"], r["solver"]), []).append((r["error"], r["cpu"]))
        # time at matched error: each default point against the other formulation's curve (log-log interpolation)
        theirs = sorted(curves.get((other, "default"), []))
        ratios = [cpu / o for err, cpu in curves.get((default, "default"), []) if (o := _interp(theirs, err))]
        targets.append(
            [
                f"{mech}: default formulation ({default}) / {other}, time at the same error, rtol "
                f"{R['rtols'][0]:g}…{R['rtols'][-1]:g}",
                "≤ 1× (no worse at any error)",
                f"{min(ratios):.2f}×…{max(ratios):.2f}× ({len(ratios)} matched points)" if ratios else "no overlap",
                "independent reference",
                "yes" if ratios and max(ratios) <= 1.0 else ("no" if ratios else "—"),
            ]
        )
        keys = sorted(
            {(r["method"], r["solver"]) for r in mine.values()},
            key=lambda k: (k[0] != default, k[1] != "default", k[1]),
        )
        prefix = f"{mech} " if "mechanisms" in R else ""
        body = []
        for rtol in R["rtols"]:
            cells = [f"{rtol:g}"]
            for key in keys:
                r = rows[f"{prefix}{key[0]} {key[1]} {rtol:g}"]
                cells.append(f"{t(r['cpu'])}, {e(r['error'])}")
            body.append(cells)
        out += [f"### {mech}", ""]
        out += table(["rtol"] + [f"{m}, {s} solver" for m, s in keys], body)
        if len(keys) > 2:
            out += [
                "The default solver (`jaxnh.default_solver`) against diffrax's Tsit5 and Dopri8 in the same "
                "formulation: the default's time over theirs at the errors the default reaches (interpolated on their "
                "curves).",
                "",
            ]
            body = []
            for m, s in keys:
                if s == "default":
                    continue
                rs = [cpu / o for err, cpu in curves[(m, "default")] if (o := _interp(sorted(curves[(m, s)]), err))]
                cell = f"{np.median(rs):.2f}× ({min(rs):.2f}×…{max(rs):.2f}×, {len(rs)} points)" if rs else "no overlap"
                body.append([m, s, cell])
            out += table(["formulation", "other solver", "default / other at the same error: median (range)"], body)
    return targets, out


def friction(R) -> tuple[list, list]:
    rows = R["rows"]
    rolling = rows["rolling"]
    cases = [k for k in rows if k != "rolling"]
    targets = [
        [
            "friction contacts: a scene without them",
            "pays nothing",
            "dispatched before tracing: the rolling solve's program is the one without the feature "
            f"(program digest `{rolling.get('program_sha256', '?')}`)",
            e(rolling.get("error")),
            "—",
        ],
        [
            "friction solve with k transitions / rolling solve, per call",
            "—",
            ", ".join(f"k = {rows[k]['transitions']}: {rows[k]['over_rolling']:.2f}×" for k in cases),
            "slip onset " + ", ".join(e(rows[k].get("error")) for k in cases if "error" in rows[k]),
            "—",
        ],
    ]
    out = [
        "## Friction-held contacts",
        "",
        "The variator of `examples/variator_slip.py` (ratio 1 → 2 in 0.5 s at 100 rad/s, the roller held by a "
        f"`FrictionContact`), simulate's defaults, 1 s, {R.get('report_times', '?')} report times "
        "(`python -m benchmarks.friction`). *rolling*: the same mechanism without its contact. Errors: the slip "
        "onset against its closed-form condition; for the rolling solve, φ1' against its closed form.",
        "",
    ]
    body = []
    for k, r in rows.items():
        body.append(
            [
                k,
                str(r.get("transitions", 0)),
                str(r.get("segments", 1)),
                str(r.get("steps", "")),
                t(r["cpu"]),
                f"{r['over_rolling']:.2f}×",
                e(r.get("error")),
            ]
        )
    out += table(["case", "transitions", "segments", "steps", "CPU per call", "/ rolling", "error"], body)
    first = R.get("first") or {}
    if first:
        out += [
            "First call in a fresh process (import, trace, compile, run), wall and CPU time:",
            "",
        ]
        out += table(
            ["case", "import", "first call", "whole process, CPU"],
            [[k, t(v.get("import")), t(v.get("first_call")), t(v.get("cpu"))] for k, v in first.items()],
        )
    return targets, out


def speeds(R) -> tuple[list, list]:
    D, TT = R["disc"], R["turntable"]
    st, fa = D["steady"], D["first_answers"]
    targets_, out = [], []
    jx = "jaxnh simulate (lagrange, default)"
    cells, errs, ok = [], [], []
    for key, blk in st.items():
        r = blk["ratios"].get("SciPy's better / jaxnh")
        better = blk.get("better_scipy") or "?"
        if r is not None:
            cells.append(f"error ≤ {blk['target']:.0e}: {r:.1f}× ({'RK45' if 'RK45' in better else 'DOP853'})")
            errs.append(f"{e(blk['rows'][jx]['error'])} vs {e(blk['rows'][better]['error'])}")
            ok.append(r >= 20)
    targets_.append(
        [
            "rolling disc in Kane's speeds, steady solve at matched error: SciPy's better method (RK45 or DOP853, "
            "lambdified SymPy) / jaxnh `simulate` (defaults but rtol)",
            "≥ 20×",
            "; ".join(cells) or "—",
            "; ".join(errs) or "—",
            met(all(ok)) if ok else "—",
        ]
    )
    fr = fa["ratios"]
    J, G, H = (fa["rows"][k] for k in ("jaxnh", "jaxnh, first gradient", "hand JAX (diffrax Tsit5)"))
    if "jaxnh / hand (CPU)" in fr:
        targets_.append(
            [
                "rolling disc: first answer in a fresh process, jaxnh / hand-written diffrax program of SymPy's "
                "equations",
                "≤ 1.5×",
                f"{fr['jaxnh / hand (CPU)']:.2f}× CPU ({fr['jaxnh / hand (wall)']:.2f}× wall)",
                f"{e(J['error'])} vs {e(H['error'])}",
                met(fr["jaxnh / hand (CPU)"] <= 1.5),
            ]
        )
    if "gradient / answer (CPU)" in fr:
        targets_.append(
            [
                "rolling disc: first gradient / first answer (fresh processes)",
                "≤ 2.5×",
                f"{fr['gradient / answer (CPU)']:.2f}× CPU ({fr['gradient / answer (wall)']:.2f}× wall)",
                f"gradient {e(G['error'])} (relative)",
                met(fr["gradient / answer (CPU)"] <= 2.5),
            ]
        )
    L = TT["long"]
    q_, e_, e6 = (L["rows"][k] for k in ("quaternion", "Euler ZYX, default max_steps", "Euler ZYX, max_steps 10⁶"))
    targets_.append(
        [
            f"ball on a turntable, {L['t_end']:.0f} s at rtol {TT['rtol']:g}: unit quaternion against ZYX Euler angles "
            "(q̇)",
            "—",
            f"steps {q_['steps']:,} vs {e6['steps']:,}; Euler with the default max_steps "
            + ("completes" if e_["success"] else f"stops at t = {e_['reached']:.0f} s")
            + f"; centre {e(q_['centre_error'])} vs {e(e6['centre_error'])} m",
            "closed form",
            "—",
        ]
    )
    m = R["machine"]
    out += [
        "## Speeds and quaternions: the rolling disc and the ball on a turntable",
        "",
        f"Measured by `python -m benchmarks.speeds{' --quick' if R.get('quick') else ''}` at revision "
        f"`{m['revision']}`"
        + (" with uncommitted changes in jaxnh/" if m["uncommitted"] else "")
        + f" (source digest `{m['digest']}`), {m['date']}, load average {m['load_average'][0]:.1f} at the end.",
        "",
        f"**The rolling disc** (`jaxnh.models.disc_speeds`, the disc of `jaxnh.models.disc`): a wobbling disc, "
        f"the steady circle at lean {D['lean']:g} rad and yaw rate {D['yaw_rate']:g} rad/s (spin "
        f"{D['spin']:.2f} rad/s) plus a lean rate of {D['lean_rate']:g} rad/s, {D['t_end']:g} s, "
        f"{D['n_report']} report times. Every contender integrates in the generalized speeds of SymPy's "
        "rolling-disc example (u1, u2, u3: the disc's angular velocity in the lean frame). jaxnh: `simulate` with "
        "the user's defaults but rtol (atol = rtol/100), Lagrange's form (the default; state q and five speeds, "
        "the slip speeds held at zero by multipliers) and Appell's (state q, u1, u2, u3, as SymPy's). SciPy: "
        "SymPy's `KanesMethod` (the example's frames and speeds, x and y added as kinematic equations), "
        "`lambdify(cse=True)` with NumPy, `solve_ivp`. Hand JAX: the same SymPy equations printed as `jax.numpy` "
        "source, `diffrax.Tsit5`, jitted. Errors: the largest absolute error over the report times of q and "
        "u1…u3 against SciPy's DOP853 at rtol 1e-13 on SymPy's equations (`jaxnh.models.disc`, in q̇, at rtol "
        f"1e-12 differs from it by {e(D['reference_check'])}). Matched error: each contender's loosest tolerance "
        "on a half-decade grid that reaches the target error; CPU time per solve after compilation, medians over "
        "interleaved rounds.",
        "",
    ]
    for key, blk in st.items():
        better = blk.get("better_scipy")
        out += [f"**Target error {blk['target']:.0e}**", ""]
        body = []
        for k, r in blk["rows"].items():
            mine = blk["ratios"].get("SciPy's better / " + ("jaxnh" if k == jx else k))
            ratio = "1×" if k == better else (f"{mine:.1f}×" if mine is not None else "")
            body.append(
                [
                    k + (" (SciPy's better)" if k == better else ""),
                    f"{r['rtol']:.1e}" if r["rtol"] else "not reached",
                    e(r["error"]),
                    f"{r['steps']:.0f}" if r["steps"] is not None else "—",
                    t(r["cpu"]),
                    ratio,
                ]
            )
        out += table(["contender", "rtol", "error", "steps", "CPU per solve", "SciPy's better / this"], body)
        if "jaxnh / hand JAX" in blk["ratios"]:
            out += [f"jaxnh (default) / hand JAX: {blk['ratios']['jaxnh / hand JAX']:.2f}×.", ""]
    fc = D.get("field_cost")
    if fc:
        out += [
            "The equations' own cost, CPU per `diffrax.Tsit5` step at a constant step (1000 steps, jitted, no "
            "step-size control): "
            + ", ".join(f"{k} {t(v)}" for k, v in fc.items() if not k.startswith("SciPy"))
            + "; SciPy's lambdified right-hand side per call (six per step): "
            + ", ".join(t(v) for k, v in fc.items() if k.startswith("SciPy"))
            + ".",
            "",
        ]
    rtols = ", ".join(f"{k.split(' (')[0]}: rtol {v:.1e}" for k, v in fa["rtols"].items())
    out += [
        f"First answers, fresh processes (every core, the user's settings, no compilation cache), medians of "
        f"{fa['repeats']}, from before the first import to the answer on the host, at the tolerances matched to "
        f"the first target ({rtols}). "
        "The gradient: `jax.grad` of the final coordinates' sum with respect to every parameter (m, r, I1, I3, g); "
        "its error, relative, along a random direction against a Richardson-extrapolated central difference of "
        "the reference. SymPy + SciPy includes the derivation and `lambdify`.",
        "",
    ]
    out += table(
        ["process", "CPU", "wall", "of which the imports (wall)", "error"],
        [
            [k, t(v["cpu_median"]), t(v["wall_median"]), t(v.get("imports_median")), e(v["error"])]
            for k, v in fa["rows"].items()
        ],
    )
    out += [
        f"**The ball on a turntable** (`jaxnh.models.turntable`, a unit quaternion with angular-velocity speeds) "
        f"against the same ball in ZYX Euler angles (yaw, pitch, roll) written in q̇ "
        f"(`benchmarks.speeds.euler_mechanism`), both at rtol {TT['rtol']:g}, atol {TT['atol']:g}, `simulate`'s "
        "default formulation and solver. Centre: error against `turntable.closed_form` (m); orientation: largest "
        "Frobenius norm of the difference of the rotation matrices against the quaternion model at rtol "
        f"{TT['ref_rtol']:g}; both over the times the solve reached. From the issue's state (the identity "
        f"orientation), {L['t_end']:.0f} s:",
        "",
    ]

    def cos_cell(r):
        if r.get("min_cos_pitch") is None:
            return "—"
        return f"{np.degrees(np.arccos(r['min_cos_pitch'])):.2f}° at t = {r['at']:.0f} s"

    out += table(
        [
            "model",
            "outcome",
            "reached",
            "steps (accepted)",
            "centre error",
            "orientation error",
            "pitch closest to ±90°",
            "CPU",
        ],
        [
            [
                k,
                "success" if r["success"] else r["message"][:60],
                f"{r['reached']:.0f} s",
                f"{r['steps']:,} ({r['accepted']:,})",
                e(r["centre_error"]),
                e(r["orientation_error"]),
                cos_cell(r),
                t(r.get("cpu")),
            ]
            for k, r in L["rows"].items()
        ],
    )
    N = TT["near_lock"]
    out += [
        f"Starts near gimbal lock: the same state with the ball turned by π/2 − δ about y (pitch π/2 − δ), "
        f"{N['t_end']:.0f} s, `simulate`'s default max_steps:",
        "",
    ]
    body = []
    for r in N["rows"].values():
        qn, eu = r["quaternion"], r["euler"]
        body.append(
            [
                f"{r['delta']:g}",
                f"{qn['steps']:,}, {e(qn['centre_error'])}, {e(qn['orientation_error'])}",
                ("success" if eu["success"] else eu["message"][:60]) + f" (reached {eu['reached']:.0f} s)",
                f"{eu['steps']:,}, {e(eu['centre_error'])}, {e(eu['orientation_error'])}",
            ]
        )
    out += table(
        [
            "δ (rad)",
            "quaternion: steps, centre error, orientation error",
            "Euler: outcome",
            "Euler: steps, centre error, orientation error",
        ],
        body,
    )
    return targets_, out


def _interp(points, err):
    """Time at `err` on a sorted (error, time) curve by log-log interpolation, None outside it."""
    pts = [(a, b) for a, b in points if a > 0 and np.isfinite(a)]
    for (e0, t0), (e1, t1) in zip(pts, pts[1:]):
        if e0 <= err <= e1 and e1 > e0:
            w = np.log(err / e0) / np.log(e1 / e0)
            return float(np.exp(np.log(t0) + w * np.log(t1 / t0)))
    return None


def figures(results):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    C.FIGURES.mkdir(parents=True, exist_ok=True)
    if "size" in results:
        R = results["size"]
        fa = R["first_answers"]
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        default = R.get("default", "appell")
        for k, label in ((default, f"jaxnh {default}"), ("sympy", "SymPy + SciPy")):
            pts = [(N, fa[f"{N} {k}"]["cpu_median"]) for N in R["ns_compare"] if fa.get(f"{N} {k}", {}).get("cpu")]
            if pts:
                ax[0].plot(*zip(*pts), "o-", label=label)
        ax[0].set(xlabel="N trailers", ylabel="first answer, CPU s (fresh process)", title="against SymPy")
        for k in ("appell", "lagrange", "gradient"):
            pts = [
                (N, fa[f"{N} {k}"]["cpu_after_import_median"])
                for N in R["ns_growth"]
                if fa.get(f"{N} {k}", {}).get("cpu_after_import_median")
            ]
            if pts:
                ax[1].loglog(*zip(*pts), "o-", label=k)
        ax[1].set(xlabel="N trailers", ylabel="CPU s after the import", title="growth")
        ax[1].set_xticks(R["ns_growth"], [str(n) for n in R["ns_growth"]])
        ax[1].minorticks_off()
        for a in ax:
            a.legend()
            a.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(C.FIGURES / "chain.png", dpi=110)
        plt.close(fig)
    if "precision" in results:
        rows = results["precision"]["rows"]
        mechanisms = results["precision"].get("mechanisms", ["ball"])
        fig, axes = plt.subplots(1, len(mechanisms), figsize=(5 * len(mechanisms), 4.2), squeeze=False)
        for ax, mech in zip(axes[0], mechanisms):
            mine = [r for r in rows.values() if r.get("mechanism", "ball") == mech]
            for key in sorted({(r["method"], r["solver"]) for r in mine}):
                pts = sorted((r["cpu"], r["error"]) for r in mine if (r["method"], r["solver"]) == key)
                ax.loglog(*zip(*pts), "o-" if key[1] == "default" else "x--", label=f"{key[0]}, {key[1]}")
            ax.set(xlabel="CPU time per solve, s", ylabel="largest error (coordinates, velocities)", title=mech)
            ax.legend(fontsize=11)
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(C.FIGURES / "wp_ball.png", dpi=110)
        plt.close(fig)


def main():
    results = {s: r for s in STUDIES if (r := C.load(s)) is not None}
    targets, sections = [], []
    studies = (
        ("headline", headline),
        ("size", size),
        ("first_answer", first_answer),
        ("precision", precision),
        ("friction", friction),
        ("speeds", speeds),
    )
    for name, fn in studies:
        if name in results:
            tg, sec = fn(results[name])[:2]
            targets += tg
            sections += sec
        else:
            sections += [f"## {name}", "", f"Not run (`python -m benchmarks.{name}`).", ""]
    figures(results)
    lines = (
        ["# jaxnh benchmarks", ""]
        + stamp(results)
        + [
            "Written by `python -m benchmarks.run_all` (`make bench`; `make bench-quick` writes a short run to "
            "`benchmarks/quick/`). Every number below comes from `results/*.json` beside this file.",
            "",
            HOW_TO_READ,
            "",
            "## Targets",
            "",
        ]
    )
    lines += table(["target", "goal", "measured", "error (jaxnh vs peer)", "met"], targets)
    lines += sections
    lines += ["## Other studies", "", "Reports beside this file, each stamped with what it measured:", ""]
    lines += [f"* [{k}]({k}): {v}" for k, v in RECORDS.items() if (C.HERE / k).exists()] + [""]
    (C.OUT / "RESULTS.md").write_text("\n".join(lines))
    C.log(f"[report] wrote {C.OUT / 'RESULTS.md'}")


if __name__ == "__main__":
    main()
