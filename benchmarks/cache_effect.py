"""What the persistent compilation cache saves: a user's first simulation in a fresh process.

Each case runs `import jaxnh` plus the README's variator `simulate` in a new
Python process, with an empty cache folder ("cold"), then again in new
processes reading the folder the first one wrote ("warm"). Cases: JAX's
default write threshold (1 s) against jaxnh's `MIN_COMPILE_TIME_SECS` and 0;
with equinox's host-callback checks (`EQX_ON_ERROR` default) and without
(`EQX_ON_ERROR=nan`), since JAX never caches programs with host callbacks.
Also `jaxnh fit` on the embedded record, cold and warm.

    python benchmarks/cache_effect.py [--repeats 3] [--fit]
    python -m benchmarks.cache_effect --first-answer [--repeats 5]

`--first-answer` measures only what issue 16's targets name (the variator with
jaxnh's default settings, cold and warm; `jaxnh fit` cold and warm), writes
`results/first_answer.json` and is rendered into RESULTS.md by `report.py`.

Prints medians (s) and the number of cache entries written: "cold"/"warm" are
the wall clock of import + first call, "first call" the part after the import
(the import itself does not depend on the cache). Cases are interleaved
within each repeat, so a change of machine load hits all of them alike.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


USER = r"""
import time, os, json
t0 = time.perf_counter()
import jax, jax.numpy as jnp
import jaxnh as nh
from jaxnh._cache import setup_compilation_cache
path = setup_compilation_cache()
if os.environ.get("BENCH_MIN") is not None and path is not None:
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(os.environ["BENCH_MIN"]))
t_import = time.perf_counter() - t0

def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)
def U21(t):
    return 1.0 + 0.4 * jnp.sin(jnp.pi * t)
def rolling(q, qd, t, p):
    return jnp.stack([U21(t) * qd[0] - qd[1]])
def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])

mech = nh.Mechanism(T, constraints=rolling, forces=torques, names=("phi1", "phi2"))
p = {"J1": 0.02, "J2": 0.05, "M1": 0.3, "M2": -0.1}
ts = jnp.linspace(0.0, 10.0, 101)
sol = nh.simulate(mech, p, jnp.zeros(2), jnp.array([2.0, 2.0]), ts)
jax.block_until_ready(sol.q)
t_total = time.perf_counter() - t0
print(json.dumps({"import": t_import, "total": t_total, "cache": path, "q": float(sol.q[-1, 0])}))
"""


BIKE = r"""
import time, json
t0 = time.perf_counter()
import numpy as np
import jax
import jaxnh
from jaxnh.models import bicycle
A = bicycle.linear_lean_steer(5.0)
jax.block_until_ready(A)
t_first = time.perf_counter() - t0
further = []
for v in np.linspace(5.1, 6.0, 10):
    t = time.perf_counter()
    jax.block_until_ready(bicycle.linear_lean_steer(float(v)))
    further.append(time.perf_counter() - t)
eig = np.sort_complex(np.linalg.eigvals(np.asarray(A)))
err = float(np.abs(eig - np.sort_complex(np.array(bicycle.PUBLISHED["eigenvalues_v5"]))).max())
print(json.dumps({"total": t_first, "further": float(np.median(further)), "eig_error": err}))
"""


def _as_a_user(env):
    """The process as a user starts it: on every core, without XLA flags (undo the single-core
    pinning and single-thread XLA flags that `benchmarks.common` sets for CPU-time measurements,
    if this process or its parent imported it)."""
    env = {k: v for k, v in env.items() if k != "XLA_FLAGS"}
    env["JAXNH_BENCH_XLA_THREADS"] = "default"

    def unpin():
        if hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, range(os.cpu_count() or 1))

    return {"env": env, "preexec_fn": unpin}


def _run_script(script, env, timeout):
    """Run `script` in a new Python process as a user would; its last stdout line is JSON."""
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=timeout, **_as_a_user(env)
    )
    if out.returncode != 0:
        raise RuntimeError(out.stderr[:1500] + " ... " + out.stderr[-1500:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_user(env):
    return _run_script(USER, env, 600)


def run_bike(env):
    return _run_script(BIKE, env, 900)


def run_fit(env):
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-m", "jaxnh.cli", "fit", "--quiet"],
        capture_output=True,
        text=True,
        timeout=900,
        **_as_a_user(env),
    )
    el = time.perf_counter() - t0
    if out.returncode not in (0, 1):
        raise RuntimeError(out.stderr[:1500] + " ... " + out.stderr[-1500:])
    return el


def entries(path):
    return sum(len(f) for _, _, f in os.walk(path))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fit", action="store_true", help="also time `jaxnh fit` cold and warm")
    ap.add_argument("--eqx", nargs="+", default=["default", "nan"], help="EQX_ON_ERROR values to try")
    ap.add_argument(
        "--min",
        nargs="+",
        default=["1.0", "default", "0"],
        help="write thresholds to try (s; 'default' = jaxnh's MIN_COMPILE_TIME_SECS)",
    )
    ap.add_argument("--no-off", action="store_true", help="skip the cache-off case")
    ap.add_argument(
        "--first-answer", action="store_true", help="only issue 16's cases; write results/first_answer.json"
    )
    args = ap.parse_args()
    if args.first_answer:
        return first_answer(args.repeats)
    cases = [(e, m) for e in args.eqx for m in args.min]
    res = {c: {"cold": [], "warm": [], "cold_call": [], "warm_call": [], "entries": []} for c in cases}
    for _ in range(args.repeats):  # cases interleaved within each repeat, so a change of load hits all alike
        for eqx_mode, min_t in cases:
            r = res[(eqx_mode, min_t)]
            with tempfile.TemporaryDirectory() as d:
                env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
                if min_t != "default":
                    env["BENCH_MIN"] = min_t
                if eqx_mode == "nan":
                    env["EQX_ON_ERROR"] = "nan"
                c = run_user(env)
                r["entries"].append(entries(os.path.join(d, "c")))
                w = run_user(env)
                r["cold"].append(c["total"])
                r["warm"].append(w["total"])
                r["cold_call"].append(c["total"] - c["import"])
                r["warm_call"].append(w["total"] - w["import"])
    med = statistics.median
    print(
        f"{'EQX_ON_ERROR':<14}{'min_compile_time':<18}{'cold':>8}{'warm':>8}{'first call cold':>17}"
        f"{'first call warm':>17}{'entries':>9}   (s, medians of {args.repeats})"
    )
    for (eqx_mode, min_t), r in res.items():
        print(
            f"{eqx_mode:<14}{min_t:<18}{med(r['cold']):8.2f}{med(r['warm']):8.2f}{med(r['cold_call']):17.2f}"
            f"{med(r['warm_call']):17.2f}{med(r['entries']):9.0f}",
            flush=True,
        )
    if not args.no_off:
        env = dict(os.environ, JAXNH_CACHE_DIR="off")
        off = [run_user(env)["total"] for _ in range(args.repeats)]
        print(f"cache off: {statistics.median(off):6.2f} s", flush=True)
    if args.fit:
        with tempfile.TemporaryDirectory() as d:
            env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
            c = run_fit(env)
            w = [run_fit(env) for _ in range(max(1, args.repeats - 1))]
            print(
                f"jaxnh fit: cold {c:.2f} s, warm {statistics.median(w):.2f} s "
                f"(entries {entries(os.path.join(d, 'c'))})"
            )


def first_answer(repeats: int) -> None:
    """The variator (import + first simulate) and `jaxnh fit`, cold (empty cache folder) and warm (a
    second process on the folder the first wrote), `repeats` times each, interleaved."""
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from benchmarks import common as C

    keys = (
        "variator_cold",
        "variator_warm",
        "variator_warm_call",
        "fit_cold",
        "fit_warm",
        "bicycle_cold",
        "bicycle_warm",
        "bicycle_further",
        "bicycle_eig_error",
    )
    res: dict = {k: [] for k in keys}
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d:
            env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
            res["variator_cold"].append(run_user(env)["total"])
            w = run_user(env)
            res["variator_warm"].append(w["total"])
            res["variator_warm_call"].append(w["total"] - w["import"])
        with tempfile.TemporaryDirectory() as d:
            env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
            res["fit_cold"].append(run_fit(env))
            res["fit_warm"].append(run_fit(env))
        with tempfile.TemporaryDirectory() as d:
            env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
            c, w = run_bike(env), run_bike(env)
            res["bicycle_cold"].append(c["total"])
            res["bicycle_warm"].append(w["total"])
            res["bicycle_further"].append(max(c["further"], w["further"]))
            res["bicycle_eig_error"].append(max(c["eig_error"], w["eig_error"]))
    med = {k: statistics.median(v) for k, v in res.items()}
    for k in keys:
        print(f"{k:<20} median {med[k]:6.2f} s   runs {', '.join(f'{x:.2f}' for x in res[k])}")
    C.save("first_answer", {"machine": C.machine(), "repeats": repeats, "runs": res, "median": med})


def section(R: dict | None) -> list:
    """RESULTS.md lines (called by benchmarks/report.py)."""
    if not R:
        return []
    m = R["median"]
    rows = [
        ("A user's variator, import + first simulate, empty cache", 2.5, "variator_cold", "s"),
        ("The same, second process (persistent cache)", 1.0, "variator_warm", "s"),
        ("`jaxnh fit` on the embedded record, empty cache", 8.0, "fit_cold", "s"),
        ("The same, second run (cache and exported program)", 3.0, "fit_warm", "s"),
        ("Bicycle, import to the lean/steer matrix at 5 m/s, empty cache", 5.0, "bicycle_cold", "s"),
        ("The same, second process (cache and exported program)", None, "bicycle_warm", "s"),
        ("Bicycle, each further speed (median of 10, either process)", 0.010, "bicycle_further", "ms"),
    ]
    L = [
        "## First answers in fresh processes (issue 16)",
        "",
        "Wall-clock seconds from the start of a new Python process to the answer, as a user meets them: the "
        "README's variator (`import jaxnh` and one `simulate`), the command `jaxnh fit --quiet` on the "
        "embedded record (a 12-parameter fit of 1501 samples: import, reading, starting guess, the fit, "
        "standard errors, output), and the bicycle's 4×4 lean/steer state matrix "
        "(`jaxnh.models.bicycle.linear_lean_steer(5.0)`, then 10 further speeds), each process on all cores "
        "with JAX's default threads (not pinned like the CPU-time benchmarks). Medians of "
        f"{R['repeats']} interleaved runs, each cold run with an empty cache folder and each warm run a "
        "second process on the folder it wrote; `python -m benchmarks.cache_effect --first-answer`.",
        "",
        "| case | target | measured (median) | met | runs |",
        "|---|---:|---:|---|---|",
    ]
    for label, goal, key, unit in rows:
        if key not in m:
            continue
        scale = 1e3 if unit == "ms" else 1.0
        value = m[key]
        runs = ", ".join(f"{x * scale:.3g}" for x in R["runs"][key])
        if goal is None:
            target, met = "–", "–"
        else:
            target = f"≤ {goal * scale:g} {unit}"
            met = "yes" if value <= goal else f"no (+{(value / goal - 1) * 100:.0f} %)"
        L.append(f"| {label} | {target} | {value * scale:.3g} {unit} | {met} | {runs} |")
    load = R.get("machine", {}).get("load_average")
    if load:
        L += ["", f"Load average when the runs started: {load[0]:.2f} (2 cores; the machine is shared)."]
    if "bicycle_eig_error" in m:
        L += [
            "",
            f"The bicycle's eigenvalues at 5 m/s agree with Meijaard et al. (2007) to "
            f"{max(R['runs']['bicycle_eig_error']):.1e} in every run.",
        ]
    L += [
        "",
        f"Of the warm variator run, {m['variator_warm_call']:.2f} s is the first `simulate` (identifying the "
        "mechanism by the jaxprs of its functions, loading the program the first process exported, lowering "
        "it and loading its compiled form from the cache); the rest is Python and `import jaxnh` (JAX, "
        "diffrax and equinox are most of it).",
        "",
    ]
    return L


if __name__ == "__main__":
    main()
