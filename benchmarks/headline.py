"""Where jaxnh stands on the README's variator, with the user's default settings (rtol 1e-8, atol 1e-10).

Contenders, timed in interleaved rounds after their first (compiling) call,
each with its error against the closed form:

* `nh.simulate(...)`, a plain call with every default (the default
  formulation, Lagrange's, default solver), and the same under `jax.jit`
  (with the report times closed over, and with every input an argument and
  the eager call's XLA options: the plain call's median excess over the
  latter is its per-call overhead);
* eq. (9) written by hand, `diffrax.diffeqsolve` with `diffrax.Tsit5`, jitted,
  its report times closed over as constants (as a script writes it), and the
  same program taking the report times as an argument (as `simulate`, which
  takes them as data, must: XLA then cannot fold them into the step loop);
* jaxnh's Appell field from `nh.ode` in the user's `diffrax.Tsit5` (with the
  formulation's step maps and error norm), jitted: its cost per step against
  the hand field's;
* SciPy `solve_ivp` (RK45, its default) on SymPy's `LagrangesMethod`
  derivation, lambdified with NumPy;
* the limit: eq. (9) in an adaptive Tsit5 loop compiled by numba;
* a gradient of the final state's sum through `simulate` (`jax.grad`, jitted)
  against the forward solve, and a `jax.vmap` batch per trajectory.

    python -m benchmarks.headline [--quick]
"""

from __future__ import annotations

import argparse
import time

from . import common as C


C.pin()  # before JAX starts

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh._base.compile import SOLVE  # noqa: E402

from .mechanisms import variator as VV  # noqa: E402


PLAIN = "jaxnh simulate (defaults)"
JIT = "jaxnh jit(simulate)"
JIT_ARGS = "jaxnh jit(simulate), every input an argument"
HAND = "eq. (9) by hand, diffrax Tsit5"
HAND_TS = "eq. (9) by hand, diffrax Tsit5, ts as an argument"
FIELD = "jaxnh Appell field (nh.ode), diffrax Tsit5"
SCIPY = "SciPy RK45, lambdified SymPy"
NUMBA = "numba Tsit5 loop (limit)"
GRAD = "gradient: jit(grad(simulate)), 4 parameters"
BATCH = "batch: jit(vmap(simulate)), per call"


def contenders(batch: int):
    """name -> (call, result -> (q, qd, steps)); every call blocks until its result is ready."""
    mech, P, ts = VV.mechanism(), VV.PARAMS, VV.TS
    pid = diffrax.PIDController(rtol=C.RTOL, atol=C.ATOL)
    out = {}

    def plain():
        return jax.block_until_ready(nh.simulate(mech, P, VV.Q0, VV.QD0, ts))

    out[PLAIN] = (plain, lambda s: (s.q, s.qd, s.stats["num_steps"]))
    jsim = jax.jit(lambda p: nh.simulate(mech, p, VV.Q0, VV.QD0, ts))
    out[JIT] = (lambda: jax.block_until_ready(jsim(P)), lambda s: (s.q, s.qd, s.stats["num_steps"]))
    # the same inputs as the plain call, all of them arguments, and the XLA options simulate compiles
    # its eager program with: the same program, so plain − this is the eager call's own cost
    jargs = jax.jit(lambda p, q0, qd0, ts_: nh.simulate(mech, p, q0, qd0, ts_), compiler_options=SOLVE)
    out[JIT_ARGS] = (
        lambda: jax.block_until_ready(jargs(P, VV.Q0, VV.QD0, ts)),
        lambda s: (s.q, s.qd, s.stats["num_steps"]),
    )

    def eq9_solve(args, ts_):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(VV.eq9),
            diffrax.Tsit5(),
            ts_[0],
            ts_[-1],
            None,
            jnp.asarray(VV.EQ9_Y0),
            args=args,
            saveat=diffrax.SaveAt(ts=ts_),
            stepsize_controller=pid,
            max_steps=100_000,
        )
        return sol.ys, sol.stats["num_steps"]

    hand = jax.jit(lambda a: eq9_solve(a, ts))  # the report times closed over: constants of the program
    hand_ts = jax.jit(eq9_solve)  # the report times an argument: data
    args = tuple(jnp.asarray(a) for a in VV.EQ9_ARGS)
    for name, call in ((HAND, lambda: hand(args)), (HAND_TS, lambda: hand_ts(args, ts))):
        out[name] = (lambda call=call: jax.block_until_ready(call()), lambda r: (*VV.eq9_unpack(r[0], ts), r[1]))

    @jax.jit
    def field(p):
        o = nh.ode(mech, p, VV.Q0, VV.QD0, ts[0], method="appell")
        sol = diffrax.diffeqsolve(
            o.term,
            o.solver(diffrax.Tsit5()),
            ts[0],
            ts[-1],
            None,
            o.y0,
            args=o.args,
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=100_000,
            stepsize_controller=diffrax.PIDController(rtol=C.RTOL, atol=C.ATOL, norm=o.error_norm),
        )
        q, qd = jax.vmap(o.unpack)(sol.ys, ts)
        return q, qd, sol.stats["num_steps"]

    out[FIELD] = (lambda: jax.block_until_ready(field(P)), lambda r: r)

    ns = VV.sympy_namespace()
    rhs, p_np, ts_np = ns["numpy_rhs"](), np.asarray(VV.EQ9_ARGS), np.asarray(ts)
    y0 = np.r_[np.asarray(VV.Q0), np.asarray(VV.QD0)]
    out[SCIPY] = (
        lambda: ns["solve"](rhs, y0, p_np, ts_np, C.RTOL, C.ATOL),
        lambda s: (s.y[:2].T, s.y[2:].T, s.nfev / 6),
    )
    solve = VV.numba_tsit5()
    if solve is not None:
        out[NUMBA] = (
            lambda: solve(VV.EQ9_Y0, ts_np, C.RTOL, C.ATOL),
            lambda r: (*VV.eq9_unpack(r[0], ts_np), r[1]),
        )

    def loss(p):
        return jnp.sum(nh.simulate(mech, p, VV.Q0, VV.QD0, ts).q[-1])

    g = jax.jit(jax.grad(loss))
    out[GRAD] = (lambda: jax.block_until_ready(g(P)), None)
    J1s = P["J1"] * jnp.linspace(0.8, 1.2, batch)
    vm = jax.jit(jax.vmap(lambda j: nh.simulate(mech, {**P, "J1": j}, VV.Q0, VV.QD0, ts).q[-1]))
    out[BATCH] = (lambda: jax.block_until_ready(vm(J1s)), None)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer rounds, a batch of 100")
    a = ap.parse_args(argv)
    batch = 100 if a.quick else 1000
    q_ref, qd_ref = VV.reference()
    calls, rows = {}, {}
    for name, (fn, unpack) in contenders(batch).items():
        c0 = time.process_time()
        res = fn()  # the first call compiles
        cpu = time.process_time() - c0
        many, n = C.repeat(fn, 0.02 if a.quick else 0.1)
        calls[name] = many
        rows[name] = dict(first_call_cpu=cpu, per_round=n)
        if unpack is not None:
            q, qd, steps = unpack(res)
            rows[name].update(error=C.max_error(q, qd, q_ref, qd_ref), steps=float(steps))
        C.log(f"[headline] {name}: compiled; {rows[name]}")
    T = C.interleave(calls, rounds=5 if a.quick else 9, budget=20 if a.quick else 180)
    for name, r in rows.items():
        n = r["per_round"]
        r["cpu"] = C.median(np.asarray(T[name]["cpu"]) / n)
        r["wall"] = C.median(np.asarray(T[name]["wall"]) / n)
        r["rounds"] = len(T[name]["cpu"])
        if "steps" in r:
            r["per_step"] = r["cpu"] / r["steps"]
        C.log(f"[headline] {name}: {r['cpu'] * 1e3:.3f} ms CPU, error {r.get('error', float('nan')):.1e}")

    def ratio(a_, b_, per_step=False):
        x = np.asarray(T[a_]["cpu"]) / rows[a_]["per_round"] / (rows[a_]["steps"] if per_step else 1)
        y = np.asarray(T[b_]["cpu"]) / rows[b_]["per_round"] / (rows[b_]["steps"] if per_step else 1)
        return C.paired_ratio(x, y)

    ratios = {
        "simulate / hand": ratio(PLAIN, HAND),
        "jit(simulate) / hand": ratio(JIT, HAND),
        "jit(simulate) / hand with ts as an argument": ratio(JIT, HAND_TS),
        "field per step / hand per step": ratio(FIELD, HAND, per_step=True),
        "SciPy / simulate": ratio(SCIPY, PLAIN),
        "gradient / jit(simulate)": ratio(GRAD, JIT),
        "batch per trajectory / jit(simulate)": ratio(BATCH, JIT) / batch,
    }
    if NUMBA in rows:
        ratios["simulate / numba"] = ratio(PLAIN, NUMBA)
    # the eager call's overhead: per-round differences, plain call − jit with the same arguments (s)
    per_call = {k: np.asarray(T[k]["cpu"]) / rows[k]["per_round"] for k in (PLAIN, JIT_ARGS)}
    overhead = C.median(per_call[PLAIN] - per_call[JIT_ARGS])
    C.log(f"[headline] ratios: {ratios}; eager overhead {overhead * 1e6:.0f} us")
    C.save("headline", dict(rows=rows, ratios=ratios, overhead=overhead, batch=batch, rtol=C.RTOL, atol=C.ATOL,
                            quick=a.quick))  # fmt: skip


if __name__ == "__main__":
    main()
