"""What friction-held contacts cost: a scene without them, and solves with 0, 1 and 2 transitions.

The variator of examples/variator_slip.py (ratio 1 → 2 in 0.5 s at 100 rad/s,
the roller's rolling constraint held by a `FrictionContact`), at simulate's
default settings (rtol 1e-8, atol 1e-10, the default solver and formulation)
over 1 s with 21 report times:

* **rolling** — the same mechanism with its contacts removed: the constraint
  holds whatever force it takes. A mechanism without contacts never reaches
  the friction solve (`simulate` dispatches on `mech.contacts` before any
  tracing), so this is what every scene without friction runs. Its lowered
  program's SHA-256 is recorded, so that two revisions can be compared.
* **friction, k transitions** — μs = 0.5 (never slips, k = 0), 0.02 (slips
  once and to the end, k = 1), 0.3 (slips and locks again, k = 2).

Per case: CPU time per call (median over interleaved rounds, after
compilation), solver steps, segments, and the error reached: the slip onset
against the closed-form condition J1 J2 |U21'| φ1' = μs N ρ (J1 + J2 U21²)
(`examples/variator_slip.py`), and for the rolling solve φ1' against its
closed form w0 √(I(0)/I(t)), I = J1 + J2 U21². Fixed costs: the first call
(import, trace, compile, run) of the rolling and the slipping (k = 2) solve,
each in a fresh process.

    python -m benchmarks.friction [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib

from . import common as C


C.pin()  # before JAX starts

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402


CASES = {"friction, k = 0": 0.5, "friction, k = 1": 0.02, "friction, k = 2": 0.3}

FIRST_CALL = """
import jax.numpy as jnp
import jaxnh as nh
{IMPORTED}
from benchmarks import common as C
V = C.example("variator_slip")
import dataclasses, time
mech = V.VARIATOR if {friction} else dataclasses.replace(V.VARIATOR, contacts=())
t0 = time.perf_counter()
sol = nh.simulate(mech, V.PARAMS, V.Q0, V.QD0, jnp.linspace(0.0, 1.0, 21), step_ts=[V.PARAMS["Tr"]])
sol.q.block_until_ready()
OUT["first_call"] = time.perf_counter() - t0
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer rounds, no fresh processes")
    a = ap.parse_args(argv)
    V = C.example("variator_slip")
    p, q0, qd0 = V.PARAMS, V.Q0, V.QD0
    ts = jnp.linspace(0.0, 1.0, 21)
    rolling = dataclasses.replace(V.VARIATOR, contacts=())

    def solve(mech, mu_s):
        return nh.simulate(mech, {**p, "mu_s": mu_s}, q0, qd0, ts, step_ts=[p["Tr"]], throw=False)

    def rolling_error(sol) -> float:
        U = p["r"] / np.asarray(jax.vmap(lambda t: V.rho(t, p))(ts))
        inertia = p["J1"] + p["J2"] * U**2
        w = V.W0 * np.sqrt(inertia[0] / inertia)
        return float(np.max(np.abs(np.asarray(sol.qd[:, 0]) - w)))

    rows, calls = {}, {}
    sol = solve(rolling, 0.3)
    lowered = jax.jit(lambda pp: solve(rolling, pp["mu_s"]).q).lower({**p, "mu_s": jnp.asarray(0.3)})
    rows["rolling"] = dict(
        steps=int(sol.stats["num_steps"]),
        segments=1,
        error=rolling_error(sol),
        error_of="max |φ1' − closed form|, rad/s",
        program_sha256=hashlib.sha256(lowered.as_text().encode()).hexdigest()[:16],
    )
    calls["rolling"] = C.repeat(lambda: jax.block_until_ready(solve(rolling, 0.3)), 0.05)
    for name, mu_s in CASES.items():
        sol = solve(V.VARIATOR, mu_s)
        assert sol.contacts is not None and bool(sol.status == nh.STATUS.successful), sol.message
        kinds = sol.contacts.transitions("roller")
        row = dict(mu_s=mu_s, transitions=len(kinds), steps=int(sol.stats["num_steps"]))
        row["segments"] = int(sol.stats["segments"])
        if kinds:
            row["error"] = abs(kinds[0][0] - V.onset_closed_form({**p, "mu_s": mu_s}))
            row["error_of"] = "|slip onset − closed form|, s"
        rows[name] = row
        calls[name] = C.repeat(lambda mu_s=mu_s: jax.block_until_ready(solve(V.VARIATOR, mu_s)), 0.05)
        C.log(f"[friction] {name}: {row}")
    T = C.interleave({k: m for k, (m, _) in calls.items()}, rounds=5 if a.quick else 9, budget=20 if a.quick else 120)
    for k, (_, n) in calls.items():
        rows[k]["cpu"] = C.median(np.asarray(T[k]["cpu"]) / n)
        rows[k]["over_rolling"] = C.paired_ratio(T[k]["cpu"], T["rolling"]["cpu"]) * calls["rolling"][1] / n
        C.log(f"[friction] {k}: {rows[k]['cpu'] * 1e3:.2f} ms, {rows[k]['over_rolling']:.2f} × rolling")
    first = {}
    if not a.quick:
        for key, friction in (("rolling", False), ("friction, k = 2", True)):
            first[key] = C.fresh(FIRST_CALL.format(IMPORTED=C.IMPORTED, friction=friction))
            C.log(f"[friction] first call, {key}: {first[key]}")
    C.save("friction", dict(rows=rows, first=first, quick=a.quick, report_times=int(ts.shape[0])))


if __name__ == "__main__":
    main()
