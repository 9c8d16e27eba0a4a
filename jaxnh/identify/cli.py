"""`jaxnh fit`: fit the variator to a measured record from the command line.

    jaxnh fit [DATA.csv] --model variator --json OUT.json [--out DIR] [--knots K]
              [--observe phi1 [phi2]] [--noise S1 [S2]] [--shooting S] [--max-iterations N] [--quiet]

Without DATA.csv the embedded record is fitted. Exit status: 0 when the fit
converged and every parameter is identifiable, 3 when it did not converge or
some combination is not determined (the results are still written), 2 on
bad input (a message says what is wrong).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from importlib import resources

import numpy as np

__all__ = ["add_fit_parser", "run_fit", "fit_main", "demo_fit", "MODELS"]

MODELS = ("variator",)
Z95 = 1.959963984540054


def add_fit_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `fit` sub-command to an argparse `subparsers`; its handler is
    `args.func(args) -> int` (= `run_fit`)."""
    p = subparsers.add_parser(
        "fit", help="fit J1, J2 and U21(t) to a measured record (default: the embedded one)",
        description="Least-squares fit of the variator's inertias J1, J2 and ratio law U21(t) to encoder angles "
                    "phi1, phi2 with applied torques M1, M2 (CSV columns t, phi1, phi2, M1, M2; s, rad, N·m).")
    p.add_argument("data", nargs="?", default=None, help="CSV file (default: the embedded variator record)")
    p.add_argument("--model", default="variator", choices=MODELS, help="model to fit (default: variator)")
    p.add_argument("--json", default=None, metavar="OUT.json", help="write estimates and standard errors as JSON")
    p.add_argument("--out", default=None, metavar="DIR", help="folder for the figures (default: none written)")
    p.add_argument("--knots", type=int, default=None, help="number of U21 spline knots over the record (default 7)")
    p.add_argument("--observe", nargs="+", default=None, metavar="CHANNEL",
                   help="channels to fit: phi1 and/or phi2 (default: both)")
    p.add_argument("--noise", nargs="+", type=float, default=None, metavar="SIGMA",
                   help="encoder noise std per observed channel, rad (default: estimated from the data)")
    p.add_argument("--shooting", type=int, default=1, help="multiple-shooting segments (default 1)")
    p.add_argument("--max-iterations", type=int, default=100, help="Levenberg–Marquardt iteration limit")
    p.add_argument("--quiet", action="store_true", help="no per-iteration progress")
    p.set_defaults(func=run_fit)
    return p


def fit_main(argv=None) -> int:
    """`jaxnh fit ...` as a function: parse `argv` (without "fit") and run."""
    parser = argparse.ArgumentParser(prog="jaxnh")
    sub = parser.add_subparsers(dest="command", required=True)
    add_fit_parser(sub)
    args = parser.parse_args(["fit", *(sys.argv[1:] if argv is None else argv)])
    return run_fit(args)


def run_fit(args) -> int:
    """Handler of `jaxnh fit`: read, fit, print the table, write JSON and figures."""
    from .data import load_default, read_csv
    from .variator import DEFAULT_KNOTS, fit_variator

    observe = tuple(args.observe) if args.observe else ("phi1", "phi2")
    try:
        bad = [c for c in observe if c not in ("phi1", "phi2")]
        if bad:
            raise ValueError(f"--observe: unknown channel(s) {bad}; expected phi1 and/or phi2")
        if args.data is None:
            record, source = load_default(), "embedded variator record (jaxnh/data/variator_record.csv)"
        else:
            record, source = read_csv(args.data, coordinates=observe), args.data
        noise = None
        if args.noise is not None:
            if len(args.noise) not in (1, len(observe)):
                raise ValueError(f"--noise: give 1 or {len(observe)} values (one per observed channel); got {len(args.noise)}")
            noise = dict(zip(observe, np.broadcast_to(args.noise, (len(observe),)).tolist()))
        knots = DEFAULT_KNOTS if args.knots is None else args.knots
    except (ValueError, OSError) as e:
        print(f"jaxnh fit: {e}", file=sys.stderr)
        return 2
    print(f"jaxnh fit — model {args.model}, data: {source}")
    print(f"  {record.n} samples over {record.t[-1] - record.t[0]:.3g} s, channels {', '.join(observe)}, "
          f"inputs {', '.join(record.inputs) or 'none'}; U21 spline with {knots} knots")
    try:
        result = fit_variator(record, knots=knots, observe=observe, noise=noise, shooting=args.shooting,
                              max_iterations=args.max_iterations, progress=not args.quiet)
    except ValueError as e:
        print(f"jaxnh fit: {e}", file=sys.stderr)
        return 2
    rep = _print_and_write(result, source, args.json, args.out, record)
    return 0 if rep["converged"] and rep["identifiable"] else 3


def _print_and_write(result, source, json_path, out_dir, record, truth=None):
    from .plots import plot_fit, plot_ratio
    from .variator import report

    print()
    print(estimate_table(result, truth))
    rep = report(result, source=source)
    if json_path:
        d = os.path.dirname(os.path.abspath(json_path))
        os.makedirs(d, exist_ok=True)
        with open(json_path, "w") as f:
            json.dump(rep, f, indent=1, allow_nan=False)
        print(f"  JSON: {json_path}")
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
        p1 = plot_fit(result, os.path.join(out_dir, "fit_data.png"), record)
        tr = None
        if truth is not None:
            from ..profiles import CubicSpline

            tr = CubicSpline(truth["U21_knots"], truth["U21_values"])
        p2 = plot_ratio(result, os.path.join(out_dir, "fit_ratio.png"), truth=tr)
        rep["figures"] = [p1, p2]
        print(f"  figures: {p1}, {p2}")
    return rep


def estimate_table(result, truth=None) -> str:
    """The estimates ± standard errors with 95 % intervals (and the truth, when known)."""
    est = result.estimates
    head = f"  {'parameter':<12}{'estimate':>13}{'± std error':>13}{'rel.':>9}   {'95 % interval':<27}"
    if truth is not None:
        head += f"{'true':>10}  inside"
    lines = [head]

    def row(name, v, s, true=None):
        rel = f"{s / abs(v):8.3%}" if np.isfinite(s) and v != 0 else "     n/a"
        ci = f"[{v - Z95 * s:.6g}, {v + Z95 * s:.6g}]" if np.isfinite(s) else "undetermined"
        line = f"  {name:<12}{v:>13.6g}{s:>13.3g}{rel:>9}   {ci:<27}"
        if true is not None:
            inside = abs(true - v) <= Z95 * s
            line += f"{true:>10.6g}  {'yes' if inside else 'NO'}"
        return line

    units = {"J1": " kg·m²", "J2": " kg·m²"}
    for k in ("J1", "J2"):
        lines.append(row(k + units[k], est[k]["value"], est[k]["std"], None if truth is None else truth[k]))
    knots = np.asarray(result.params.U21.knots)
    for i, (v, s) in enumerate(zip(np.asarray(est["U21"]["value"]), np.asarray(est["U21"]["std"]))):
        true = None if truth is None else truth["U21_values"][i]
        lines.append(row(f"U21({knots[i]:.3g} s)", v, s, true))
    for k, e in est.items():
        if k not in ("J1", "J2", "U21"):
            lines.append(row(k, e["value"], e["std"]))
    lines.append(f"  rms residual {1e3 * result.rms_residual:.4f} mrad ("
                 + ", ".join(f"{c} {1e3 * v:.4f}" for c, v in result.rms_by_channel.items())
                 + "); noise σ " + ", ".join(f"{c} {1e3 * v:.4f}" for c, v in result.noise.items())
                 + f" mrad; s² = {result.chi2_dof:.3f}")
    lines.append("  " + result.lack_of_fit.message)
    lines.append(f"  {result.iterations} iterations, {'converged' if result.converged else 'NOT CONVERGED'}: "
                 f"{result.message}; {result.elapsed:.1f} s")
    if result.identifiability.messages:
        lines += ["  " + m for m in result.identifiability.messages]
    else:
        lines.append(f"  all parameters identifiable (condition number of the scaled Jacobian "
                     f"{result.identifiability.condition:.3g})")
    return "\n".join(lines)


def _truth():
    text = resources.files("jaxnh").joinpath("data", "variator_truth.json").read_text()
    return json.loads(text)


def demo_fit(out_dir: str = "jaxnh_out") -> dict:
    """The demo's last part: fit the embedded record, print progress and the
    table of estimates ± standard errors next to the true values, write
    `fit_data.png` and `fit_ratio.png` into `out_dir`; return the report dict
    (see `jaxnh.identify.variator.report`) with "truth_inside_95" added."""
    from .data import load_default
    from .variator import fit_variator

    record = load_default()
    truth = _truth()
    print("\n4. Parameter identification on the embedded record (jaxnh fit)")
    print(f"   {record.n} samples over {record.t[-1]:.3g} s at {1 / np.median(np.diff(record.t)):.0f} Hz: "
          "two quantised encoders, motor and load torque, U21 changing from "
          f"{truth['U21_values'][0]} to {truth['U21_values'][-1]}")
    print("   unknowns: J1, J2, U21 at 7 knots, phi1(0), phi2(0), phi1'(0); Levenberg–Marquardt, "
          "Jacobian from forward sensitivities integrated with the solve (first call compiles)")
    result = fit_variator(record, progress=True)
    os.makedirs(out_dir, exist_ok=True)
    rep = _print_and_write(result, "embedded", os.path.join(out_dir, "fit.json"), out_dir, record, truth)
    inside = {k: bool(abs(truth[k] - result.estimates[k]["value"]) <= Z95 * result.estimates[k]["std"])
              for k in ("J1", "J2")}
    v, s = np.asarray(result.estimates["U21"]["value"]), np.asarray(result.estimates["U21"]["std"])
    inside["U21_knots"] = bool(np.all(np.abs(np.asarray(truth["U21_values"]) - v) <= Z95 * s))
    rep["truth_inside_95"] = inside
    print(f"   true values inside the 95 % intervals: J1 {inside['J1']}, J2 {inside['J2']}, "
          f"all U21 knots {inside['U21_knots']}")
    return rep
