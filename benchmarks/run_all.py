"""Run every benchmark, then write the figures and benchmarks/RESULTS.md.

    python -m benchmarks.run_all            # the performance suite (what `make bench` runs)
    python -m benchmarks.run_all --quick    # fewer solvers, tolerances and sizes
    python -m benchmarks.run_all --only work_precision gradients
    python -m benchmarks.run_all --all      # also the project's other benchmark scripts

Each benchmark runs in its own Python process (no JAX caches shared, one
failure does not stop the rest). With `--all` the other benchmark scripts of
the project (stability, calibration, sweeps, bicycle cost: they write their
own reports, linked from RESULTS.md, and some take tens of minutes) are run
too when present, with their quick option under `--quick` if they offer one
(under `--quick` a script without one is skipped).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

from . import common as C


OURS = [
    "work_precision",
    "overhead",
    "field_cost",
    "throughput",
    "gradients",
    "compile_time",
    "lean_loop",
    "field_size",
    "cache_effect",
]
ARGS = {"cache_effect": (["--first-answer", "--repeats", "5"], ["--first-answer", "--repeats", "1"])}
"""(full, quick) arguments of the scripts that do not take plain / --quick."""
OTHERS = ["stability", "calibration", "sweep_bench", "bicycle_cost"]


def _quick_flag(module: str) -> list:
    """The quick option a script offers (from its --help), if any."""
    try:
        out = subprocess.run(
            [sys.executable, "-m", f"benchmarks.{module}", "--help"],
            capture_output=True,
            text=True,
            cwd=str(C.HERE.parent),
            timeout=120,
        )
    except subprocess.TimeoutExpired:
        return []
    return ["--quick"] if "--quick" in out.stdout else []


def run(module: str, args: list) -> dict:
    C.log(f"\n=== benchmarks.{module} {' '.join(args)}")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", f"benchmarks.{module}", *args], cwd=str(C.HERE.parent))
    dt = time.perf_counter() - t0
    C.log(f"=== benchmarks.{module}: {'ok' if proc.returncode == 0 else f'FAILED ({proc.returncode})'} in {dt:.0f} s")
    return dict(module=module, args=args, returncode=proc.returncode, seconds=dt)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="short run of every benchmark")
    ap.add_argument("--only", nargs="*", help=f"run only these of {OURS + OTHERS}")
    ap.add_argument("--all", action="store_true", help=f"also run {OTHERS} (long)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    log = []
    for m in OURS:
        if a.only and m not in a.only:
            continue
        full, quick = ARGS.get(m, ([], ["--quick"]))
        log.append(run(m, quick if a.quick else full))
    if a.all or (a.only and any(m in OTHERS for m in a.only)):
        for m in OTHERS:
            if (a.only and m not in a.only) or not (C.HERE / f"{m}.py").exists():
                continue
            flag = _quick_flag(m) if a.quick else []
            if a.quick and not flag:
                C.log(f"\n=== benchmarks.{m}: skipped under --quick (it has no quick option)")
                continue
            log.append(run(m, flag))
    log.append(run("report", []))
    C.save("run_all", dict(runs=log, quick=a.quick, seconds=time.perf_counter() - t0))
    failed = [r["module"] for r in log if r["returncode"] != 0]
    C.log(
        f"\nrun_all: {len(log)} scripts in {time.perf_counter() - t0:.0f} s; "
        + (f"FAILED: {failed}" if failed else "all ok")
        + f"; see {C.OUT / 'RESULTS.md'}"
    )
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
