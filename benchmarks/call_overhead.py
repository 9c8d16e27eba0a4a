"""What a repeat `simulate` call costs in Python on top of its compiled solve.

The README's variator (default method, no hints), a short run (1 s, 11 report
times) so that the per-call cost is visible next to the solve. Three ways of
calling the same solve, interleaved in one process, medians of many calls:

* "compiled": `jax.jit(lambda p, q0, qd0: nh.simulate(...).q)` — the solve alone;
* "simulate": a plain repeat `nh.simulate(...)` call (argument resolution in
  Python, the cached compiled program, the status check after the call);
* "simulate, throw=False": the same without the status check.

The difference "simulate − compiled" is the Python overhead per call.

    python -m benchmarks.call_overhead [--calls N]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh


def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def rolling(q, qd, t, p):
    return jnp.stack([(1.0 + 0.4 * jnp.sin(jnp.pi * t)) * qd[0] - qd[1]])


def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=300)
    args = ap.parse_args(argv)
    mech = nh.Mechanism(T, constraints=rolling, forces=torques)
    p = {"J1": jnp.asarray(0.02), "J2": jnp.asarray(0.05), "M1": jnp.asarray(0.3), "M2": jnp.asarray(-0.1)}
    q0, qd0, ts = jnp.zeros(2), jnp.array([2.0, 2.0]), jnp.linspace(0.0, 1.0, 11)

    compiled = jax.jit(lambda p_, a, b: nh.simulate(mech, p_, a, b, ts).q)
    ways = {
        "compiled": lambda: compiled(p, q0, qd0).block_until_ready(),
        "simulate": lambda: nh.simulate(mech, p, q0, qd0, ts).q.block_until_ready(),
        "simulate, throw=False": lambda: nh.simulate(mech, p, q0, qd0, ts, throw=False).q.block_until_ready(),
    }
    ref = np.asarray(compiled(p, q0, qd0))
    for name, f in ways.items():  # compile and warm up
        for _ in range(5):
            f()
    err = float(np.max(np.abs(np.asarray(nh.simulate(mech, p, q0, qd0, ts).q) - ref)))
    times = {k: [] for k in ways}
    for _ in range(args.calls):  # interleaved rounds
        for name, f in ways.items():
            t0 = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t0)
    med = {k: float(np.median(v)) * 1e3 for k, v in times.items()}
    out = {
        "median_ms": med,
        "overhead_ms": med["simulate"] - med["compiled"],
        "overhead_no_throw_ms": med["simulate, throw=False"] - med["compiled"],
        "max_abs_difference_simulate_vs_compiled": err,
        "calls": args.calls,
    }
    for k, v in med.items():
        print(f"{k:>24}: {v:.3f} ms per call (median of {args.calls})")
    print(
        f"Python overhead of a repeat simulate call: {out['overhead_ms']:.3f} ms "
        f"({out['overhead_no_throw_ms']:.3f} ms with throw=False); results equal to {err:.1e}"
    )
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=1))
