"""Does a designed experiment deliver the precision it predicts? (issue 18)

Run:  nice -n 10 python benchmarks/experiment_design.py [--n 400] [--batch 400] [--seed 2]
                  [--design-args "..."] [--reuse]

1. Design: `jaxnh design` (jaxnh.identify._design_cli.main) with its defaults —
   the embedded record's duration, sampling, encoders and nominal values;
   |M1| no larger than in the record; contact force within the largest |λ| of
   the embedded experiment; J2 and the U21 knots no less precise — writes
   benchmarks/experiment/{designed_input.csv, design.json, design.png}
   (`--reuse` takes an existing design instead).
2. Monte Carlo: the true variator (examples/make_variator_data.py) is driven
   by the designed torques (read back from the CSV, as a rig would replay
   them) and measured `--n` times with independent encoder noise (quantised
   counts plus jitter, random count-grid phase), exactly as the embedded
   record was made. Each record is fitted as `jaxnh fit` does (noise
   estimated from the record, Levenberg–Marquardt on J1, J2, 7 U21 knots and
   the initial state, Gauss–Newton covariance scaled by s²), from one
   starting guess, batched with `jax.vmap`; the ODE tolerance is the one
   `fit(rtol="auto")` chooses on the first record.
3. Compares, per parameter, the mean fitted standard error and the spread of
   the estimates with the predicted standard error (±15 % asked), and the
   coverage of the truths by estimate ± 1.96 std (93–97 % asked).
4. Fits that keep up with informative data: issue 18's record
   (M1 = 0.27 sin(0.8πt)) and a designed-input record fitted by `fit_variator`
   with rtol="auto": iterations, convergence, the rtol used, the solver error
   in standard errors.

Writes benchmarks/experiment_design.json and benchmarks/EXPERIMENT.md.
"""

import argparse
import importlib.util
import json
import os
import platform
import shlex
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.identify import noise_level, solve_least_squares, statistics
from jaxnh.identify.data import Record
from jaxnh.identify._fit import GN_STEP_TOL, ode_error_in_std, prepare
from jaxnh.identify.problem import Observations
from jaxnh.identify.variator import FREE, fit_variator, params_for, ratio_knots, starting_guess
from jaxnh.identify._experiment import predict, variator_experiment
from jaxnh.models import variator as V
from jaxnh.profiles import Fourier, Sampled

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "experiment")
Z95 = 1.959963984540054


def _maker():
    path = os.path.join(HERE, "..", "examples", "make_variator_data.py")
    spec = importlib.util.spec_from_file_location("make_variator_data", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def record_with(mk, M1, M2, key, t):
    """A synthetic record of the true variator driven by torque profiles M1, M2 (N·m), measured like the
    embedded record (mk.measure); returns (Record, clean angles)."""
    p = mk.truth()
    p = V.VariatorParams(p.J1, p.J2, p.U21, M1, M2)
    ts = jnp.asarray(t)
    w0 = mk.TRUTH["w0"]
    sol = nh.simulate(V.mechanism(), p, jnp.zeros(2), jnp.array([w0, float(p.U21(0.0)) * w0]), ts,
                      rtol=1e-12, atol=1e-12)
    y = np.asarray(mk.measure(sol.q, key))
    m1 = np.asarray(jax.vmap(M1)(ts))
    m2 = np.asarray(jax.vmap(M2)(ts))
    return Record(t, {"phi1": y[:, 0], "phi2": y[:, 1]}, {"M1": m1, "M2": m2}, "synthetic"), np.asarray(sol.q)


def fit_report(res, truth):
    th = np.asarray(res.theta)
    obs = Observations(jnp.asarray(res.t), jnp.asarray(res.measured), jnp.asarray(list(res.noise.values())))
    from jaxnh.identify import value_and_jacobian

    r, J = value_and_jacobian(res.problem, jnp.asarray(th), obs)
    err = ode_error_in_std(res.problem, th, obs, r, J)
    z = {k: (res.estimates[k]["value"] - truth[k]) / res.estimates[k]["std"] for k in ("J1", "J2")}
    return {"iterations": int(res.iterations), "converged": bool(res.converged), "rtol": float(res.problem.rtol),
            "gn_step": float(res.gn_step), "ode_error_in_std_at_end": err, "message": res.message,
            "z_J1": float(z["J1"]), "z_J2": float(z["J2"]), "elapsed_s": float(res.elapsed)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=400, help="noise realisations (default 400)")
    ap.add_argument("--batch", type=int, default=400, help="realisations per vmapped batch (default 400: all)")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--design-args", default="", help="extra arguments for jaxnh design")
    ap.add_argument("--reuse", action="store_true", help="use an existing benchmarks/experiment/designed_input.csv")
    args = ap.parse_args(argv)
    mk = _maker()
    T = mk.TRUTH
    truth = {"J1": T["J1"], "J2": T["J2"]}

    # 1. design
    t_design = None
    if not args.reuse:
        from jaxnh.identify._design_cli import main as design_main

        t0 = time.perf_counter()
        code = design_main(["--out", OUT, *shlex.split(args.design_args)])
        t_design = time.perf_counter() - t0
        print(f"jaxnh design exit status {code} ({t_design:.0f} s)")
    with open(os.path.join(OUT, "design.json")) as f:
        design = json.load(f)
    with open(os.path.join(OUT, "designed_input.csv")) as f:
        rows = [ln for ln in f if not ln.startswith("#")]
    assert rows[0].strip() == "t,M1,M2", rows[0]
    tab = np.loadtxt(rows[1:], delimiter=",")
    t = tab[:, 0]
    M1, M2 = Sampled(t, tab[:, 1]), Sampled(t, tab[:, 2])


    # 2. Monte Carlo: the true motion under the designed input, many measurements
    rec0, q_clean = record_with(mk, M1, M2, jax.random.PRNGKey(args.seed), t)
    # The batched fits run first in the process (on this machine a vmapped batch run after other compiled
    # fits in the same process stalled); rtol is fit(rtol="auto")'s starting value, and the auto fit of the
    # first record below says whether it would have tightened it.
    rtol = 1e-8
    knots = ratio_knots(rec0)
    J1g, J2g, Ug = starting_guess(rec0, knots)
    problem, theta0, obs0, names = prepare(V.mechanism(), params_for(rec0, J1g, J2g, Ug), rec0, free=FREE,
                                           positive=FREE, rtol=rtol)
    q_true = jnp.asarray(q_clean)

    def one(key):
        y = mk.measure(q_true, key)
        obs = Observations(obs0.t, y, noise_level(y))
        out = solve_least_squares(problem, theta0, obs)
        st = statistics(out["J"], out["r"])
        return out["theta"], st["std"], out["steps"], out["result"], st["gn_step"], st["s2"]

    batched = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.PRNGKey(args.seed + 1000), args.n)
    # The first batch's call compiles and runs; its results are kept. (On the shared machine where this was
    # measured, a second call of the same vmapped program stalled in XLA's CPU runtime, so the default is one
    # batch of all realisations: --batch ≥ --n.)
    t0 = time.perf_counter()
    outs = [[np.asarray(x) for x in jax.block_until_ready(batched(keys[: args.batch]))]]
    compile_s = time.perf_counter() - t0
    t_run = compile_s
    print(f"  {min(args.batch, args.n)}/{args.n} fits, {t_run:.1f} s (with compilation)", flush=True)
    for i in range(args.batch, args.n, args.batch):
        t0 = time.perf_counter()
        o = jax.block_until_ready(batched(keys[i:i + args.batch]))
        t_run += time.perf_counter() - t0
        outs.append([np.asarray(x) for x in o])
        print(f"  {min(i + args.batch, args.n)}/{args.n} fits, {t_run:.1f} s", flush=True)
    theta, std, steps, result, gn, s2 = (np.concatenate(x)[: args.n] for x in zip(*outs))
    first = fit_variator(rec0)  # rtol="auto": the tolerance this record's fit uses
    print(f"first record: {first.iterations} iterations, converged {first.converged}, rtol {first.problem.rtol:.2g}")
    # predicted standard errors for this input (what the design JSON reports, recomputed)
    exp, base_params = variator_experiment()
    pred_params = V.VariatorParams(base_params.J1, base_params.J2, base_params.U21, M1, M2)
    pred = predict(exp, pred_params)
    base = predict(exp)
    P = exp.n_params
    labels = exp.labels
    ok = (result == 0) & (gn < GN_STEP_TOL) & np.all(np.isfinite(std[:, :P]), axis=1)
    est = np.exp(theta[:, :P])
    std_nat = std[:, :P] * est
    true = np.concatenate([[T["J1"], T["J2"]], T["U21_values"]])
    z = (est - true) / std_nat
    rows = {}
    for j in range(P):
        rows[labels[j]] = {
            "true": float(true[j]),
            "predicted_std": float(pred.std[j]),
            "baseline_predicted_std": float(base.std[j]),
            "mean_fitted_std": float(np.mean(std_nat[ok, j])),
            "fitted_over_predicted": float(np.mean(std_nat[ok, j]) / pred.std[j]),
            "spread_over_predicted": float(np.std(est[ok, j], ddof=1) / pred.std[j]),
            "coverage_95": float(np.mean(np.abs(z[ok, j]) <= Z95)),
            "mean_z": float(np.mean(z[ok, j])),
        }
    n_ok = int(ok.sum())
    pooled = float(np.mean(np.abs(z[ok]) <= Z95))
    ratios = np.array([r["fitted_over_predicted"] for r in rows.values()])
    cov = np.array([r["coverage_95"] for r in rows.values()])

    # 4. fits keep up with informative data (rtol="auto")
    issue = record_with(mk, Fourier(0.0, cos=[0.0, 0.0], sin=[0.0, 0.27], period=5.0), mk.truth().M2,
                        jax.random.PRNGKey(1), t)[0]
    fits = {"issue 18 record (M1 = 0.27 sin(0.8πt))": fit_report(fit_variator(issue), truth),
            "designed-input record (first realisation)": fit_report(first, truth)}
    fixed = fit_variator(issue, rtol=1e-8)
    fits["issue 18 record, rtol fixed at 1e-8"] = fit_report(fixed, truth)

    j1_gain = float(base.std[0] / pred.std[0])
    keep_ok = bool(np.all(pred.std[1:P] <= base.std[1:P] * (1 + 1e-9)))
    res = {
        "design": {k: design[k] for k in ("design", "check")},
        "predicted_std_ratio_J1": j1_gain,
        "J2_and_knots_no_worse": keep_ok,
        "predicted_ratios_baseline_over_designed": {lab: float(b / d) for lab, b, d in
                                                    zip(labels[:P], base.std[:P], pred.std[:P])},
        "realisations": args.n, "converged": n_ok, "rtol": rtol, "rtol_auto_first_record": float(first.problem.rtol),
        "parameters": rows,
        "fitted_over_predicted_range": [float(ratios.min()), float(ratios.max())],
        "coverage_range": [float(cov.min()), float(cov.max())],
        "coverage_pooled": pooled,
        "binomial_std_of_coverage": float(np.sqrt(0.95 * 0.05 / max(n_ok, 1))),
        "s2_mean": float(np.mean(s2[ok])),
        "iterations": {"mean": float(np.mean(steps)), "max": int(np.max(steps))},
        "fits_per_second": args.n / t_run, "compile_seconds": compile_s, "design_seconds": t_design,
        "fits_rtol_auto": fits,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU(s), jax {jax.__version__}",
    }
    with open(os.path.join(HERE, "experiment_design.json"), "w") as f:
        json.dump(res, f, indent=1)

    lim = design["design"]["limits"]
    chk = design["check"]
    lines = [
        "# Experiment design: predicted against realised precision",
        "",
        f"`nice -n 10 python benchmarks/experiment_design.py --n {args.n} --batch {args.batch} --seed {args.seed}`"
        + (f" `--design-args \"{args.design_args}\"`" if args.design_args else "")
        + " (issue 18). Set-up: the embedded record's (6 s at 250 Hz, encoders of 8192 and 4096 counts/rev "
        "with 0.3 and 0.6 mrad jitter, true J1 = 0.018, J2 = 0.045 kg·m², U21 spline on 7 knots, "
        "phi1'(0) = 4 rad/s); unknowns J1, J2, 7 U21 knot values and the initial state.",
        "",
        "## 1. The design (`jaxnh design`, defaults)",
        "",
        f"Designed: {', '.join(design['design']['inputs'])} as {design['design']['law']}; criterion "
        f"{design['design']['criterion']} on {', '.join(design['design']['of'])}; limits |M1| ≤ "
        f"{lim['M1_abs_max']:.4g} N·m (the record's largest |M1|)"
        + (f", |M2| ≤ {lim['M2_abs_max']:.4g} N·m (the record's largest |M2|)" if lim.get("M2_abs_max") else "")
        + f", contact force |λ| ≤ {lim['lambda_abs_max']:.4g} N·m ({lim['lambda_source']}), "
        f"no worse than the baseline: {', '.join(lim['keep_no_worse'])}. "
        f"Outputs: `benchmarks/experiment/designed_input.csv`, `design.json`, `design.png`.",
        "",
        f"Check with the torques as written to the CSV: max |λ| = {chk['max_abs_lambda']:.4g} N·m "
        f"(limit {lim['lambda_abs_max']:.4g}), max |M1| = {chk['max_abs_M1']:.4g} N·m, feasible: {chk['feasible']}.",
        "",
        f"**Predicted SE(J1): {j1_gain:.2f}× smaller than with the embedded record's input** (asked: ≥ 3×); "
        f"J2 and every U21 knot no worse: {keep_ok}.",
        "",
        "| parameter | predicted std, baseline | predicted std, designed | baseline / designed |",
        "|---|---|---|---|",
    ]
    for lab in labels[:P]:
        r = rows[lab]
        lines.append(f"| {lab} | {r['baseline_predicted_std']:.4g} | {r['predicted_std']:.4g} | "
                     f"{r['baseline_predicted_std'] / r['predicted_std']:.2f} |")
    lines += [
        "",
        "![design](experiment/design.png)",
        "",
        f"## 2. Monte Carlo: {args.n} records with the designed input",
        "",
        f"Converged: {n_ok} of {args.n} (ODE rtol {rtol:.2g}; `fit(rtol=\"auto\")` on the first record chose "
        f"{first.problem.rtol:.2g}). Mean {res['iterations']['mean']:.1f} Levenberg–Marquardt iterations (max "
        f"{res['iterations']['max']}); s² = {res['s2_mean']:.3f} on average. Binomial standard deviation of a "
        f"coverage estimate at 95 %: ±{100 * res['binomial_std_of_coverage']:.1f} points.",
        "",
        "| parameter | predicted std | mean fitted std | fitted / predicted | spread of estimates / predicted | "
        "coverage 95 % | mean z |",
        "|---|---|---|---|---|---|---|",
    ]
    for lab, r in rows.items():
        lines.append(f"| {lab} | {r['predicted_std']:.4g} | {r['mean_fitted_std']:.4g} | "
                     f"{r['fitted_over_predicted']:.3f} | {r['spread_over_predicted']:.3f} | "
                     f"{100 * r['coverage_95']:.1f} % | {r['mean_z']:+.3f} |")
    lines += [
        "",
        f"Fitted standard errors / predicted: {ratios.min():.3f} … {ratios.max():.3f} (asked: within ±15 %). "
        f"Coverage per parameter {100 * cov.min():.1f} … {100 * cov.max():.1f} %, pooled over the "
        f"{P} parameters {100 * pooled:.1f} % (asked: 93–97 %).",
        "",
        f"Speed: {res['fits_per_second']:.1f} fits/s including compilation ({compile_s:.0f} s for the first batch); "
        + f"design {(t_design or design['elapsed_s']):.0f} s; "
        + f"machine {res['machine']}, shared with other jobs (times are upper bounds).",
        "",
        "## 3. Fits keep up with informative data (`fit(rtol=\"auto\")`)",
        "",
        "The fit starts at rtol 1e-8, then compares the fitted channels with a solve 1000× tighter; the "
        "difference projected on the Jacobian's range is the shift of the estimates caused by the solver, in "
        "standard errors. Above 0.05 (the Gauss–Newton stopping precision) rtol is tightened and the fit "
        "continued.",
        "",
        "| record | iterations | converged | rtol used | remaining GN step (std) | solver error at the end (std) | "
        "z(J1), z(J2) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, f in fits.items():
        lines.append(f"| {name} | {f['iterations']} | {f['converged']} | {f['rtol']:.2g} | {f['gn_step']:.3f} | "
                     f"{f['ode_error_in_std_at_end']:.3f} | {f['z_J1']:+.2f}, {f['z_J2']:+.2f} |")
    with open(os.path.join(HERE, "EXPERIMENT.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
