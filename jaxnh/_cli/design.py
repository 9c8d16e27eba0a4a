"""`jaxnh design`: design the variator's identification experiment before measuring.

    jaxnh design [--out DIR] [--criterion A|D] [--of J1 ...] [--inputs M1 [M2]]
                 [--harmonics K] [--starts N] [--steps N] [--m1-max X] [--m2-max X]
                 [--normal-force N] [--mu-static MU] [--roller-radius R] [--lambda-max X]
                 [--energy-max E] [--power-max P] [--no-keep] [--seed S] [--quiet]

With the embedded record's set-up (6 s at 250 Hz, its two encoders, its
nominal values J1, J2, U21(t), phi1'(0) = 4 rad/s) it
chooses the motor and load torques M1(t), M2(t) — Fourier series of period =
the duration, bounded by |M1| ≤ --m1-max and |M2| ≤ --m2-max (default: the
record's largest |M1| and |M2|) — that
minimises the predicted variance of J1 (default `--criterion A --of J1`)
while the roller keeps rolling: the tangential force F = λ U21 / r it needs
stays inside the static friction cone |F| ≤ μs N (its stick margin
1 − |F|/(μs N) ≥ 0; λ is eq. (4)'s multiplier, N·m, and ρ = r / U21 the
contact radius), with the pressing force --normal-force N (default: the
smallest that keeps the embedded experiment rolling), --mu-static μs
(default 0.3) and --roller-radius r (default 0.05 m); or, with --lambda-max,
within a fixed |λ| bound instead. Unless --no-keep, J2 and every U21 knot
are predicted no less precise than with the record's own input. Writes into
DIR (default `jaxnh_design/`):

* `designed_input.csv` — columns t, M1, M2 (s, N·m) at the record's sample
  times, ready to drive a test rig;
* `design.json` — predicted standard errors for the baseline (the embedded
  record's input) and the designed input, their ratios, the limits and how
  the design was obtained;
* `design.png` — the inputs, the contact force and the predicted 95 %
  half-width of U21(t) for both.

Figures need matplotlib (the `plot` extra): without it the CSV and
the JSON are written, a note on stderr says that design.png is not drawn, and
the exit status is the design's.

The first run compiles the experiment's simulation, its sensitivities and the
design criterion's gradient, which takes minutes; progress lines on stderr
say so before each long compilation (`--quiet` leaves them out). The compiled
programs are kept in JAX's persistent compilation cache (`jaxnh._base.cache`),
so a later run with the same settings loads them instead.

Exit status:
    0    a design satisfying every limit was found (files written);
    1    none was: the best attempt is still written, marked infeasible (or the
         embedded experiment itself could not be simulated: nothing written);
    2    bad input or arguments (a message on stderr; nothing written);
    130  interrupted (Ctrl-C): each file is whole or absent.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._base.atomic import atomic_save_figure, atomic_write
from jaxnh._base.cache import enable_compilation_cache
from jaxnh._cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    plotting_available,
    probe_writable_dir,
    use_agg,
)
from jaxnh._model.profiles import Bounded, Fourier, Sampled
from jaxnh.identify._experiment import (
    design_loss,
    evaluate_design,
    LIMIT_KEYS,
    Limits,
    optimal_design,
    predict,
    StickLimit,
)
from jaxnh.identify.data import load_default
from jaxnh.identify.estimates import Z95
from jaxnh.models import variator as V
from jaxnh.models.variator_fit import embedded_truth, variator_experiment


__all__ = ["main", "build_parser"]

OUTPUTS = {"csv": "designed_input.csv", "json": "design.json", "figure": "design.png"}
DEFAULT_MU_STATIC = 0.3
"""`--mu-static` when not given. With the default `--normal-force` the limit does not depend on it."""
DEFAULT_ROLLER_RADIUS = 0.05
"""`--roller-radius` when not given, m. With the default `--normal-force` the limit does not depend on it or on μs."""

EPILOG = """\
exit status:
  0    a design within every limit was found (files written)
  1    none was: the best attempt is written, marked infeasible ("feasible": false
       in design.json); or the embedded experiment could not be simulated (nothing written)
  2    bad input or arguments (a message says what is wrong; nothing is written)
  130  interrupted (Ctrl-C; each file is whole or absent)
without matplotlib, designed_input.csv and design.json are written but not design.png
(a note on stderr says so); the exit status is the design's.
the first run compiles for minutes (progress lines on stderr say so; --quiet hides them);
compiled programs are cached in ~/.cache/jaxnh ($JAXNH_CACHE_DIR; JAXNH_CACHE_DIR=off disables).
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="jaxnh design",
        description="Design the motor (and load) torque of a variator identification experiment before "
        "measuring: minimise the predicted standard error of the named parameters (Fisher "
        "information from forward sensitivities) within the rig's torque, contact-force and "
        "energy limits. Default set-up: the embedded record's.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        default="jaxnh_design",
        metavar="DIR",
        help="folder for designed_input.csv, design.json, design.png (default jaxnh_design)",
    )
    p.add_argument(
        "--criterion",
        choices=("A", "D"),
        default="A",
        help="A: log of the summed relative variances of --of (default); D: log det of their covariance",
    )
    p.add_argument(
        "--of",
        nargs="+",
        default=["J1"],
        metavar="NAME",
        help="parameters whose precision to optimise: J1, J2, U21 (all knots) or U21[k] (default J1)",
    )
    p.add_argument(
        "--inputs",
        nargs="+",
        default=["M1", "M2"],
        choices=("M1", "M2"),
        help="torques to design (default both; one not designed keeps the record's)",
    )
    p.add_argument(
        "--harmonics",
        type=int,
        default=12,
        help="Fourier harmonics of each designed torque over the duration (default 12: up to 2 Hz)",
    )
    p.add_argument("--starts", type=int, default=3, help="optimisation starts; the best feasible is kept (default 3)")
    p.add_argument("--steps", type=int, default=400, help="Adam steps per start (default 400)")
    p.add_argument("--learning-rate", type=float, default=0.1, help="Adam step size (default 0.1)")
    p.add_argument(
        "--m1-max", type=float, default=None, help="bound on |M1|, N·m (default: the embedded record's largest |M1|)"
    )
    p.add_argument(
        "--m2-max",
        type=float,
        default=None,
        help="bound on |M2| when designed, N·m (default: the embedded record's largest |M2|)",
    )
    p.add_argument(
        "--normal-force",
        type=float,
        default=None,
        help="force pressing the roller, N: the design keeps the tangential force within μs N (default: the "
        "smallest N that keeps the embedded experiment rolling)",
    )
    p.add_argument("--mu-static", type=float, default=None, help="static friction coefficient μs (default 0.3)")
    p.add_argument("--roller-radius", type=float, default=None, help="roller radius r, m (default 0.05)")
    p.add_argument(
        "--lambda-max",
        type=float,
        default=None,
        help="instead of the friction cone, a fixed bound on |λ| (tangential force × contact radius), N·m",
    )
    p.add_argument(
        "--energy-max", type=float, default=None, help="energy the drives may deliver, J (default: no limit)"
    )
    p.add_argument("--power-max", type=float, default=None, help="peak drive power, W (default: no limit)")
    p.add_argument(
        "--no-keep",
        action="store_true",
        help="do not require J2 and the U21 knots to stay at least as precise as with the record's input",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the random starts (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress lines (notes and errors are still printed)")
    return p


def _check_args(a) -> None:
    for name in ("harmonics", "starts", "steps"):
        v = getattr(a, name)
        if v < 1:
            raise ValueError(f"--{name}: must be ≥ 1; got {v}")
    if a.harmonics > 40:
        raise ValueError(f"--harmonics: at most 40 (a 250 Hz record over 6 s); got {a.harmonics}")
    friction = [n for n in ("normal_force", "mu_static", "roller_radius") if getattr(a, n) is not None]
    if a.lambda_max is not None and friction:
        raise ValueError(
            f"--lambda-max replaces the friction cone; drop it or --{friction[0].replace('_', '-')} (choose one limit)"
        )
    for name in ("m1_max", "m2_max", "lambda_max", "energy_max", "power_max", "learning_rate", *friction):
        v = getattr(a, name)
        if v is not None and not (np.isfinite(v) and v > 0):
            raise ValueError(f"--{name.replace('_', '-')}: must be a finite number > 0; got {v}")
    for n in a.of:
        base = n.split("[")[0]
        if base not in ("J1", "J2", "U21"):
            raise ValueError(f"--of: {n!r} is not a parameter; use J1, J2, U21 or U21[k] (k = 0..6)")


def _check_out(path: str) -> dict:
    """Resolve the output paths and make sure they can be written, before any work."""
    out = os.path.abspath(path)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"--out: {path!r} exists and is not a folder")
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out: cannot create the folder {path!r}: {e.strerror}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"--out: the folder {path!r} is not writable")
    why = probe_writable_dir(out, "--out")
    if why:
        raise ValueError(why)
    files = {k: os.path.join(out, v) for k, v in OUTPUTS.items()}
    for f in files.values():
        if os.path.isdir(f):
            raise ValueError(f"--out: {f!r} is a folder; it must be free for an output file")
    return files


def _num(x):
    x = float(x)
    return x if np.isfinite(x) else None


def main(argv: list[str] | None = None) -> int:
    """`jaxnh design ...` (argv without "design"); returns the exit status (0, 1, 2 or 130)."""
    parser = build_parser()
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    except SystemExit as e:  # --help (0) or a usage error (2)
        return int(e.code or 0)
    try:
        _check_args(args)
        files = _check_out(args.out)
    except ValueError as e:
        print(f"jaxnh design: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    args.cache = enable_compilation_cache()  # the command line owns its process: compiled programs kept
    use_agg()
    if not plotting_available("design", f"{OUTPUTS['figure']} is not drawn"):
        files.pop("figure")
    try:
        return _run(args, files)
    except ValueError as e:
        print(f"jaxnh design: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("\njaxnh design: interrupted (files are whole or absent)", file=sys.stderr)
        return EXIT_INTERRUPTED


def _say(args, *msg):
    if not args.quiet:
        print(*msg, flush=True)


def _compiling(args, what: str, first: bool = False) -> None:
    """A progress line on stderr before a long compilation (not with --quiet)."""
    if args.quiet:
        return
    note = ""
    if first:
        cache = getattr(args, "cache", None)  # the folder main() turned the compilation cache on in
        kept = f"; the compiled programs are kept in {cache}, so a later run with the same settings loads them"
        note = f" (a first run spends minutes compiling{kept if cache else ''})"
    print(f"jaxnh design: compiling {what}{note}…", file=sys.stderr, flush=True)


def _run(args, files) -> int:

    started = time.perf_counter()
    record = load_default()
    truth = embedded_truth()
    t = record.t
    duration = float(t[-1] - t[0])
    m1_max = args.m1_max or float(np.max(np.abs(record.inputs["M1"])))
    m2_max = args.m2_max or float(np.max(np.abs(record.inputs["M2"])))
    _say(
        args,
        "jaxnh design — variator, embedded record's set-up: "
        f"{record.n} samples over {duration:.3g} s, encoders {truth['counts_per_rev']} counts/rev, "
        f"nominal J1 = {truth['J1']}, J2 = {truth['J2']} kg·m², U21 on {len(truth['U21_knots'])} knots",
    )
    _compiling(args, "the experiment's simulation and its sensitivities", first=True)
    exp, base_params = variator_experiment(record)
    _say(args, "  baseline (the record's torques): predicting standard errors …")
    base = predict(exp)
    if base.status != 0:
        print("jaxnh design: the baseline experiment cannot be simulated", file=sys.stderr)
        return EXIT_FAILED
    assert base.max_multiplier is not None  # the variator's Appell solve records its multiplier
    mu_s = args.mu_static or DEFAULT_MU_STATIC
    lever = V.ContactRadius(args.roller_radius or DEFAULT_ROLLER_RADIUS)
    base_sol = exp.simulate(base_params, adjoint=None)
    # the force the embedded experiment's roller needs, N: λ (N·m) over the contact radius ρ(t)
    base_force = float(
        np.max(
            np.abs(np.asarray(base_sol.multipliers)[:, 0])
            / np.asarray(jax.vmap(lambda t: lever(t, base_params))(base_sol.ts))
        )
    )
    normal = args.normal_force or base_force / mu_s
    lam_max = args.lambda_max
    stick = None if lam_max is not None else StickLimit(capacity=mu_s * normal, lever=lever)
    P = exp.n_params
    keep = None
    if not args.no_keep:
        rel = base.std[:P] / base.values[:P]  # θ units: relative for the (positive) parameters
        keep = {
            lab: float(r)
            for lab, r in zip(exp.labels[:P], rel)
            if lab.split("[")[0] not in args.of and lab not in args.of
        }
    limits = Limits(multiplier=lam_max, stick=stick, energy=args.energy_max, power=args.power_max, std=keep or None)
    if stick is not None:
        limit_text = f"|F| ≤ μs N = {mu_s:.3g} × {normal:.4g} N (roller r = {lever.radius:.3g} m)"
    else:
        limit_text = f"|λ| ≤ {lam_max:.4g} N·m"
    K = args.harmonics
    rng = np.random.default_rng(args.seed)

    def law(bound, mean):
        # start near the record's mean torque with small random harmonics (a constant law is a degenerate
        # start: see jaxnh.design); the other starts add Gaussian noise of 0.3 to every coefficient
        inner_mean = float(Bounded.inverse(np.clip(mean, -0.9 * bound, 0.9 * bound), -bound, bound))
        return Bounded(
            Fourier(inner_mean, cos=0.3 * rng.standard_normal(K), sin=0.3 * rng.standard_normal(K), period=duration),
            -bound,
            bound,
        )

    M1 = law(m1_max, np.mean(record.inputs["M1"])) if "M1" in args.inputs else base_params.M1
    M2 = law(m2_max, np.mean(record.inputs["M2"])) if "M2" in args.inputs else base_params.M2
    start = V.VariatorParams(base_params.J1, base_params.J2, base_params.U21, M1, M2)
    _say(
        args,
        f"  designing {', '.join(args.inputs)}: {args.criterion}-criterion on {', '.join(args.of)}; "
        f"|M1| ≤ {m1_max:.4g} N·m"
        + (f", |M2| ≤ {m2_max:.4g} N·m" if "M2" in args.inputs else "")
        + f", {limit_text}"
        + (", J2 and U21 knots no worse than the baseline" if keep else "")
        + f"; {args.starts} starts × {args.steps} Adam steps",
    )
    _compiling(args, "the design criterion and its gradient (the longest compilation)")
    res = optimal_design(
        exp,
        start,
        args.inputs,
        args.criterion,
        of=args.of,
        limits=limits,
        starts=args.starts,
        steps=args.steps,
        learning_rate=args.learning_rate,
        spread=0.3,
        seed=args.seed,
        progress=not args.quiet,
    )
    # what a fit will see: the designed torques sampled at the record's times (cubic spline between samples)
    tj = jnp.asarray(t)
    m1 = np.asarray(jax.vmap(res.params.M1)(tj))
    m2 = np.asarray(jax.vmap(res.params.M2)(tj))
    sampled = V.VariatorParams(base_params.J1, base_params.J2, base_params.U21, Sampled(t, m1), Sampled(t, m2))
    _compiling(args, "the check of the design with its torques as written to the CSV")
    des = predict(exp, sampled)
    assert des.max_multiplier is not None
    loss = design_loss(exp, args.criterion, of=args.of, limits=limits)

    check = evaluate_design(loss, sampled)
    feasible = check["status"] == 0 and all(check[k] <= 1.0 for k in LIMIT_KEYS if k in check)
    ratio = {lab: _num(b / d) for lab, b, d in zip(exp.labels, base.std, des.std)}
    ts_band = np.linspace(t[0], t[-1], 241)
    u_b, s_b = base.profile_band("U21", ts_band)
    u_d, s_d = des.profile_band("U21", ts_band)
    out = {
        "model": "variator",
        "setup": {
            "record": "embedded (jaxnh/data/variator_record.csv)",
            "samples": int(record.n),
            "duration_s": duration,
            "counts_per_rev": truth["counts_per_rev"],
            "jitter_std_rad": truth["jitter_std"],
            "noise_std_rad": {c: float(s) for c, s in zip(("phi1", "phi2"), np.asarray(exp.sigma))},
            "nominal": {
                "J1": truth["J1"],
                "J2": truth["J2"],
                "U21_knots": truth["U21_knots"],
                "U21_values": truth["U21_values"],
                "phi0": truth["phi0"],
                "w0": truth["w0"],
            },
            "unknowns": list(exp.labels),
        },
        "design": {
            "inputs": list(args.inputs),
            "criterion": args.criterion,
            "of": list(args.of),
            "law": f"Bounded(Fourier, {K} harmonics of period {duration:g} s)",
            "limits": {
                "M1_abs_max": m1_max,
                "M2_abs_max": m2_max if "M2" in args.inputs else None,
                "lambda_abs_max": lam_max,
                "friction": None
                if stick is None
                else {
                    "mu_static": mu_s,
                    "normal_force_N": normal,
                    "normal_force_source": "given"
                    if args.normal_force
                    else "smallest that keeps the embedded experiment rolling",
                    "roller_radius_m": lever.radius,
                    "limit": "|λ(t)| U21(t) / r ≤ μs N (stick margin ≥ 0)",
                },
                "energy_max": args.energy_max,
                "power_max": args.power_max,
                "keep_no_worse": sorted(keep) if keep else [],
            },
            "starts": [
                {
                    "value": _num(s["value"]),
                    "feasible": s["feasible"],
                    "violations": {k: _num(v) for k, v in s["violations"].items()},
                }
                for s in res.starts
            ],
            "best_start": res.best_start,
            "seed": args.seed,
            "steps": args.steps,
        },
        "check": {
            "feasible": bool(feasible),
            "max_abs_lambda": _num(des.max_multiplier[0]),
            "ratio_to_limits": {k: _num(check[k]) for k in LIMIT_KEYS if k in check},
            "stick_margin_min": None if stick is None else _num(1.0 - check["stick"]),
            "max_abs_M1": float(np.max(np.abs(m1))),
            "max_abs_M2": float(np.max(np.abs(m2))),
            "note": "predicted with the torques as written to the CSV (sampled, cubic spline between "
            "samples), as a fit of the measured record will see them",
        },
        "baseline": base.to_dict(),
        "designed": des.to_dict(),
        "std_ratio_baseline_over_designed": ratio,
        "U21_band": {
            "t": ts_band.tolist(),
            "baseline_half_width_95": (Z95 * s_b).tolist(),
            "designed_half_width_95": (Z95 * s_d).tolist(),
            "value": u_b.tolist(),
        },
        "units": {"J1": "kg m^2", "J2": "kg m^2", "U21": "1", "M1": "N m", "M2": "N m", "lambda": "N m", "t": "s"},
        "elapsed_s": time.perf_counter() - started,
    }
    header = (
        "# jaxnh design: designed input for the variator identification experiment (jaxnh design)\n"
        f"# t [s], M1 [N m] motor torque, M2 [N m] load torque; {record.n} samples over {duration:g} s; "
        f"feasible={bool(feasible)}\n"
    )

    # each file appears whole or not at all (jaxnh._base.atomic)
    with atomic_write(files["csv"], "w") as f:
        f.write(header + "t,M1,M2\n")
        for row in zip(t, m1, m2):
            f.write(",".join(f"{x:.10g}" for x in row) + "\n")
    text = json.dumps(out, indent=1, allow_nan=False)  # whole text first: a failure leaves no file
    with atomic_write(files["json"], "w") as f:
        f.write(text)
    if "figure" in files:
        _compiling(args, f"the simulations drawn in {OUTPUTS['figure']}")
        _figure(files["figure"], exp, base_params, sampled, base, des, ts_band, s_b, s_d, limits)
    _say(args, "")
    _say(args, _table(exp.labels, base, des))
    _say(
        args,
        (
            f"  contact: smallest stick margin {1.0 - float(check['stick']):.3g} (≥ 0: it keeps rolling); "
            if stick is not None
            else f"  contact force: max |λ| {out['check']['max_abs_lambda']:.4g} N·m (limit {lam_max:.4g}); "
        )
        + f"max |M1| {out['check']['max_abs_M1']:.4g} N·m (limit {m1_max:.4g}); "
        f"{'FEASIBLE' if feasible else 'NOT FEASIBLE'}",
    )
    if not feasible:
        print(f"jaxnh design: no design within the limits: {broken_limits(check, limit_text)}", file=sys.stderr)
    _say(args, f"  wrote {', '.join(files.values())} ({out['elapsed_s']:.0f} s)")
    return EXIT_OK if feasible else EXIT_FAILED


LIMIT_WORDS = {
    "multiplier": "the contact force |λ| ≤ --lambda-max",
    "stick": "the friction cone",
    "energy": "the energy the drives deliver ≤ --energy-max",
    "power": "the peak drive power ≤ --power-max",
    "std": "J2 and the U21 knots no less precise than with the record's input (--no-keep drops this limit)",
}
"""The limits of `evaluate_design` (`LIMIT_KEYS`) in words."""


def broken_limits(check: dict, limit_text: str) -> str:
    """The limits a checked design (`evaluate_design`'s dict) breaks, each with how far: its largest
    value as a multiple of the limit, and the percentage over. `limit_text`: the contact limit in words."""
    if check.get("status", 0) != 0:
        return f"the designed experiment cannot be simulated (status code {check['status']})"
    broken = [
        f"{LIMIT_WORDS[k]}{f' ({limit_text})' if k in ('stick', 'multiplier') else ''}: reaches "
        f"{check[k]:.4g} × the limit ({100 * (check[k] - 1):.3g} % over)"
        for k in LIMIT_KEYS
        if k in check and not check[k] <= 1.0
    ]
    return "; ".join(broken) or "no limit reported as exceeded"


def _table(labels, base, des) -> str:
    lines = [f"  {'parameter':<12}{'nominal':>11}{'std baseline':>14}{'std designed':>14}{'ratio':>8}"]
    for lab, v, b, d in zip(labels, base.values, base.std, des.std):
        lines.append(f"  {lab:<12}{v:>11.5g}{b:>14.3g}{d:>14.3g}{b / d:>8.2f}")
    return "\n".join(lines)


def _figure(path, exp, base_params, des_params, base, des, ts_band, s_b, s_d, limits: Limits):
    import matplotlib.pyplot as plt  # optional dependency (the plot extra); the backend: main() chose Agg

    t = np.asarray(exp.ts)
    tj = jnp.asarray(t)
    sol_b = exp.simulate(base_params, adjoint=None)
    sol_d = exp.simulate(des_params, adjoint=None)
    fig, ax = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for p, lab, st in ((base_params, "baseline (embedded record)", "--"), (des_params, "designed", "-")):
        ax[0].plot(t, np.asarray(jax.vmap(p.M1)(tj)), st, color="C0", label=f"M1 {lab}")
        ax[0].plot(t, np.asarray(jax.vmap(p.M2)(tj)), st, color="C1", label=f"M2 {lab}")
    ax[0].set_ylabel("torque, N·m")
    ax[0].legend(fontsize=8, ncol=2)
    ax[0].set_title("Inputs")
    ax[1].plot(t, np.asarray(sol_b.multipliers[:, 0]), "--", color="C2", label="λ baseline")
    ax[1].plot(t, np.asarray(sol_d.multipliers[:, 0]), "-", color="C2", label="λ designed")
    if limits.stick is not None:  # what friction holds, as a multiplier: ±μs N ρ(t) for each input's ratio law
        st = limits.stick
        for p, st_ in ((base_params, "--"), (des_params, "-")):
            lim = st.capacity * np.asarray(jax.vmap(lambda t: st.lever(t, p))(tj))
            ax[1].plot(t, lim, st_, color="k", lw=0.8)
            ax[1].plot(t, -lim, st_, color="k", lw=0.8)
        title = "Contact force (black: ±μs N ρ(t), what friction holds)"
    else:
        for s in (1, -1):
            ax[1].axhline(s * float(limits.multiplier or np.nan), color="k", lw=0.8, ls=":")
        title = f"Contact force (limit ±{float(limits.multiplier or np.nan):.3g} N·m dotted)"
    ax[1].set_ylabel("contact force × radius λ, N·m")
    ax[1].legend(fontsize=8)
    ax[1].set_title(title)
    ax[2].semilogy(ts_band, Z95 * s_b, "--", color="C3", label="baseline")
    ax[2].semilogy(ts_band, Z95 * s_d, "-", color="C3", label="designed")
    ax[2].set_ylabel("95 % half-width of U21(t)")
    ax[2].set_xlabel("t, s")
    ax[2].legend(fontsize=8)
    j1 = base.std[0] / des.std[0]
    ax[2].set_title(f"Predicted confidence band of U21 (SE(J1): baseline/designed = {j1:.2f})")
    fig.tight_layout()
    try:
        atomic_save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)
