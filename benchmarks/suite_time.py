"""How long the test suite takes, as `make test` runs it: with an empty compilation cache
("cold", a fresh machine such as CI's) and again on the folder that run wrote ("warm", a
developer's second run).

    python -m benchmarks.suite_time [--repeats 1] [--quick]

Each run is `python -m pytest tests` (the project's pytest options: two xdist workers,
files distributed whole) in a new process with `JAXNH_CACHE_DIR` pointing at a fresh
folder, so nothing from an earlier session is reused. Wall-clock seconds, the outcome line
of pytest, and the summed test time per file (from `--durations=0`), which shows where a
cold run spends its time. `--quick` times `make test-quick`'s selection (`-m "not slow"`).
Writes `results/suite_time.json`; `report.py` renders it into RESULTS.md.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

from benchmarks import common as C
from benchmarks.cache_effect import _as_a_user


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DURATION = re.compile(r"^\s*([\d.]+)s (?:call|setup|teardown)\s+(tests/[^:\s]+)::")
OUTCOME = re.compile(r"(\d+ (?:passed|failed|error)[^\n]*) in [\d.]+s")


def run_suite(cache: str, quick: bool) -> dict:
    """One run of the suite in a new process on the cache folder `cache`."""
    env = dict(os.environ, JAXNH_CACHE_DIR=cache)
    cmd = [sys.executable, "-m", "pytest", "tests", "-p", "no:cacheprovider", "--durations=0"]
    if quick:
        cmd += ["-m", "not slow"]
    t0 = time.perf_counter()
    # as a developer runs it: every core, JAX's own threads (no benchmark pinning or XLA flags)
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=3600, **_as_a_user(env))
    wall = time.perf_counter() - t0
    per_file: dict[str, float] = collections.defaultdict(float)
    for line in out.stdout.splitlines():
        m = DURATION.match(line)
        if m:
            per_file[m.group(2)] += float(m.group(1))
    outcome = OUTCOME.search(out.stdout)
    return {
        "wall": wall,
        "returncode": out.returncode,
        "outcome": outcome.group(1) if outcome else out.stdout[-300:],
        "per_file": dict(sorted(per_file.items(), key=lambda kv: -kv[1])),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=1, help="cold/warm pairs (each cold run takes ~10 min)")
    ap.add_argument("--quick", action="store_true", help="the quick tier only (-m 'not slow')")
    args = ap.parse_args()
    runs = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as d:
            cache = os.path.join(d, "cache")
            cold = run_suite(cache, args.quick)
            print(f"cold: {cold['wall']:.0f} s  ({cold['outcome']})", flush=True)
            warm = run_suite(cache, args.quick)
            print(f"warm: {warm['wall']:.0f} s  ({warm['outcome']})", flush=True)
            runs.append({"cold": cold, "warm": warm})
    result = {
        "tier": "quick" if args.quick else "full",
        "cold_median": statistics.median(r["cold"]["wall"] for r in runs),
        "warm_median": statistics.median(r["warm"]["wall"] for r in runs),
        "runs": runs,
        "cpus": os.cpu_count(),
    }
    C.save("suite_time", result)
    print(f"cold median {result['cold_median']:.0f} s, warm median {result['warm_median']:.0f} s")


def section(res) -> list:
    """RESULTS.md lines for `results/suite_time.json` (nothing when it is missing)."""
    if not res:
        return []
    L = [
        "## Test suite time (issue 16, item 5)",
        "",
        f"`python -m benchmarks.suite_time`: the {res['tier']} suite as `make test` runs it (two xdist workers on "
        f"{res['cpus']} cores; CPU: {res.get('machine', {}).get('cpu', 'not recorded')}), in a new process "
        "with an empty cache folder (cold: a fresh machine, as CI) and "
        "again on the folder that run wrote (warm). Target: at most 4 minutes on 2 idle cores, using the cache. "
        "Not part of `make bench` (a cold and a warm run take about 12 minutes); rendered here from the last "
        "run's JSON.",
        "",
        "| run | wall time | outcome |",
        "|---|---:|---|",
    ]
    for i, r in enumerate(res["runs"]):
        for kind in ("cold", "warm"):
            L.append(f"| {kind} {i + 1} | {r[kind]['wall']:.0f} s | {r[kind]['outcome']} |")
    L += ["", "Summed test time per file, cold run 1 (both workers together; the ten largest):", ""]
    L += ["| file | cold | warm |", "|---|---:|---:|"]
    cold, warm = res["runs"][0]["cold"]["per_file"], res["runs"][0]["warm"]["per_file"]
    for name in list(cold)[:10]:
        L.append(f"| `{name}` | {cold[name]:.0f} s | {warm.get(name, 0.0):.0f} s |")
    L.append("")
    return L


if __name__ == "__main__":
    main()
