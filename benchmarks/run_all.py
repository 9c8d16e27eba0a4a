"""The benchmark suite's one runner: every study, then benchmarks/RESULTS.md and its figures.

    python -m benchmarks.run_all            # the suite (`make bench`)
    python -m benchmarks.run_all --quick    # a short run (`make bench-quick`, written to benchmarks/quick/)
    python -m benchmarks.run_all --only size first_answer
    python -m benchmarks.run_all --all      # also the reliability report (RELIABILITY.md)
    python -m benchmarks.run_all --stale    # is RESULTS.md older than today's jaxnh/? (exit status 1 if so)

Studies (each in its own process; one failure does not stop the rest):

* headline — the variator: `simulate` with defaults against eq. (9) by hand in
  diffrax, the Appell field per step, SciPy on SymPy's derivation, a numba loop;
  gradient and batch costs.
* size — a car pulling N trailers: first answers against SymPy's pipeline,
  steady solves against SciPy and hand JAX, compile-time growth to N = 32.
* first_answer — fresh processes, cold and with the compilation cache, against
  hand-written diffrax programs.
* precision — work–precision of the rolling ball, Appell against Lagrange.
* friction — what friction-held contacts cost: a scene without them, and
  solves with 0, 1 and 2 transitions.
* speeds — speeds and quaternions: the rolling disc in Kane's speeds against
  SymPy's KanesMethod with SciPy and a hand-written diffrax program (steady
  solves at matched error, first answers, first gradient); the ball on a
  turntable in a quaternion against Euler angles.

Not run here: studies that write their own report beside RESULTS.md (each run as
`python -m benchmarks.<name>`, with a `--quick` smoke run written to
benchmarks/quick/): stability (STABILITY.md), calibration (CALIBRATION.md),
experiment_design (EXPERIMENT.md), fit_cost (FIT_COST.md), model_error
(MODEL_ERROR.md), sweep_bench (SWEEP.md), bicycle_cost (BICYCLE.md).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from . import common as C


STUDIES = ["headline", "size", "first_answer", "precision", "friction", "speeds"]
EXTRA = ["reliability"]  # writes RELIABILITY.md itself


def run(module: str, args: list) -> dict:
    C.log(f"\n=== benchmarks.{module} {' '.join(args)}")
    t0 = time.perf_counter()

    def unpin():  # this process was pinned by common; a study pins itself and its fresh processes use every core
        if C._CPUS0:
            os.sched_setaffinity(0, set(C._CPUS0))

    env = dict(C._ENV0, **({"JAXNH_BENCH_OUT": str(C.OUT)} if C.OUT != C.HERE else {}))
    proc = subprocess.run(
        [sys.executable, "-m", f"benchmarks.{module}", *args], cwd=str(C.ROOT), env=env, preexec_fn=unpin
    )
    dt = time.perf_counter() - t0
    C.log(f"=== benchmarks.{module}: {'ok' if proc.returncode == 0 else f'FAILED ({proc.returncode})'} in {dt:.0f} s")
    return dict(module=module, args=args, returncode=proc.returncode, seconds=dt)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a short run of every study")
    ap.add_argument("--only", nargs="*", choices=STUDIES + EXTRA, help="run only these")
    ap.add_argument("--all", action="store_true", help=f"also {EXTRA}")
    ap.add_argument("--stale", action="store_true", help="only say whether RESULTS.md is stale")
    a = ap.parse_args(argv)
    if a.stale:
        path = C.OUT / "RESULTS.md"
        old = C.stale(path)
        C.log(f"{path}: {'STALE (jaxnh/ changed since it was measured)' if old else 'up to date with jaxnh/'}")
        sys.exit(1 if old else 0)
    t0 = time.perf_counter()
    todo = [m for m in STUDIES + (EXTRA if a.all else []) if not a.only or m in a.only]
    if a.quick and any(m in EXTRA for m in todo):
        C.log(f"run_all: {EXTRA} skipped under --quick (they write their reports beside the suite, not to {C.OUT})")
        todo = [m for m in todo if m not in EXTRA]
    log = [run(m, ["--quick"] if a.quick else []) for m in todo]
    log.append(run("report", []))
    failed = [r["module"] for r in log if r["returncode"] != 0]
    C.log(
        f"\nrun_all: {len(log)} scripts in {time.perf_counter() - t0:.0f} s; "
        + (f"FAILED: {failed}" if failed else "all ok")
        + f"; see {C.OUT / 'RESULTS.md'}"
    )
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
