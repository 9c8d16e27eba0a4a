"""Work–precision on the rolling ball: the default formulation (Appell) against Lagrange's.

A ball rolling without slipping on a turntable, its orientation a quaternion
(benchmarks/mechanisms/ball.py: s = 6, two rolling constraints and the unit
quaternion's, rheonomic, with a closed form for the centre's motion). For
each rtol in 1e-6 … 1e-12 (atol = rtol / 100) a plain `simulate` call with
the default solver, method "appell" (the default) and "lagrange", timed in
interleaved rounds after compilation. The error is the larger of the
centre's deviation from the closed form (position, m, and velocity, m/s) and
the whole state's from a reference solve (Appell's form, Dopri8, rtol 1e-14;
its distance from Lagrange's form at the same tolerance is the floor of the
errors that mean something) over the report times.
Without --quick, also both formulations with diffrax's Tsit5 and Dopri8 at
each rtol, to show where the default solver stands.

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

from .mechanisms import ball as B  # noqa: E402


T_END, N_REPORT = 20.0, 101


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="rtol 1e-6, 1e-9, 1e-12, default solver only")
    a = ap.parse_args(argv)
    rtols = (1e-6, 1e-9, 1e-12) if a.quick else (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12)
    solvers = {"default": None} if a.quick else {"default": None, "Tsit5": diffrax.Tsit5, "Dopri8": diffrax.Dopri8}
    mech, p = B.mechanism(), B.params()
    q0, qd0 = B.initial_state(p)
    ts = jnp.linspace(0.0, T_END, N_REPORT)
    rho, v = (np.asarray(x) for x in B.closed_form(ts, p, q0, qd0))
    ref, check = (
        nh.simulate(mech, p, q0, qd0, ts, m, solver=diffrax.Dopri8(), rtol=1e-14, atol=1e-16, max_steps=1_000_000)
        for m in ("appell", "lagrange")
    )
    q_ref, qd_ref = np.asarray(ref.q), np.asarray(ref.qd)
    ref_centre, floor = centre_error(ref, rho, v), C.max_error(check.q, check.qd, q_ref, qd_ref)
    C.log(f"[precision] reference: centre {ref_centre:.1e} from the closed form, {floor:.1e} from Lagrange's")
    calls, rows = {}, {}
    for method in ("appell", "lagrange"):
        for sname, solver in solvers.items():
            for rtol in rtols:
                key = f"{method} {sname} {rtol:g}"

                def call(method=method, solver=solver, rtol=rtol):
                    s = nh.simulate(
                        mech,
                        p,
                        q0,
                        qd0,
                        ts,
                        method,
                        solver=None if solver is None else solver(),
                        rtol=rtol,
                        atol=rtol / 100,
                        max_steps=1_000_000,
                    )
                    return jax.block_until_ready(s)

                s = call()
                centre = centre_error(s, rho, v)
                err = max(centre, C.max_error(s.q, s.qd, q_ref, qd_ref))
                rows[key] = dict(method=method, solver=sname, rtol=rtol, error=err, centre_error=centre,
                                 steps=int(s.stats["num_steps"]))  # fmt: skip
                calls[key] = C.repeat(call, 0.05)
                C.log(f"[precision] {key}: error {err:.1e} (centre {centre:.1e}), {rows[key]['steps']} steps")
    T = C.interleave({k: m for k, (m, _) in calls.items()}, rounds=5 if a.quick else 7, budget=30 if a.quick else 240)
    for k, (_, n) in calls.items():
        rows[k]["cpu"] = C.median(np.asarray(T[k]["cpu"]) / n)
        rows[k]["rounds"] = len(T[k]["cpu"])
        C.log(f"[precision] {k}: {rows[k]['cpu'] * 1e3:.2f} ms")
    ratios = {
        f"{r:g}": C.paired_ratio(T[f"appell default {r:g}"]["cpu"], T[f"lagrange default {r:g}"]["cpu"])
        * calls[f"lagrange default {r:g}"][1]
        / calls[f"appell default {r:g}"][1]
        for r in rtols
    }
    C.save("precision", dict(rows=rows, appell_over_lagrange=ratios, rtols=rtols, horizon=T_END, quick=a.quick,
                             reference_centre_error=ref_centre, reference_floor=floor))  # fmt: skip


def centre_error(sol, rho, v) -> float:
    """Largest error of the centre's position (m) and velocity (m/s) against the closed form."""
    return float(max(np.max(np.abs(np.asarray(sol.q[:, :2]) - rho)), np.max(np.abs(np.asarray(sol.qd[:, :2]) - v))))


if __name__ == "__main__":
    main()
