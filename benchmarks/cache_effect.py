"""What the persistent compilation cache saves: a user's first simulation in a fresh process.

Each case runs `import jaxnh` plus the README's variator `simulate` in a new
Python process, with an empty cache folder ("cold"), then again in new
processes reading the folder the first one wrote ("warm"). Cases: JAX's
default write threshold (1 s) against jaxnh's `MIN_COMPILE_TIME_SECS` and 0;
with equinox's host-callback checks (`EQX_ON_ERROR` default) and without
(`EQX_ON_ERROR=nan`), since JAX never caches programs with host callbacks.
Also `jaxnh fit` on the embedded record, cold and warm.

    python benchmarks/cache_effect.py [--repeats 3] [--fit]

Prints medians (s) and the number of cache entries written; times are wall
clock of the whole process's measured section (import + first call).
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
    out = subprocess.run([sys.executable, "-m", "jaxnh.cli", "fit", "--quiet"], capture_output=True, text=True,
                         env=env, timeout=900)
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
    args = ap.parse_args()
    rows = []
    for eqx_mode in ("default", "nan"):
        for min_t in ("1.0", "default", "0"):
            cold, warm, imp, n_entries = [], [], [], []
            for _ in range(args.repeats):
                with tempfile.TemporaryDirectory() as d:
                    env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
                    if min_t != "default":
                        env["BENCH_MIN"] = min_t
                    if eqx_mode == "nan":
                        env["EQX_ON_ERROR"] = "nan"
                    r = run_user(env)
                    cold.append(r["total"])
                    n_entries.append(entries(os.path.join(d, "c")))
                    r = run_user(env)
                    warm.append(r["total"])
                    imp.append(r["import"])
            rows.append((eqx_mode, min_t, statistics.median(cold), statistics.median(warm), statistics.median(imp),
                         statistics.median(n_entries)))
            print(f"EQX_ON_ERROR={eqx_mode:<8} min_compile_time={min_t:<8} cold {rows[-1][2]:6.2f} s  "
                  f"warm {rows[-1][3]:6.2f} s  (import {rows[-1][4]:.2f} s)  entries {rows[-1][5]}", flush=True)
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, JAXNH_CACHE_DIR="off")
        off = [run_user(env)["total"] for _ in range(args.repeats)]
        print(f"cache off: {statistics.median(off):6.2f} s", flush=True)
    if args.fit:
        with tempfile.TemporaryDirectory() as d:
            env = dict(os.environ, JAXNH_CACHE_DIR=os.path.join(d, "c"))
            c = run_fit(env)
            w = [run_fit(env) for _ in range(max(1, args.repeats - 1))]
            print(f"jaxnh fit: cold {c:.2f} s, warm {statistics.median(w):.2f} s (entries {entries(os.path.join(d, 'c'))})")


if __name__ == "__main__":
    main()
