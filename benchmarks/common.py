"""Shared machinery of the benchmarks: solvers, compiled solves, interleaved timing, output.

Timing rules (SciMLBenchmarks' work-precision methodology): every JAX function is compiled ahead
of time (`jit(...).lower(...).compile()`, whose duration is the compile time
reported), then called repeatedly; contenders are interleaved round by round so
that load from other processes hits them alike, and times are medians over
rounds. Ratios are medians of the per-round ratios.

The machine these run on is shared (2 cores, several busy processes), so a
wall-clock time mostly measures how long a call waited for a core: a 3.5 ms
solve took 3.3–20 ms of wall time but 3.3–3.7 ms of process CPU time. Every
time is therefore recorded both ways; tables and ratios use the CPU time
(`time.process_time`, all threads of the process), which is what the call
costs on an idle core.
"""

from __future__ import annotations

import datetime
import json
import os
import pathlib
import platform
import time
from typing import Callable


# XLA on CPU runs independent operations of one program on a thread pool whose
# idle workers spin: the process then burns CPU time waiting. Measured here: a
# "lagrange" solve in the unrolled Tsit5 took 49–130 ms of CPU time (median 63)
# with XLA's thread pool on both cores, 45–55 ms (median 51) with the process
# pinned to one core; XLA's flags below alone did not remove the spread. So each
# benchmark process is pinned to one core before JAX starts (XLA sizes its pools
# from the affinity mask) and its CPU time is what a call costs on that core.
# These solves are too small to gain from threads. JAXNH_BENCH_XLA_THREADS=default
# keeps XLA's own setting (no pinning, no flags).
XLA_SINGLE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
PINNED_CPU = None
if os.environ.get("JAXNH_BENCH_XLA_THREADS") != "default":
    if "intra_op_parallelism" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + XLA_SINGLE_THREAD).strip()
    if hasattr(os, "sched_setaffinity"):
        _cpus = sorted(os.sched_getaffinity(0))
        PINNED_CPU = _cpus[os.getpid() % len(_cpus)]  # spread concurrent benchmark processes
        os.sched_setaffinity(0, {PINNED_CPU})

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.solvers import DOP853, Tsit5  # noqa: E402


HERE = pathlib.Path(__file__).resolve().parent
# Where JSON results, figures and RESULTS.md go: benchmarks/ itself (the committed record), or the
# folder in $JAXNH_BENCH_OUT (`make bench-quick` uses benchmarks/quick/ so a short run does not
# overwrite the full results).
OUT = pathlib.Path(os.environ["JAXNH_BENCH_OUT"]).resolve() if os.environ.get("JAXNH_BENCH_OUT") else HERE
RESULTS = OUT / "results"
FIGURES = OUT / "figures"


# label -> factory; "Tsit5u" is jaxnh's unrolled Tsit5 (jaxnh.solvers.Tsit5), "Tsit5" diffrax's
SOLVERS: dict[str, Callable] = {
    "Tsit5": diffrax.Tsit5,
    "Tsit5u": Tsit5,
    "Dopri5": diffrax.Dopri5,
    "Dopri8": diffrax.Dopri8,
    "DOP853": DOP853,
    "Kvaerno5": diffrax.Kvaerno5,
}
SOLVER_LABELS = {
    "Tsit5": "diffrax Tsit5",
    "Tsit5u": "jaxnh Tsit5 (unrolled)",
    "Dopri5": "diffrax Dopri5",
    "Dopri8": "diffrax Dopri8",
    "DOP853": "jaxnh DOP853",
    "Kvaerno5": "diffrax Kvaerno5",
}


def tol_pair(rtol: float) -> tuple[float, float]:
    """(rtol, atol) of a sweep point: atol = rtol / 100, as simulate's defaults (1e-8, 1e-10)."""
    return rtol, rtol / 100


# --------------------------------------------------------------------------- compiled solves


def jaxnh_solver_fn(
    mech, method, q0, qd0, params, ts, solver, *, independent=None, record=(), max_steps=100_000, adjoint=None
):
    """A jitted `f(params, y0, rtol, atol) -> (q, qd, num_steps, recorded)` around `simulate`.

    The tolerances are traced (they enter through the step-size controller), so
    one compilation serves the whole sweep; `y0` is `(q0, qd0)`. Returns (f, y0).
    """
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint

    def f(p, y0, rtol, atol):
        sol = nh.simulate(
            mech,
            p,
            y0[0],
            y0[1],
            ts,
            method,
            solver=solver,
            record=tuple(record),
            independent=independent,
            max_steps=max_steps,
            adjoint=adjoint,
            throw=False,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        )
        out = {k: getattr(sol, k) for k in record}
        return sol.q, sol.qd, sol.stats["num_steps"], out

    return jax.jit(f), (q0, qd0)


def hand_solver_fn(vector_field, unpack, ts, solver, max_steps=100_000):
    """A jitted `f(params, y0, rtol, atol) -> (q, qd, num_steps, {})` for a hand-written vector field."""

    def f(p, y0, rtol, atol):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            solver,
            ts[0],
            ts[-1],
            None,
            y0,
            args=p,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            max_steps=max_steps,
            throw=False,
        )
        q, qd = unpack(sol.ys, ts, p)
        return q, qd, sol.stats["num_steps"], {}

    return jax.jit(f)


def compile_aot(jitted, *args):
    """Compile `jitted` for `args` ahead of time: (compiled callable, {"cpu": s, "wall": s})."""
    compiled, cpu, wall = timed(lambda: jitted.lower(*args).compile())
    return compiled, {"cpu": cpu, "wall": wall}


def block(x):
    return jax.block_until_ready(x)


# --------------------------------------------------------------------------- timing


def interleave(calls: dict, rounds: int = 7, budget: float | None = None, min_rounds: int = 3) -> dict:
    """Time each zero-argument callable once per round, in turn, for `rounds` rounds
    (fewer if `budget` seconds of wall time run out after `min_rounds`).

    Returns name -> {"cpu": [...], "wall": [...]} in seconds. CPU time is the
    process's (`time.process_time`): on a shared machine it is what a call costs
    without the waiting for a core that wall time also counts.
    """
    times = {k: {"cpu": [], "wall": []} for k in calls}
    start = time.perf_counter()
    for r in range(rounds):
        for k, fn in calls.items():
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            times[k]["cpu"].append(time.process_time() - c0)
            times[k]["wall"].append(time.perf_counter() - w0)
        if budget is not None and r + 1 >= min_rounds and time.perf_counter() - start > budget:
            break
    return times


def timed(fn):
    """(result, cpu seconds, wall seconds) of one call."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - w0


def median(xs) -> float:
    return float(np.median(np.asarray(xs)))


def paired_ratio(num, den) -> float:
    """Median over rounds of num[i] / den[i] (both timed in the same round)."""
    n = min(len(num), len(den))
    return float(np.median(np.asarray(num[:n]) / np.asarray(den[:n])))


def max_error(q, qd, q_ref, qd_ref) -> float:
    """Max abs error over the report times, coordinates and velocities."""
    return float(
        max(np.max(np.abs(np.asarray(q) - np.asarray(q_ref))), np.max(np.abs(np.asarray(qd) - np.asarray(qd_ref))))
    )


def time_at_error(points, target: float) -> float | None:
    """Run time at a given error by log-log interpolation between the two sweep points
    that bracket it (points: iterable of (error, time)); None when not bracketed."""
    pts = sorted((e, t) for e, t in points if e > 0 and np.isfinite(e))
    for (e0, t0), (e1, t1) in zip(pts, pts[1:]):
        if e0 <= target <= e1:
            if e1 == e0:
                return float(min(t0, t1))
            w = (np.log(target) - np.log(e0)) / (np.log(e1) - np.log(e0))
            return float(np.exp(np.log(t0) + w * (np.log(t1) - np.log(t0))))
    return None


# --------------------------------------------------------------------------- scipy


def scipy_solve(f, y0, ts, method: str, rtol: float, atol: float):
    from scipy.integrate import solve_ivp

    ts = np.asarray(ts)
    sol = solve_ivp(f, (ts[0], ts[-1]), np.asarray(y0, dtype=float), method=method, t_eval=ts, rtol=rtol, atol=atol)
    return sol


# --------------------------------------------------------------------------- output


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import diffrax as dfx
    import equinox
    import jaxlib
    import scipy

    return dict(
        cpu=cpu,
        cores=os.cpu_count(),
        platform=platform.platform(),
        python=platform.python_version(),
        jax=jax.__version__,
        jaxlib=jaxlib.__version__,
        diffrax=dfx.__version__,
        equinox=equinox.__version__,
        numpy=np.__version__,
        scipy=scipy.__version__,
        jaxnh=nh.__version__,
        devices=[str(d) for d in jax.devices()],
        load_average=list(os.getloadavg()),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        pinned_cpu=PINNED_CPU,
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        jaxnh_revision=_revision(),
    )


def solver_key(solver) -> str:
    """The SOLVERS label of a solver instance ("Tsit5" is diffrax's, "Tsit5u" jaxnh's unrolled one)."""
    if isinstance(solver, Tsit5):
        return "Tsit5u"
    return type(solver).__name__


def _revision() -> str:
    """git commit of the working tree, with "+changes" when it has uncommitted edits."""
    import subprocess

    try:
        root = str(HERE.parent)
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=root, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "jaxnh"],
            capture_output=True,
            text=True,
            cwd=root,
            timeout=10,
        ).stdout.strip()
        return (rev or "unknown") + (" + uncommitted changes in jaxnh/" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def save(name: str, data: dict) -> pathlib.Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = dict(data)
    data.setdefault("machine", machine())
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=1, default=_jsonable))
    return path


def load(name: str) -> dict | None:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _jsonable(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, (np.ndarray, jax.Array)):
        return np.asarray(x).tolist()
    raise TypeError(type(x))


def log(*a):
    print(*a, flush=True)


def f64(x):
    return jnp.asarray(x, dtype=jnp.float64)
