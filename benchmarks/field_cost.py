"""Where the time of a step goes: the vector field against the integration loop.

Target 1 of issue 4 compares jaxnh's automatically derived equations with
the hand-written ones inside a whole solve. This script splits that time:

* **field**: one evaluation of the vector field, compiled alone and repeated
  in a `lax.fori_loop` whose iterations each perturb t and the state, so XLA
  cannot hoist any of it out of the loop;
* **kernels**: how many XLA CPU kernels (fusions, library calls and other
  unfused instructions) one field evaluation compiles to, alone and inside
  the step loop of a solve (the largest loop body of the compiled program).
  Each kernel has a fixed launch cost on the CPU runtime, which for
  scalar-sized data exceeds its arithmetic;
* **step**: the time of one step of a whole compiled solve (jaxnh Tsit5
  unrolled and diffrax Tsit5, rtol 1e-8, a long horizon so per-call costs
  vanish), and the same for a trivial field (an oscillator with the same
  state layout): what the integration loop costs with (almost) nothing to
  evaluate.

What was tried with it (2026-11-23, not adopted): building the variator's
velocities by fused selects instead of `jnp.stack`, and 1×1 solves by one
shared reciprocal, cut the Appell step from 69 to 51 kernels. A single
unrolled-Tsit5 solve then ran about 10 % faster (appell/hand 1.22× against
1.38× per step). But the same change made `vmap` batches of 1000 17–20 %
slower: appell/hand 2.24–2.31× against 1.91×, measured in fresh processes
with the hand-written batch as the in-process control. XLA gets its fewer
kernels by duplicating arithmetic into several fusions, which costs real
work once a batch amortises the launches. For larger mechanisms the effect
came out either way (generic s = 10 single solve: 42 % slower). Sweeps and
calibration run batched, so the change was reverted. Fewer kernels without
duplicated work would need control of XLA's fusion, or a hand-written step.

    python -m benchmarks.field_cost [--quick]
"""

from __future__ import annotations

from . import common as C  # first: it sets XLA's flags before JAX starts


# isort: split

import argparse
import re
import time

import jax
import jax.numpy as jnp

from jaxnh._simulate import formulation

from . import problems as PB


# Instructions of an optimised HLO entry computation that do no work at run time.
_FREE = {"parameter", "tuple", "get-tuple-element", "bitcast", "constant"}


def kernels(compiled) -> dict:
    """Opcode -> count of the run-time instructions in the compiled entry computation."""
    text = compiled.as_text()
    entry = text[text.index("ENTRY") :]
    entry = entry[: entry.index("\n}")]
    counts = {}
    for op in re.findall(r"=\s*\S+\s+([a-z][a-z0-9-]*)\(", entry):
        if op not in _FREE:
            counts[op] = counts.get(op, 0) + 1
    return counts


def loop_kernels(compiled) -> int:
    """Run-time instructions (kernels) outside fusions in the largest non-entry computation
    of a compiled solve: the body of the step loop, i.e. the kernels one step launches."""
    best = 0
    for comp in re.split(r"\n(?=\S)", compiled.as_text()):
        name = comp.split(" ", 1)[0]
        if name.startswith("ENTRY") or "fused" in name or "fusion" in name:
            continue
        ops = [op for op in re.findall(r"=\s*\S+\s+([a-z][a-z0-9-]*)\(", comp) if op not in _FREE]
        best = max(best, len(ops))
    return best


def _perturbed(y, acc):
    return jax.tree_util.tree_map(lambda u, a: u + 1e-30 * a, y, acc)


def field_loop(field, t, y, p, n: int):
    """A compiled zero-argument call that evaluates `field` n times, each at a new (t, y)."""

    def body(i, acc):
        dy = field(t + i * 1e-9, _perturbed(y, acc), p)
        return jax.tree_util.tree_map(lambda a, d: a + 1e-30 * d, acc, dy)

    zero = jax.tree_util.tree_map(jnp.zeros_like, y)
    f = jax.jit(lambda t, y, p: jax.lax.fori_loop(0, n, body, zero))
    compiled = f.lower(t, y, p).compile()
    return lambda: jax.block_until_ready(compiled(t, y, p))


def _oscillator(t, y, p):
    """A field with next to no arithmetic, in the Appell state layout (q, v), len(v) ≤ len(q):
    q' = v[0] (every entry), v' = −q[:len(v)] — an oscillation of period 2π s, so the step
    count over a long horizon is of the same order as for the mechanisms."""
    q, v = y
    return jnp.full_like(q, v[0]), -q[: v.shape[0]]


def measure(problem: str, rounds: int, quick: bool) -> dict:
    if problem == "variator":
        v = PB.variator(T=400.0, n=401)
        mech, p, ts, q0, qd0, ind = v.mech, v.params, v.ts, v.q0, v.qd0, (0,)
        hand_vf, hand_unpack, hand_y0, n_eval = PB.eq9_jax, PB.eq9_unpack, PB.eq9_state(v), 20_000
    else:
        g = PB.generic(T=100.0, n=401)
        mech, p, ts, q0, qd0, ind = g.mech, g.params, g.ts, g.q0, g.qd0, g.independent
        hand_vf, hand_unpack, hand_y0, n_eval = PB.generic_rhs_jax, (lambda ys, ts, p: ys), (g.q0, g.qd0), 2_000
    t = C.f64(0.3)
    fields, states = {}, {}
    for method in ("appell", "lagrange"):
        form = formulation(mech, method, q0, qd0, ts[0], p, ind if method == "appell" else None)
        states[method] = form.state(q0, qd0, ts[0], p)
        fields[method] = (lambda form: lambda t, y, p: form.vector_field(t, y, p))(form)
    fields["hand"], states["hand"] = hand_vf, hand_y0

    row = dict(
        problem=problem,
        evaluations_per_loop=n_eval,
        kernels={},
        field={},
        step={},
        steps={},
        compile={},
        step_kernels={},
    )
    calls = {}
    for k in fields:
        compiled = jax.jit(fields[k]).lower(t, states[k], p).compile()
        row["kernels"][k] = kernels(compiled)
        calls[k] = field_loop(fields[k], t, states[k], p, n_eval)
    times = C.interleave(calls, rounds=rounds)
    row["field"] = {k: C.median(v["cpu"]) / n_eval for k, v in times.items()}

    solvers = ["Tsit5u"] if quick else ["Tsit5u", "Tsit5"]
    R, A = C.f64(1e-8), C.f64(1e-10)
    for sname in solvers:
        calls = {}
        for k in fields:
            if k == "hand":
                fn, y0 = C.hand_solver_fn(hand_vf, hand_unpack, ts, C.SOLVERS[sname]()), hand_y0
            else:
                fn, y0 = C.jaxnh_solver_fn(
                    mech, k, q0, qd0, p, ts, C.SOLVERS[sname](), independent=ind if k == "appell" else None
                )
            compiled, row["compile"][f"{k}/{sname}"] = C.compile_aot(fn, p, y0, R, A)
            row["steps"][f"{k}/{sname}"] = int(compiled(p, y0, R, A)[2])
            if sname == "Tsit5u":  # one loop body per step (diffrax's Tsit5 nests a loop over stages)
                row["step_kernels"][k] = loop_kernels(compiled)
            calls[f"{k}/{sname}"] = lambda c=compiled, y0=y0: jax.block_until_ready(c(p, y0, R, A))
        # the loop alone: a trivial field in the appell state layout, same report times and tolerances
        fn = C.hand_solver_fn(_oscillator, lambda ys, ts, p: ys, ts, C.SOLVERS[sname]())
        compiled, row["compile"][f"trivial/{sname}"] = C.compile_aot(fn, p, states["appell"], R, A)
        row["steps"][f"trivial/{sname}"] = int(compiled(p, states["appell"], R, A)[2])
        if sname == "Tsit5u":
            row["step_kernels"]["trivial"] = loop_kernels(compiled)
        calls[f"trivial/{sname}"] = lambda c=compiled: jax.block_until_ready(c(p, states["appell"], R, A))
        times = C.interleave(calls, rounds=rounds)
        for k, v in times.items():
            row["step"][k] = C.median(v["cpu"]) / row["steps"][k]
    for k in fields:
        C.log(
            f"  {problem}/{k}: field {row['field'][k] * 1e9:.0f} ns, {sum(row['kernels'][k].values())} kernels; "
            + f"{row['step_kernels'][k]} kernels per Tsit5u step; "
            + "  ".join(f"{s} step {row['step'][f'{k}/{s}'] * 1e6:.2f} us" for s in solvers)
        )
    C.log(
        f"  trivial field: {row['step_kernels']['trivial']} kernels per Tsit5u step; "
        + "  ".join(f"{s} step {row['step'][f'trivial/{s}'] * 1e6:.2f} us" for s in solvers)
    )
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="variator only, jaxnh Tsit5 only, fewer rounds")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rounds = 5 if a.quick else 9
    rows = [measure("variator", rounds, a.quick)]
    if not a.quick:
        rows.append(measure("generic", rounds, a.quick))
    out = dict(quick=a.quick, rows=rows, stages_per_step=6, seconds=time.perf_counter() - t0)
    C.log(f"[field_cost] wrote {C.save('field_cost', out)} in {out['seconds']:.0f} s")


if __name__ == "__main__":
    main()
