"""Cost of `jaxnh fit` on the embedded record: compile vs iterate, and a Jacobian against a simulation.

    python -m benchmarks.fit_cost [--repeat 31]
    python -m benchmarks.fit_cost --quick    # 3 rounds; no fresh process, no compiled LM loop

Measured in one process pinned to one core (`common.pin`), on the problem
exactly as `jaxnh fit` sets it up (1501 samples, two channels, 12 unknowns:
J1, J2, 7 U21 knot values, phi1(0), phi2(0), phi1'(0); default solver
settings), with no persistent compilation cache (importing jaxnh turns none
on; a user's first run):

* one simulation: the weighted residuals at the starting guess (one solve);
* one Jacobian of the 3002 residuals by the 12 unknowns, as the fit computes
  it (`jaxnh.identify.value_and_jacobian`: `jax.jacfwd` with
  `jaxnh.ForwardSensitivity`), and, for comparison, by `jax.jacfwd` through
  `diffrax.ForwardMode` (`Problem.trajectory` with that adjoint) and the
  gradient of ½|r|² by reverse mode (`RecursiveCheckpointAdjoint`, what a fit
  with differentiation="reverse" uses); each with its compile time, the
  median of `--repeat` interleaved rounds, and its agreement with the
  ForwardSensitivity result;
* the whole fit: `fit_variator(load_default())` twice in the same process —
  the first call compiles and iterates, the second only iterates — and the
  command `jaxnh fit --quiet --json ...` in a fresh process (every core, an
  empty cache folder: imports + compile + iterate), with the iterations and
  the error reached.

Writes FIT_COST.md and results/fit_cost.json: into benchmarks/ (a `--quick`
run into benchmarks/quick/), or into $JAXNH_BENCH_OUT when set.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time

from . import common as C


C.pin()  # before JAX starts

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh  # noqa: E402, F401  (64-bit mode)
from jaxnh.identify import load_default, prepare, solve_least_squares, value_and_jacobian  # noqa: E402
from jaxnh.identify.problem import solve_least_squares_host  # noqa: E402
from jaxnh.models import variator as V  # noqa: E402
from jaxnh.models.variator_fit import embedded_truth, fit_variator, FREE, params_for, ratio_knots, starting_guess  # noqa: E402


CLI = """
from jaxnh.cli import main
OUT = {"exit_code": main(["fit", "--quiet", "--json", JSON_PATH])}
"""


def first_call(fn, *args):
    """(seconds of the first, compiling, call; output)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, out


def interleaved(calls, repeat):
    """Median seconds per call of each `(fn, args)` in `calls`, timed in `repeat` rounds that run
    every call once (so a change of the machine's load hits all of them alike)."""
    runs = {k: [] for k in calls}
    for _ in range(repeat):
        for k, (fn, a) in calls.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*a))
            runs[k].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in runs.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=31, help="timed rounds per evaluation (median reported)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="3 rounds; skip the fresh-process `jaxnh fit` and the compiled Levenberg–Marquardt loop",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.repeat = 3
    out_dir = C.report_dir(args.quick)
    truth = embedded_truth()

    rec = load_default()
    knots = ratio_knots(rec)
    J1, J2, U = starting_guess(rec, knots)
    problem, theta0, obs, names = prepare(V.mechanism(), params_for(rec, J1, J2, U), rec, free=FREE, positive=FREE)
    sim = eqx.filter_jit(lambda pr, th, ob: pr.raw_residuals(th, ob))
    problem_rev = dataclasses.replace(problem, differentiation="reverse")

    @eqx.filter_jit
    def jac_forward_mode(pr, th, ob):
        def res(t):
            q = pr.trajectory(t, ob.t, diffrax.ForwardMode())
            return ((q[:, jnp.asarray(pr.observed)] - ob.y) / ob.sigma).reshape(-1)

        return jax.jacfwd(res)(th)

    @eqx.filter_jit
    def grad_reverse(pr, th, ob):
        return jax.grad(lambda t: 0.5 * jnp.sum(pr.raw_residuals(t, ob) ** 2))(th)

    calls = {
        "simulation": (sim, (problem, theta0, obs)),
        "jacobian_forward_sensitivity": (value_and_jacobian, (problem, theta0, obs)),
        "jacobian_diffrax_forward_mode": (jac_forward_mode, (problem, theta0, obs)),
        "gradient_reverse_mode": (grad_reverse, (problem_rev, theta0, obs)),
    }
    evals, outs = {}, {}
    for k, (fn, a) in calls.items():
        c, outs[k] = first_call(fn, *a)
        evals[k] = {"compile_and_first_s": c}
        C.log(f"{k}: compile+first {c:.1f} s")
    r, J = (np.asarray(x) for x in outs["jacobian_forward_sensitivity"])
    g_ref = J.T @ r
    evals["jacobian_forward_sensitivity"]["max_rel_diff"] = 0.0
    evals["jacobian_diffrax_forward_mode"]["max_rel_diff"] = float(
        np.max(np.abs(np.asarray(outs["jacobian_diffrax_forward_mode"]) - J)) / np.max(np.abs(J))
    )
    evals["gradient_reverse_mode"]["max_rel_diff"] = float(
        np.max(np.abs(np.asarray(outs["gradient_reverse_mode"]) - g_ref)) / np.max(np.abs(g_ref))
    )
    for k, m in interleaved(calls, args.repeat).items():
        evals[k]["median_s"] = m
    t_sim = evals["simulation"]["median_s"]
    for v in evals.values():
        v["relative_to_simulation"] = v["median_s"] / t_sim
    for k, v in evals.items():
        C.log(
            f"{k}: compile+first {v['compile_and_first_s']:.1f} s, median {1e3 * v['median_s']:.2f} ms "
            f"= {v['relative_to_simulation']:.2f} simulations"
        )

    fits = []
    for _ in range(2):
        t0 = time.perf_counter()
        res = fit_variator(rec)
        fits.append(
            {
                "wall_s": time.perf_counter() - t0,
                "iterations": res.iterations,
                "converged": res.converged,
                **{f"{k}_rel_err": res.estimates[k]["value"] / truth[k] - 1 for k in ("J1", "J2")},
                **{f"{k}_rel_std": res.estimates[k]["std"] / res.estimates[k]["value"] for k in ("J1", "J2")},
            }
        )
        C.log(f"fit_variator: {fits[-1]['wall_s']:.1f} s, {res.iterations} iterations")
    iterate_s = fits[1]["wall_s"]
    compile_s = fits[0]["wall_s"] - iterate_s
    # of which the Levenberg–Marquardt solve itself (the host loop the fits use: compiled above)
    # and, for comparison, the same iteration as one compiled lax.while_loop (for vmap batches):
    # its compile comes on top of value_and_jacobian's, which XLA compiles again inside the loop
    lm_calls = {"host": (solve_least_squares_host, (problem, theta0, obs))}
    loop_compile = lm_diff = None
    if not args.quick:
        loop_compile, loop_out = first_call(solve_least_squares, problem, theta0, obs)
        lm_calls["loop"] = (solve_least_squares, (problem, theta0, obs))
    lm_runs = interleaved(lm_calls, 5 if not args.quick else 2)
    lm, lm_loop = lm_runs["host"], lm_runs.get("loop")
    if not args.quick:
        host_out = solve_least_squares_host(problem, theta0, obs)
        lm_diff = float(np.max(np.abs(np.asarray(loop_out["theta"]) - np.asarray(host_out["theta"]))))
        C.log(
            f"Levenberg–Marquardt: host loop {lm:.2f} s; compiled loop {lm_loop:.2f} s "
            f"(its compile {loop_compile:.1f} s); max |Δθ| {lm_diff:.1e}"
        )

    cli = None
    if not args.quick:
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "fit.json")
            cli = C.fresh(f"JSON_PATH = {out!r}\n" + CLI)
            rep = json.load(open(out)) if cli["exit_code"] == 0 and os.path.exists(out) else None
        cli["iterations"] = None if rep is None else rep["iterations"]
        cli["elapsed_in_fit_s"] = None if rep is None else rep["elapsed_s"]
        C.log(f"jaxnh fit (fresh process): {cli['wall']:.1f} s, exit {cli['exit_code']}")

    res_all = {
        "problem": {"samples": int(rec.n), "residuals": int(obs.y.size), "unknowns": int(problem.size)},
        "evaluations": evals,
        "fit_in_process": {
            "first_call_s": fits[0]["wall_s"],
            "second_call_s": iterate_s,
            "lm_solve_s": lm,
            "lm_compiled_loop_s": lm_loop,
            "lm_compiled_loop_compile_s": loop_compile,
            "lm_compiled_loop_max_theta_diff": lm_diff,
            "compile_s": compile_s,
            "runs": fits,
            "per_iteration_s": iterate_s / max(fits[1]["iterations"], 1),
        },
        "cli_fresh_process": cli,
        "repeat": args.repeat,
        "quick": args.quick,
    }
    C.save("fit_cost", res_all, out_dir)
    m = C.machine()
    e = evals
    f0, f1 = fits
    lines = [
        "# Cost of `jaxnh fit` on the embedded record",
        "",
        C.stamp_line(C.command("fit_cost", argv)),
        "",
        f"The problem as `jaxnh fit` sets it up: {rec.n} samples × 2 channels = {obs.y.size} residuals, "
        f"{problem.size} unknowns, default solver settings (rtol 1e-8, atol 1e-10), no persistent compilation "
        f"cache (a first run). Medians of {args.repeat} interleaved rounds after the first (compiling) call; one "
        "process on one core, one run of the script.",
        "",
        "| evaluation at the starting guess | compile + first call | median | relative to one simulation | "
        "max rel. difference from the fit's Jacobian |",
        "|---|---|---|---|---|",
    ]
    label = {
        "simulation": "one simulation (residuals)",
        "jacobian_forward_sensitivity": "Jacobian (3002 × 12), as the fit does: `jacfwd` + `ForwardSensitivity`",
        "jacobian_diffrax_forward_mode": "Jacobian by `jacfwd` through `diffrax.ForwardMode`",
        "gradient_reverse_mode": "gradient of ½‖r‖² by reverse mode (`RecursiveCheckpointAdjoint`)",
    }
    for k, v in e.items():
        d = (
            "—"
            if k == "simulation"
            else ("(reference)" if k == "jacobian_forward_sensitivity" else f"{v['max_rel_diff']:.1e}")
        )
        lines.append(
            f"| {label[k]} | {v['compile_and_first_s']:.1f} s | {1e3 * v['median_s']:.2f} ms | "
            f"{v['relative_to_simulation']:.2f} | {d} |"
        )
    cli_row = (
        f"| `jaxnh fit --quiet --json …` in a fresh process, every core, empty cache (import + compile + iterate) | "
        f"{cli['wall']:.1f} s | {cli['iterations']} | exit code {cli['exit_code']} | |"
        if cli
        else "| `jaxnh fit` in a fresh process | not run (`--quick`) | | | |"
    )
    lines += [
        "",
        "The whole fit (`fit_variator(load_default())`, what `jaxnh fit` runs; Levenberg–Marquardt):",
        "",
        "| | wall time | iterations | J1 error (rel. std) | J2 error (rel. std) |",
        "|---|---|---|---|---|",
        f"| first call in a process (compile + iterate) | {f0['wall_s']:.1f} s | {f0['iterations']} | "
        f"{100 * f0['J1_rel_err']:+.3f} % ({100 * f0['J1_rel_std']:.3f} %) | "
        f"{100 * f0['J2_rel_err']:+.4f} % ({100 * f0['J2_rel_std']:.4f} %) |",
        f"| second call (iterate only) | {f1['wall_s']:.1f} s | {f1['iterations']} | "
        f"{100 * f1['J1_rel_err']:+.3f} % | {100 * f1['J2_rel_err']:+.4f} % |",
        cli_row,
        "",
        f"Compile ≈ first − second call = {compile_s:.1f} s; iterating = {iterate_s:.2f} s, of which the "
        f"Levenberg–Marquardt solve itself (`solve_least_squares_host`, residuals and Jacobian at every trial "
        f"point, the optimiser's linear algebra) takes {lm:.2f} s = {1e3 * lm / max(f1['iterations'], 1):.0f} ms "
        "per iteration; the rest is the starting guess, set-up, final statistics, the U21 band and Python "
        f"overhead. Machine: {m['cpu']}, {m['cores']} cores (this process on one); the machine may be shared, "
        "so times are upper bounds and ratios measured in the same run are the meaningful numbers.",
        "",
    ]
    if lm_loop is not None:
        lines.append(
            "The fit iterates from Python around the compiled `value_and_jacobian`. The same iteration as one "
            f"compiled `lax.while_loop` (`solve_least_squares`, for `jax.vmap` batches) took {loop_compile:.1f} s "
            f"more to compile in this process (value_and_jacobian's own compile: "
            f"{e['jacobian_forward_sensitivity']['compile_and_first_s']:.1f} s, above) and {lm_loop:.2f} s to run "
            f"against {lm:.2f} s; the two reach the same θ to {lm_diff:.1e}."
        )
    else:
        lines.append(
            "The compiled `lax.while_loop` form of the iteration (`solve_least_squares`): not run (`--quick`)."
        )
    path = out_dir / "FIT_COST.md"
    path.write_text("\n".join(lines) + "\n")
    C.log("\n".join(lines))
    C.log(f"wrote {path}")
    return res_all


if __name__ == "__main__":
    main()
