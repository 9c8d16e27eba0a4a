"""Shared machinery of the benchmarks: solvers, compiled solves, interleaved timing, output.

Timing rules (NOTES.md, SciMLBenchmarks): every JAX function is compiled ahead
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
import sys
import time
from typing import Callable

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.equations import formulation
from jaxnh.solvers import DOP853

from . import proposals

HERE = pathlib.Path(__file__).resolve().parent
RESULTS = HERE / "results"
FIGURES = HERE / "figures"

_integrate = sys.modules["jaxnh.simulate"]._integrate

# label -> factory; "Tsit5u" is the proposed unrolled Tsit5 (jaxnh.solvers.Tsit5 once applied)
SOLVERS: dict[str, Callable] = {
    "Tsit5": diffrax.Tsit5,
    "Tsit5u": proposals.Tsit5,
    "Dopri5": diffrax.Dopri5,
    "Dopri8": diffrax.Dopri8,
    "DOP853": DOP853,
    "Kvaerno5": diffrax.Kvaerno5,
}
SOLVER_LABELS = {
    "Tsit5": "diffrax Tsit5", "Tsit5u": "Tsit5 unrolled (proposed)", "Dopri5": "diffrax Dopri5",
    "Dopri8": "diffrax Dopri8", "DOP853": "jaxnh DOP853", "Kvaerno5": "diffrax Kvaerno5",
}


def tol_pair(rtol: float) -> tuple[float, float]:
    """(rtol, atol) of a sweep point: atol = rtol / 100, as simulate's defaults (1e-8, 1e-10)."""
    return rtol, rtol / 100


# --------------------------------------------------------------------------- compiled solves


def jaxnh_solver_fn(mech, method, q0, qd0, params, ts, solver, *, independent=None, record=(), max_steps=100_000,
                    adjoint=None):
    """A jitted `f(params, y0, rtol, atol) -> (q, qd, num_steps)` around `simulate`'s compiled part.

    The tolerances are traced, so one compilation serves the whole sweep; `y0` is
    the formulation's state at ts[0]. Returns (f, y0).
    """
    form = formulation(mech, method, q0, qd0, ts[0], params, independent)
    y0 = form.state(q0, qd0, ts[0], params)
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint

    def f(p, y0, rtol, atol):
        controller = diffrax.PIDController(rtol=rtol, atol=atol)
        (q, qd), result, stats, out = _integrate(form, p, y0, ts, solver, controller, tuple(record), max_steps, None,
                                                 adjoint, False)
        return q, qd, stats["num_steps"], out

    return jax.jit(f), y0


def hand_solver_fn(vector_field, unpack, ts, solver, max_steps=100_000):
    """A jitted `f(params, y0, rtol, atol) -> (q, qd, num_steps, {})` for a hand-written vector field."""

    def f(p, y0, rtol, atol):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field), solver, ts[0], ts[-1], None, y0, args=p,
            saveat=diffrax.SaveAt(ts=ts), stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            max_steps=max_steps, throw=False,
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
    return float(max(np.max(np.abs(np.asarray(q) - np.asarray(q_ref))),
                     np.max(np.abs(np.asarray(qd) - np.asarray(qd_ref)))))


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
        cpu=cpu, cores=os.cpu_count(), platform=platform.platform(), python=platform.python_version(),
        jax=jax.__version__, jaxlib=jaxlib.__version__, diffrax=dfx.__version__, equinox=equinox.__version__,
        numpy=np.__version__, scipy=scipy.__version__, jaxnh=nh.__version__,
        devices=[str(d) for d in jax.devices()], load_average=list(os.getloadavg()),
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        proposals_applied=proposals.applied(),
    )


def save(name: str, data: dict) -> pathlib.Path:
    RESULTS.mkdir(exist_ok=True)
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
