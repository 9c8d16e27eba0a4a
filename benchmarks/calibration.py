"""Calibration of the fit's error bars: do the 95 % intervals cover the truth 95 % of the time?

    python -m benchmarks.calibration [--n 240] [--batch 60] [--seed 1] [--noise encoder|gaussian]
    python -m benchmarks.calibration --quick     # 8 realisations in one batch: a smoke run

The embedded record's experiment (examples/make_variator_data.py: same true
J1, J2, U21(t), torques and initial state) is repeated with independent
encoder noise: every realisation gets its own Gaussian jitter before the
quantisation to whole counts. Each record is fitted exactly as `jaxnh fit`
does (noise levels estimated from that record, Levenberg–Marquardt on J1,
J2, 7 U21 knot values and the initial state, Gauss–Newton covariance scaled
by the residual variance), all from the same starting guess, in batches with
`jax.vmap` (`jaxnh.identify.prepare`, `solve_least_squares`, `statistics`).
Reports, per parameter, how often |estimate − truth| ≤ 1.96 std, the mean
and spread of (estimate − truth)/std (0 and 1 when calibrated), the fit's
lack-of-fit test's false-alarm rate, and fits per second after compilation.

Writes CALIBRATION.md and results/calibration.json: into benchmarks/ (a
`--quick` run into benchmarks/quick/), or into $JAXNH_BENCH_OUT when set.
The process runs on one core (`common.pin`): with XLA's pool threads a
vmapped batch of fits deadlocked on a 2-core machine (see experiment_design.py).
"""

from __future__ import annotations

import argparse
import time

from . import common as C


C.pin()  # before JAX starts

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh  # noqa: E402, F401  (64-bit mode)
from jaxnh.identify import load_default, noise_level, Observations, prepare, solve_least_squares, statistics  # noqa: E402
from jaxnh.identify._fit import GN_STEP_TOL  # noqa: E402  (the fit's convergence test; not public)
from jaxnh.identify.diagnostics import LACK_OF_FIT_Z, NOISE_ESTIMATE_REL_VAR  # noqa: E402
from jaxnh.models import variator as V  # noqa: E402
from jaxnh.models.variator_fit import FREE, params_for, ratio_knots, starting_guess  # noqa: E402


Z95 = 1.959963984540054


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=240, help="noise realisations (default 240)")
    ap.add_argument("--batch", type=int, default=60, help="realisations per vmapped batch (default 60)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--noise",
        choices=("encoder", "gaussian"),
        default="encoder",
        help="encoder: quantised readings as in the embedded record (default); gaussian: white "
        "Gaussian noise of the same standard deviation (a control)",
    )
    ap.add_argument("--quick", action="store_true", help="--n 8 --batch 8 (a smoke run, about a minute)")
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.batch = 8, 8
    out_dir = C.report_dir(args.quick)
    mk = C.example("make_variator_data")
    T = mk.TRUTH
    q_true = jnp.asarray(mk.clean_motion())

    # the problem as `jaxnh fit` sets it up on the embedded record; only the data change
    rec = load_default()
    knots = ratio_knots(rec)
    J1, J2, U = starting_guess(rec, knots)
    problem, theta0, obs0, names = prepare(V.mechanism(), params_for(rec, J1, J2, U), rec, free=FREE, positive=FREE)
    labels = problem.labels(names)
    P = problem.par.size
    truth_theta = np.concatenate([np.log([T["J1"], T["J2"]]), np.log(T["U21_values"])])
    log = problem.par.log_mask()

    sigma_true = jnp.asarray(mk.noise_std())

    def one(key):
        if args.noise == "encoder":
            y = mk.measure(q_true, key)
        else:
            y = q_true + sigma_true * jax.random.normal(key, q_true.shape)
        obs = Observations(obs0.t, y, noise_level(y))
        out = solve_least_squares(problem, theta0, obs)
        st = statistics(out["J"], out["r"])
        return out["theta"], st["std"], out["steps"], out["result"], st["gn_step"], st["s2"], st["dof"]

    batched = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.n)
    t0 = time.perf_counter()
    jax.block_until_ready(batched(keys[: args.batch]))
    compile_s = time.perf_counter() - t0
    outs, t_run = [], 0.0
    for i in range(0, args.n, args.batch):
        t0 = time.perf_counter()
        o = jax.block_until_ready(batched(keys[i : i + args.batch]))
        t_run += time.perf_counter() - t0
        outs.append([np.asarray(x) for x in o])
        C.log(f"  {min(i + args.batch, args.n)}/{args.n} fits, {t_run:.1f} s")
    theta, std, steps, result, gn, s2, dof = (np.concatenate(x)[: args.n] for x in zip(*outs))
    # the fit's lack-of-fit test (jaxnh.identify.diagnostics.lack_of_fit, noise estimated from the record):
    # the model contains the truth here, so every alarm is a false one (expected rate 1 %)
    k = obs0.y.shape[1]
    s2_limit = 1 + LACK_OF_FIT_Z * np.sqrt(2 / dof + NOISE_ESTIMATE_REL_VAR / ((rec.n - 3) * k))
    ok = (result == 0) & (gn < GN_STEP_TOL) & np.all(np.isfinite(std[:, :P]), axis=1)
    # coverage on the natural scale, as reported by `fit`: value ± 1.96 · std, std = std(log θ) · θ
    est = np.exp(theta[:, :P])
    std_nat = std[:, :P] * est
    true = np.exp(truth_theta)
    z = (est - true) / std_nat
    rows = {}
    for j in range(P):
        zj = z[ok, j]
        rows[labels[j]] = {
            "true": float(true[j]),
            "coverage_95": float(np.mean(np.abs(zj) <= Z95)),
            "mean_z": float(np.mean(zj)),
            "std_z": float(np.std(zj, ddof=1)),
            "mean_relative_std": float(np.mean(std[ok, j])) if log[j] else None,
            "empirical_relative_spread": float(np.std(est[ok, j] / true[j], ddof=1)),
        }
    n_ok = int(ok.sum())
    cov = {k: rows[k]["coverage_95"] for k in ("J1", "J2")}
    res = {
        "realisations": args.n,
        "converged": n_ok,
        "coverage_95": cov,
        "both_within_90_99": bool(all(0.90 <= v <= 0.99 for v in cov.values())),
        "binomial_std_of_coverage": float(np.sqrt(0.95 * 0.05 / max(n_ok, 1))),
        "parameters": rows,
        "iterations": {"mean": float(np.mean(steps)), "max": int(np.max(steps))},
        "s2_mean": float(np.mean(s2[ok])),
        "s2_std": float(np.std(s2[ok], ddof=1)),
        "s2_limit_1pct": float(np.median(s2_limit)),
        "lack_of_fit_false_alarm_rate": float(np.mean(s2[ok] > s2_limit[ok])),
        "fits_per_second": args.n / t_run,
        "run_seconds": t_run,
        "compile_seconds": compile_s,
        "batch": args.batch,
        "seed": args.seed,
        "noise": args.noise,
        "samples_per_record": int(rec.n),
        "unknowns": int(problem.size),
        "quick": args.quick,
    }
    C.save("calibration", res, out_dir)
    m = C.machine()
    lines = [
        "# Calibration of the fit's 95 % intervals",
        "",
        C.stamp_line(C.command("calibration", argv)),
        "",
        f"{args.n} independent noise realisations of the embedded record's experiment "
        f"({rec.n} samples per record, "
        + ("two quantised encoders with jitter" if args.noise == "encoder" else "white Gaussian noise (a control)")
        + f"), each fitted like `jaxnh fit` "
        f"({problem.size} unknowns: J1, J2, 7 U21 knot values, phi1(0), phi2(0), phi1'(0); noise levels "
        "estimated per record; Gauss–Newton covariance scaled by the residual variance), "
        f"batched with `jax.vmap` ({args.batch} per batch), seed {args.seed}.",
        "",
        f"Converged: {n_ok} of {args.n}. Coverage of the true value by estimate ± 1.96 std "
        "(binomial standard deviation of a coverage estimate at 95 %: "
        f"±{100 * res['binomial_std_of_coverage']:.1f} points):",
        "",
        "| parameter | true | coverage 95 % | mean z | std z | mean rel. std | spread of estimates (rel.) |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, r in rows.items():
        mr = f"{100 * r['mean_relative_std']:.4f} %" if r["mean_relative_std"] is not None else "-"
        lines.append(
            f"| {k} | {r['true']:.6g} | {100 * r['coverage_95']:.1f} % | {r['mean_z']:+.3f} | "
            f"{r['std_z']:.3f} | {mr} | {100 * r['empirical_relative_spread']:.4f} % |"
        )
    lines += [
        "",
        "z = (estimate − truth) / reported std; a calibrated fit has mean z ≈ 0, std z ≈ 1, coverage ≈ 95 %.",
        "",
        f"Speed: {res['fits_per_second']:.2f} fits/s after compilation ({t_run:.1f} s for {args.n} fits; "
        f"compilation {compile_s:.1f} s); mean {res['iterations']['mean']:.1f} Levenberg–Marquardt "
        f"iterations (max {res['iterations']['max']}). One core of {m['cores']} (wall times; the machine may be "
        "shared: times are upper bounds).",
        "",
        f"Lack-of-fit test (the model contains the truth, so every alarm is false; nominal rate 1 %): s² = "
        f"{res['s2_mean']:.3f} ± {res['s2_std']:.3f} (mean ± std over realisations; the test assumes "
        f"± {(res['s2_limit_1pct'] - 1) / LACK_OF_FIT_Z:.3f}), limit {res['s2_limit_1pct']:.3f}, "
        f"false alarms {100 * res['lack_of_fit_false_alarm_rate']:.1f} %.",
    ]
    path = out_dir / "CALIBRATION.md"
    path.write_text("\n".join(lines) + "\n")
    C.log("\n".join(lines))
    C.log(f"wrote {path}")
    return res


if __name__ == "__main__":
    main()
