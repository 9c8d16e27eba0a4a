"""What the persistent compilation cache saves: a user's first simulation in a fresh process.

Each case runs `import jaxnh` plus the README's variator `simulate` in a new
Python process, with an empty cache folder ("cold"), then again in new
processes reading the folder the first one wrote ("warm"). Cases: JAX's
default write threshold (1 s) against jaxnh's `MIN_COMPILE_TIME_SECS` and 0;
with equinox's host-callback checks (`EQX_ON_ERROR` default) and without
(`EQX_ON_ERROR=nan`), since JAX never caches programs with host callbacks.
Also `jaxnh fit` on the embedded record, cold and warm.

    python benchmarks/cache_effect.py [--repeats 3] [--fit]

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


def run_user(env):
    out = subprocess.run([sys.executable, "-c", USER], capture_output=True, text=True, env=env, timeout=600)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[:1500] + " ... " + out.stderr[-1500:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_fit(env):
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-m", "jaxnh.cli", "fit", "--quiet"], capture_output=True, text=True, env=env, timeout=900
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
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
