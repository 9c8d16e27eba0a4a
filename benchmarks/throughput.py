"""Batch throughput: time per trajectory against batch size under `jax.vmap`.

The variator over 10 s (101 report times) at rtol 1e-10, atol 1e-12 (max error
≈ 1e-8 against the closed form, the matched error of target 3); the members
differ in J1 and the initial speed. `jit(vmap(...))` over `simulate`'s
compiled inner function (one compilation per batch size, reported); the
whole batch steps until its slowest member is done. Contenders: jaxnh
"appell" in DOP853 and in diffrax Tsit5, and eq. (9) by hand in DOP853.

    python -m benchmarks.throughput [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.models import variator as V

from . import problems as PB


RTOL, ATOL = 1e-10, 1e-12


def _batched(kind: str, solver_name: str, ts):
    mech = V.mechanism()
    p0 = V.default_params()
    solver = C.SOLVERS[solver_name]()
    form = nh.Appell(independent=(0,))

    def one(J1, w0, rtol, atol):
        p = V.VariatorParams(J1, p0.J2, p0.U21, p0.M1, p0.M2)
        if kind == "hand":
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(PB.eq9_jax),
                solver,
                ts[0],
                ts[-1],
                None,
                (jnp.zeros(2), jnp.stack([w0])),
                args=p,
                saveat=diffrax.SaveAt(ts=ts),
                stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
                max_steps=100_000,
                throw=False,
            )
            return sol.ys[0], sol.stats["num_steps"]
        sol = nh.simulate(
            mech,
            p,
            jnp.zeros(2),
            jnp.stack([w0, w0 * p.U21(0.0)]),
            ts,
            form,
            solver=solver,
            max_steps=100_000,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
            throw=False,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        )
        return sol.q, sol.stats["num_steps"]

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None, None)))


def run(quick: bool) -> dict:
    ts = jnp.linspace(0.0, 10.0, 101)
    sizes = [1, 1000] if quick else [1, 100, 1000, 10000]
    contenders = (
        [("appell", "DOP853")]
        if quick
        else [("appell", "DOP853"), ("appell", "Tsit5"), ("appell", "Tsit5u"), ("hand", "DOP853")]
    )
    R, A = C.f64(RTOL), C.f64(ATOL)
    rows = []
    for kind, sname in contenders:
        f = _batched(kind, sname, ts)
        for n in sizes:
            rng = np.random.RandomState(n)
            J1 = jnp.asarray(0.02 * (1 + 0.2 * rng.rand(n)))
            w0 = jnp.asarray(0.5 + rng.rand(n))
            compiled, compile_s = C.compile_aot(f, J1, w0, R, A)
            q, steps = jax.block_until_ready(compiled(J1, w0, R, A))
            # accuracy of one member against its closed form
            p = V.VariatorParams(J1[0], 0.05, V.default_params().U21, 0.3, -0.1)
            q_ref, _ = V.closed_form(p, ts, w0=float(w0[0]))
            err = float(np.max(np.abs(np.asarray(q[0]) - np.asarray(q_ref))))
            rounds = 3 if n >= 10000 else 5
            t = C.interleave({"batch": lambda: jax.block_until_ready(compiled(J1, w0, R, A))}, rounds=rounds)["batch"]
            row = dict(
                kind=kind,
                solver=sname,
                batch=n,
                compile=compile_s,
                time=C.median(t["cpu"]),
                time_wall=C.median(t["wall"]),
                per_trajectory=C.median(t["cpu"]) / n,
                per_trajectory_wall=C.median(t["wall"]) / n,
                max_steps_in_batch=int(np.max(steps)),
                mean_steps=float(np.mean(steps)),
                error_member0=err,
            )
            rows.append(row)
            C.log(
                f"  {kind}/{sname} batch {n:6d}: {row['per_trajectory'] * 1e6:9.1f} us/trajectory cpu "
                f"({row['per_trajectory_wall'] * 1e6:9.1f} wall), compile {compile_s['cpu']:.1f} s cpu"
            )
    return dict(rows=rows, rtol=RTOL, atol=ATOL, quick=quick)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="batch sizes 1 and 1000; appell/DOP853 only")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = run(a.quick)
    out["seconds"] = time.perf_counter() - t0
    C.log(f"[throughput] wrote {C.save('throughput', out)} in {out['seconds']:.0f} s")


if __name__ == "__main__":
    main()
