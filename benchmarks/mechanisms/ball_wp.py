"""Work-precision of the ball on the turntable (`benchmarks.mechanisms.ball`) against its closed form.

Contenders: the default (`method="appell"`, the partition chosen and re-chosen
during the run), Appell with a fixed split (`ball.GOOD_INDEPENDENT`) and
`method="lagrange"`; rtol 1e-6 … 1e-12, atol = rtol/100. Error: distance of
the centre from the closed form at the end time (and the largest over the
report times), m. Time: median wall and process-CPU time of `REPEAT` calls after a
first (compiling) call.

Two motions: "circling" (`initial_state` defaults: the centre circles at
2Ω/7 on a circle of radius 1.57 m) and "held" (ω = (Ω x0 / r, 0, 3) rad/s:
the turntable holds the centre still, v0 = 0, while the ball turns).

    python -m benchmarks.mechanisms.ball_wp [--t-end 50,200] [--motions circling,held] [--out FILE]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh

from . import ball as B


RTOLS = (1e-6, 1e-8, 1e-10, 1e-12)
REPEAT = 3
MOTIONS = {"circling": {}, "held": {"omega": (5.0, 0.0, 3.0)}}


def contenders():
    return {
        "appell (auto)": "appell",
        "appell fixed %s" % (B.GOOD_INDEPENDENT,): nh.Appell(independent=B.GOOD_INDEPENDENT),
        "lagrange": "lagrange",
    }


def run(t_ends, motions, rtols=RTOLS, repeat=REPEAT, log=print):
    p = B.params()
    mech = B.mechanism()
    rows = []
    for motion in motions:
        q0, qd0 = B.initial_state(p, **MOTIONS[motion])
        for t_end in t_ends:
            ts = jnp.linspace(0.0, t_end, 11)
            rho = B.closed_form(ts, p, q0, qd0)[0]
            for name, method in contenders().items():
                for rtol in rtols:
                    kw = dict(method=method, rtol=rtol, atol=rtol / 100, throw=False, max_steps=1_000_000)
                    sol = nh.simulate(mech, p, q0, qd0, ts, **kw)
                    jax.block_until_ready(sol.q)
                    walls, cpus = [], []
                    for _ in range(repeat):
                        w, c = time.perf_counter(), time.process_time()
                        sol = nh.simulate(mech, p, q0, qd0, ts, **kw)
                        jax.block_until_ready(sol.q)
                        walls.append(time.perf_counter() - w)
                        cpus.append(time.process_time() - c)
                    dist = np.asarray(jnp.linalg.norm(sol.q[:, :2] - rho, axis=1))
                    row = dict(
                        motion=motion,
                        t_end=t_end,
                        method=name,
                        rtol=rtol,
                        err_end=float(dist[-1]),
                        err_max=float(np.max(dist)),
                        steps=int(sol.stats["num_steps"]),
                        accepted=int(sol.stats["num_accepted_steps"]),
                        wall=float(np.median(walls)),
                        cpu=float(np.median(cpus)),
                        status=sol.message,
                    )
                    rows.append(row)
                    log(
                        "%-8s T=%5g %-22s rtol=%.0e  err(T)=%.2e max=%.2e  steps=%6d (%6d acc)  "
                        "wall=%.4f s cpu=%.4f s  %s"
                        % (
                            motion,
                            t_end,
                            name,
                            rtol,
                            row["err_end"],
                            row["err_max"],
                            row["steps"],
                            row["accepted"],
                            row["wall"],
                            row["cpu"],
                            row["status"][:40],
                        )
                    )
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", default="50", help="end times, s, comma-separated")
    ap.add_argument("--motions", default="circling,held")
    ap.add_argument("--repeat", type=int, default=REPEAT)
    ap.add_argument("--out", default=None, help="also append the table to this file")
    a = ap.parse_args()
    lines = ["jaxnh: %s" % nh.__file__]
    print(lines[0], flush=True)

    def log(s):
        print(s, flush=True)
        lines.append(s)

    run([float(x) for x in a.t_end.split(",")], a.motions.split(","), repeat=a.repeat, log=log)
    if a.out:
        with open(a.out, "a") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
