"""Cost of the gradient of a trajectory loss relative to one forward solve.

The variator over 10 s (101 report times, rtol 1e-8); the loss is the sum of
squared differences between the simulated angles and a data set. Its
parameters are J1, J2, M1, M2 and a Fourier ratio law U21(t) with K harmonics
(P = 5 + 2K scalars: K = 1, 7, 31 give P = 7, 19, 67; P = 2 differentiates J1, J2 only). Modes:

* reverse: `jax.grad` with diffrax's `RecursiveCheckpointAdjoint` (jaxnh's
  default today) and `BacksolveAdjoint` (smallest P only: it compiles slowly);
* forward: `jax.jacfwd` with `diffrax.ForwardMode()`;
* forward sensitivities (`jaxnh.ForwardSensitivity`): `jax.grad` through an
  augmented solve of the state and its P sensitivity columns;
* auto: what `simulate(adjoint=None)` picks (`jaxnh._sensitivity.auto_adjoint`):
  `ForwardSensitivity` up to `FORWARD_MAX_PARAMETERS` scalars in
  (params, q0, qd0), reverse mode above. Its ratio is that of the mode it
  picks (the same compiled function).

Each gradient is compiled once (compile time reported) and timed interleaved
with the forward solve; the ratio is the median of per-round ratios.

    python -m benchmarks.gradients [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

import jaxnh as nh
from jaxnh._sensitivity import auto_adjoint, FORWARD_MAX_PARAMETERS, ForwardSensitivity
from jaxnh._simulate import default_solver
from jaxnh.models import variator as V


RTOL, ATOL = 1e-8, 1e-10


def _params(K: int) -> V.VariatorParams:
    sin = [0.4] + [0.0] * (K - 1)
    return V.VariatorParams(
        J1=0.02, J2=0.05, U21=nh.profiles.Fourier(1.0, cos=[0.0] * K, sin=sin, period=2.0), M1=0.3, M2=-0.1
    )


def _setup(K: int, only_inertias: bool):
    p = _params(K)
    ts = jnp.linspace(0.0, 10.0, 101)
    q_data = V.closed_form(p, ts, w0=1.0)[0] + 0.01 * jnp.sin(ts)[:, None]
    mask = nh.profiles.trainable(p)
    if only_inertias:
        mask = jax.tree_util.tree_map(lambda _: False, mask)
        mask = eqx.tree_at(lambda m: (m.J1, m.J2), mask, (True, True))
    theta, static = eqx.partition(p, mask)
    return theta, static, ts, q_data


def _loss(static, ts, q_data, solver, adjoint):
    def loss(theta):
        p = eqx.combine(theta, static)
        qd0 = jnp.stack([1.0, p.U21(0.0)])
        sol = nh.simulate(
            V.mechanism(),
            p,
            jnp.zeros(2),
            qd0,
            ts,
            solver=solver,
            rtol=RTOL,
            atol=ATOL,
            adjoint=adjoint,
            independent=(0,),
        )
        return jnp.sum((sol.q - q_data) ** 2)

    return loss


def run(quick: bool, solver_name: str) -> dict:
    cases = [(1, False)] if quick else [(1, True), (1, False), (7, False), (31, False)]
    solver = C.SOLVERS[solver_name]()
    rows = []
    for K, only_J in cases:
        theta, static, ts, q_data = _setup(K, only_J)
        P = sum(x.size for x in jax.tree_util.tree_leaves(theta))
        p_full = eqx.combine(theta, static)
        auto = auto_adjoint(p_full, jnp.zeros(2), jnp.zeros(2))  # what simulate(adjoint=None) would pick
        modes = {
            "forward solve": jax.jit(_loss(static, ts, q_data, solver, None)),
            "reverse RecursiveCheckpoint": jax.jit(
                jax.grad(_loss(static, ts, q_data, solver, diffrax.RecursiveCheckpointAdjoint()))
            ),
            "ForwardSensitivity": jax.jit(jax.grad(_loss(static, ts, q_data, solver, ForwardSensitivity()))),
        }
        if not quick:
            modes["jacfwd ForwardMode"] = jax.jit(jax.jacfwd(_loss(static, ts, q_data, solver, diffrax.ForwardMode())))
        if not quick and (K, only_J) == (1, True):
            modes["reverse BacksolveAdjoint"] = jax.jit(
                jax.grad(_loss(static, ts, q_data, solver, diffrax.BacksolveAdjoint()))
            )
        compiled, compile_s, values = {}, {}, {}
        for name, f in modes.items():
            compiled[name], compile_s[name] = C.compile_aot(f, theta)
            values[name] = jax.block_until_ready(compiled[name](theta))
        # all gradients must agree (they differentiate the same discrete solution)
        ref = values["reverse RecursiveCheckpoint"]
        agree = {}
        for name, g in values.items():
            if name != "forward solve":
                d = jax.tree_util.tree_map(
                    lambda a, b: float(jnp.max(jnp.abs(a - b)) / (jnp.max(jnp.abs(b)) + 1e-300)), g, ref
                )
                agree[name] = max(jax.tree_util.tree_leaves(d))
        times = C.interleave(
            {k: (lambda c=c: jax.block_until_ready(c(theta))) for k, c in compiled.items()}, rounds=5 if quick else 7
        )
        cpu = {k: t["cpu"] for k, t in times.items()}
        auto_name = "ForwardSensitivity" if isinstance(auto, ForwardSensitivity) else "reverse RecursiveCheckpoint"
        row = dict(
            K=K,
            P=P,
            only_inertias=only_J,
            solver=solver_name,
            compile=compile_s,
            time={k: C.median(v) for k, v in cpu.items()},
            ratio={k: C.paired_ratio(v, cpu["forward solve"]) for k, v in cpu.items()},
            relative_difference_to_reverse=agree,
            auto=auto_name,
        )
        row["ratio"]["auto (simulate default)"] = row["ratio"][auto_name]
        rows.append(row)
        C.log(
            f"  P={P:3d}: "
            + "  ".join(f"{k} {r:.2f}x" for k, r in row["ratio"].items() if k != "forward solve")
            + f"  (forward {row['time']['forward solve'] * 1e3:.2f} ms)"
        )
    return dict(
        rows=rows, rtol=RTOL, atol=ATOL, solver=solver_name, quick=quick, forward_max_parameters=FORWARD_MAX_PARAMETERS
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="P = 7 only; no jacfwd/backsolve")
    ap.add_argument(
        "--solver",
        default="default",
        choices=["default"] + sorted(C.SOLVERS),
        help="default: what simulate picks at rtol 1e-8 (jaxnh._simulate.default_solver)",
    )
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = run(a.quick, C.solver_key(default_solver(RTOL)) if a.solver == "default" else a.solver)
    out["seconds"] = time.perf_counter() - t0
    C.log(f"[gradients] wrote {C.save('gradients', out)} in {out['seconds']:.0f} s")


if __name__ == "__main__":
    main()
