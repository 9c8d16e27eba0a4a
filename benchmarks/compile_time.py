"""First-call time of a variator simulation, each in a fresh Python process.

A user's first `nh.simulate(...)` pays for tracing, XLA compilation, and the
compilation of every operation the argument checks dispatch one by one. Each
scenario runs in a new interpreter (no JAX caches), calls the same thing
twice and reports: import time, first call, second call, and their difference
(the compile cost), as process CPU time and wall time.

    python -m benchmarks.compile_time [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import json
import os
import subprocess
import sys
import time


SCENARIOS = {
    "simulate (default solver: jaxnh Tsit5 at rtol 1e-8)": "simulate",
    "simulate, solver=jaxnh DOP853": "simulate_dop853",
    "simulate, solver=diffrax Tsit5": "simulate_diffrax_tsit5",
    "simulate, method=lagrange": "simulate_lagrange",
    "jit(vmap(simulate)), 1000 members": "batch",
    "reference: diffrax solve of eq. (9) by hand, jitted (diffrax Tsit5)": "hand",
    "jax.grad of a trajectory loss (default adjoint: ForwardSensitivity)": "grad",
    "jax.grad of a trajectory loss (RecursiveCheckpointAdjoint)": "grad_reverse",
}
QUICK = ["simulate", "grad"]


def child(kind: str) -> dict:
    t0 = time.perf_counter()
    import jax
    import jax.numpy as jnp

    import jaxnh as nh
    from jaxnh.models import variator as V

    import_s = time.perf_counter() - t0
    mech, p = V.mechanism(), V.default_params()
    ts = jnp.linspace(0.0, 10.0, 101)
    q0 = jnp.zeros(2)
    qd0 = jnp.array([1.0, float(p.U21(0.0))])
    kw = {}
    if kind == "simulate_dop853":
        kw["solver"] = nh.solvers.DOP853()
    elif kind == "simulate_diffrax_tsit5":
        import diffrax

        kw["solver"] = diffrax.Tsit5()
    elif kind == "simulate_lagrange":
        kw["method"] = "lagrange"

    if kind.startswith("simulate"):

        def call():
            return jax.block_until_ready(nh.simulate(mech, p, q0, qd0, ts, **kw).q)
    elif kind == "hand":
        import diffrax

        from .problems import eq9_jax

        @jax.jit
        def f(p_, y0):
            return diffrax.diffeqsolve(
                diffrax.ODETerm(eq9_jax),
                diffrax.Tsit5(),
                ts[0],
                ts[-1],
                None,
                y0,
                args=p_,
                saveat=diffrax.SaveAt(ts=ts),
                max_steps=100_000,
                stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10),
            ).ys

        def call():
            return jax.block_until_ready(f(p, (q0, qd0[:1])))
    elif kind == "batch":
        w = jnp.linspace(0.5, 1.5, 1000)
        f = jax.jit(
            jax.vmap(
                lambda w_: (
                    nh.simulate(mech, p, q0, jnp.stack([w_, w_ * p.U21(0.0)]), ts, independent=(0,), throw=False).q
                )
            )
        )

        def call():
            return jax.block_until_ready(f(w))
    else:
        import diffrax

        adjoint = diffrax.RecursiveCheckpointAdjoint() if kind == "grad_reverse" else None

        def loss(J):
            pp = V.VariatorParams(J[0], J[1], p.U21, p.M1, p.M2)
            return jnp.sum(nh.simulate(mech, pp, q0, qd0, ts, independent=(0,), adjoint=adjoint).q ** 2)

        g = jax.grad(loss)
        J = jnp.array([0.02, 0.05])

        def call():
            return jax.block_until_ready(g(J))

    _, cpu1, wall1 = C.timed(call)
    _, cpu2, wall2 = C.timed(call)
    return dict(
        kind=kind,
        import_s=import_s,
        first={"cpu": cpu1, "wall": wall1},
        second={"cpu": cpu2, "wall": wall2},
        compile={"cpu": cpu1 - cpu2, "wall": wall1 - wall2},
        load_average=list(os.getloadavg()),
    )


def run(quick: bool) -> dict:
    rows = []
    for label, kind in SCENARIOS.items():
        if quick and kind not in QUICK:
            continue
        out = subprocess.run(
            [sys.executable, "-m", "benchmarks.compile_time", "--child", kind],
            capture_output=True,
            text=True,
            cwd=str(C.HERE.parent),
        )
        if out.returncode != 0:
            rows.append(dict(label=label, kind=kind, error=out.stderr[-2000:]))
            C.log(f"  {label}: FAILED\n{out.stderr[-2000:]}")
            continue
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["label"] = label
        rows.append(row)
        C.log(
            f"  {label:<62s} first call {row['first']['wall']:6.2f} s wall / {row['first']['cpu']:6.2f} s cpu;"
            f" compile {row['compile']['wall']:6.2f} s wall / {row['compile']['cpu']:6.2f} s cpu"
        )
    return dict(rows=rows, quick=quick)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="two scenarios only")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child)))
        return
    t0 = time.perf_counter()
    out = run(a.quick)
    out["seconds"] = time.perf_counter() - t0
    C.log(f"[compile_time] wrote {C.save('compile_time', out)} in {out['seconds']:.0f} s")


if __name__ == "__main__":
    main()
