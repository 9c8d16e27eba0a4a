"""Work–precision: the default formulation (Lagrange's) against Appell's, on three mechanisms.

* the rolling ball: a ball rolling without slipping on a turntable, its
  orientation a quaternion (benchmarks/mechanisms/ball.py: s = 6, two rolling
  constraints and the unit quaternion's, rheonomic), 20 s; error: the larger
  of the centre's deviation from the closed form (position, m, and velocity,
  m/s) and the whole state's from a reference solve (Appell's form, Dopri8,
  rtol 1e-14);
* the variator with a sinusoidal ratio (benchmarks/mechanisms/variator.py),
  10 s; error against the closed form of the seed paper's eq. (9);
* a car with 4 trailers (benchmarks/mechanisms/chain.py: s = 7, five knife
  edges), 10 s; error against SciPy's DOP853 at rtol 1e-12 on the mechanism's
  equations written out in NumPy (`chain.lagrange_numpy`, no jaxnh code).

For each rtol in 1e-6 … 1e-12 (atol = rtol / 100) a plain `simulate` call with
the default solver, method "lagrange" (the default) and "appell", timed in
interleaved rounds after compilation; the error is the largest over the
report times of coordinates and velocities. Without --quick, also both
formulations with diffrax's Tsit5 and Dopri8 at each rtol on the ball, to show
where the default solver stands.

    python -m benchmarks.precision [--quick]
"""

from __future__ import annotations

import argparse

from . import common as C


C.pin()  # before JAX starts

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402

from .mechanisms import ball as B, chain as CH, variator as VV  # noqa: E402


T_END, N_REPORT = 20.0, 101
METHODS = ("lagrange", "appell")  # the default first


def problems():
    """name -> (mechanism, params, q0, qd0, ts, error(sol) -> float, note)."""
    out = {}
    p = B.params()
    q0, qd0 = B.initial_state(p)
    ts = jnp.linspace(0.0, T_END, N_REPORT)
    rho, v = (np.asarray(x) for x in B.closed_form(ts, p, q0, qd0))
    mech = B.mechanism()
    ref = nh.simulate(mech, p, q0, qd0, ts, "appell", solver=diffrax.Dopri8(), rtol=1e-14, atol=1e-16,
                      max_steps=1_000_000)  # fmt: skip
    q_ref, qd_ref = np.asarray(ref.q), np.asarray(ref.qd)

    def ball_error(sol):
        return max(centre_error(sol, rho, v), C.max_error(sol.q, sol.qd, q_ref, qd_ref))

    note = f"reference centre {centre_error(ref, rho, v):.1e} from the closed form"
    out["ball"] = (mech, p, q0, qd0, ts, ball_error, note)
    vq, vqd = VV.reference()
    out["variator"] = (VV.mechanism(), VV.PARAMS, VV.Q0, VV.QD0, VV.TS, lambda sol: C.max_error(sol.q, sol.qd, vq, vqd),
                       "closed form")  # fmt: skip
    n = 4
    pc = CH.params(n)
    cq0, cqd0 = CH.initial_state(n, pc)
    cts = CH.report_times()
    cq, cqd = CH.reference(n, pc, cq0, cqd0, cts)
    out["chain4"] = (CH.mechanism(n), pc, cq0, cqd0, cts, lambda sol: C.max_error(sol.q, sol.qd, cq, cqd),
                     "SciPy DOP853 at rtol 1e-12 on NumPy equations")  # fmt: skip
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="rtol 1e-6, 1e-9, 1e-12, default solver only")
    a = ap.parse_args(argv)
    rtols = (1e-6, 1e-9, 1e-12) if a.quick else (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12)
    calls, rows, notes = {}, {}, {}
    for name, (mech, p, q0, qd0, ts, error, note) in problems().items():
        notes[name] = note
        solvers = {"default": None}
        if name == "ball" and not a.quick:
            solvers.update(Tsit5=diffrax.Tsit5, Dopri8=diffrax.Dopri8)
        for method in METHODS:
            for sname, solver in solvers.items():
                for rtol in rtols:
                    key = f"{name} {method} {sname} {rtol:g}"

                    def call(mech=mech, p=p, q0=q0, qd0=qd0, ts=ts, method=method, solver=solver, rtol=rtol):
                        s = nh.simulate(mech, p, q0, qd0, ts, method, solver=None if solver is None else solver(),
                                        rtol=rtol, atol=rtol / 100, max_steps=1_000_000)  # fmt: skip
                        return jax.block_until_ready(s)

                    s = call()
                    rows[key] = dict(mechanism=name, method=method, solver=sname, rtol=rtol, error=error(s),
                                     steps=int(s.stats["num_steps"]))  # fmt: skip
                    calls[key] = C.repeat(call, 0.05)
                    C.log(f"[precision] {key}: error {rows[key]['error']:.1e}, {rows[key]['steps']} steps")
    T = C.interleave({k: m for k, (m, _) in calls.items()}, rounds=5 if a.quick else 7, budget=60 if a.quick else 300)
    for k, (_, n) in calls.items():
        rows[k]["cpu"] = C.median(np.asarray(T[k]["cpu"]) / n)
        rows[k]["rounds"] = len(T[k]["cpu"])
        C.log(f"[precision] {k}: {rows[k]['cpu'] * 1e3:.2f} ms")
    C.save("precision", dict(rows=rows, rtols=rtols, horizon=T_END, quick=a.quick, references=notes,
                             mechanisms=sorted(notes)))  # fmt: skip


def centre_error(sol, rho, v) -> float:
    """Largest error of the centre's position (m) and velocity (m/s) against the closed form."""
    return float(max(np.max(np.abs(np.asarray(sol.q[:, :2]) - rho)), np.max(np.abs(np.asarray(sol.qd[:, :2]) - v))))


if __name__ == "__main__":
    main()
