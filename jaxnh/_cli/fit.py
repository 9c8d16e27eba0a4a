"""`jaxnh fit`: fit a mechanism's parameters to a measured record from the command line.

    jaxnh fit [DATA.csv] [--model variator | module:function | file.py:function]
              [--json OUT.json] [--out DIR] [--knots K] [--observe NAME ...] [--noise SIGMA ...]
              [--shooting S] [--max-iterations N] [--max-samples N] [--every K] [--quiet]

Without DATA.csv the embedded variator record is fitted. `--model variator`
(the default) fits J1, J2 and the ratio law U21(t) of the friction variator
(CSV columns t, phi1, phi2, M1, M2; s, rad, N·m). `--model module:function`
fits a user's own mechanism: the function returns a
`jaxnh.identify.spec.FitSpec` (mechanism, starting params, free and positive
parameter names, observed coordinates and input columns; see that module).

Checks made before any fitting: the output paths can be written (`--json`
in an existing, writable folder; `--out` creatable), the CSV is UTF-8 text
(a byte-order mark is fine) with the needed columns and plain numbers
(`1_000`, NaN, inf and values beyond the float range are refused), times
strictly increasing, at most `--max-samples` samples (keep every k-th with
`--every`), and the unknowns fewer than the measured values (`--knots` at
most the number of samples). Problems name the file's 1-based line number.

Outputs are written whole or not at all (a temporary file in the same
folder, then renamed). Every number in the JSON is finite or null; a null
comes with a "status" other than "fitted".

Figures (`--out`) need matplotlib (the `plot` extra). Without it
the fit runs and its JSON is written; a note on stderr says that no figures
are drawn, and the exit status is the fit's.

Exit status:
    0    fitted: converged, every parameter determined, every number finite;
    1    the fit failed: not converged, a parameter combination not determined
         by the data, the simulation failed or gave non-finite numbers (the
         JSON and figures are still written, with "status" saying why);
    2    bad input: a message on stderr says what is wrong and how to fix it;
         nothing is written;
    130  interrupted (Ctrl-C): nothing is written.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import warnings
from importlib import resources
from typing import Any

import numpy as np

from jaxnh._base.atomic import atomic_save_figure, atomic_write, check_writable_dir, check_writable_file
from jaxnh._base.dataframe import json_safe
from jaxnh._cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    occupied_outputs,
    plotting_available,
    probe_writable_dir,
)
from jaxnh._model.profiles import CubicSpline
from jaxnh.identify._fit import fit, RATE_WINDOW
from jaxnh.identify.data import load_default, MAX_SAMPLES, read_csv
from jaxnh.identify.estimates import Z95
from jaxnh.identify.parameters import Parametrisation
from jaxnh.identify.plots import plot_fit, plot_ratio
from jaxnh.identify.spec import _where_in_user_code, load_model, ModelError
from jaxnh.models.variator_fit import DEFAULT_KNOTS, fit_variator, report


__all__ = [
    "add_fit_parser",
    "run_fit",
    "demo_fit",
    "estimate_table",
    "MODELS",
    "EXIT_CODES",
    "MAX_KNOTS",
    "BadInput",
]

MODELS = ("variator",)
MAX_KNOTS = 200
MAX_ABS = 1e100  # larger values in a record are refused (their squares overflow)
EXIT_FITTED = EXIT_OK
EXIT_CODES = {
    EXIT_FITTED: "fitted",
    EXIT_FAILED: "the fit failed (results written with a failure status)",
    EXIT_BAD_INPUT: "bad input (nothing written)",
    EXIT_INTERRUPTED: "interrupted (nothing written)",
}
PROGRESS_BYTES = 8 << 20  # show reading progress for files larger than this

EPILOG = """\
exit status: 0 fitted (converged, all parameters determined, all numbers finite);
             1 the fit failed (not converged, not identifiable, simulation failed or
               non-finite; the JSON and figures are still written, "status" says why);
             2 bad input (a message says what is wrong; nothing is written);
             130 interrupted (Ctrl-C; nothing is written).
without matplotlib, --out gets no figures (a note on stderr says so); the JSON is
written and the exit status is the fit's.

--model module:function (or path/to/file.py:function) fits your own mechanism: the
function takes no arguments and returns a jaxnh.identify.spec.FitSpec(mechanism=,
params=, free=, positive=, observed=, inputs=) or a dict with those keys; params may
be a function of the Record (to put measured inputs in as jaxnh.profiles.Sampled).
The CSV then has columns t, the observed coordinates (the mechanism's names) and
the inputs. Row numbers in messages are 1-based line numbers of the file.
"""


class BadInput(ValueError):
    """Input the command refuses (exit status 2)."""


def _int_arg(lo, hi=None):
    def parse(s):
        s2 = s.strip()
        if "_" in s2 or not s2.isascii() or not s2.lstrip("+-").isdigit():
            raise argparse.ArgumentTypeError(f"{s!r} is not an integer")
        v = int(s2)
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(
                f"{v} is out of range: expected {lo} ≤ value" + (f" ≤ {hi}" if hi is not None else "")
            )
        return v

    return parse


def _positive_float(s):
    s2 = s.strip()
    try:
        if "_" in s2 or not s2.isascii():
            raise ValueError
        v = float(s2)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{s!r}: expected a finite number > 0")
    return v


def add_fit_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `fit` sub-command to an argparse `subparsers`; its handler is
    `args.func(args) -> int` (= `run_fit`)."""
    p = subparsers.add_parser(
        "fit",
        help="fit a mechanism's parameters to a measured record (default: the variator, embedded record)",
        description="Least-squares fit of a mechanism's parameters and initial state to measured coordinates, "
        "with standard errors, a lack-of-fit test and an identifiability report. Default model: the "
        "variator's inertias J1, J2 and ratio law U21(t) from encoder angles phi1, phi2 with applied "
        "torques M1, M2 (CSV columns t, phi1, phi2, M1, M2; s, rad, N·m).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "data",
        nargs="?",
        default=None,
        help="CSV file, UTF-8, comma-separated, header row (default: the embedded variator record)",
    )
    p.add_argument(
        "--model",
        default="variator",
        metavar="MODEL",
        help="'variator' (default), or module:function / file.py:function returning a FitSpec",
    )
    p.add_argument(
        "--json",
        default=None,
        metavar="OUT.json",
        help="write estimates, standard errors and status as JSON (the folder must exist)",
    )
    p.add_argument("--out", default=None, metavar="DIR", help="folder for the figures (created; default: none)")
    p.add_argument(
        "--knots",
        type=_int_arg(2, MAX_KNOTS),
        default=None,
        help=f"variator: number of U21 spline knots over the record (default 7; 2…{MAX_KNOTS}, "
        "at most the number of samples)",
    )
    p.add_argument(
        "--observe",
        nargs="+",
        default=None,
        metavar="CHANNEL",
        help="coordinates to fit (variator: phi1 and/or phi2; default: all the model observes)",
    )
    p.add_argument(
        "--noise",
        nargs="+",
        type=_positive_float,
        default=None,
        metavar="SIGMA",
        help="noise std per observed channel, units of the channel (default: estimated from the data)",
    )
    p.add_argument("--shooting", type=_int_arg(1, 1000), default=1, help="multiple-shooting segments (default 1)")
    p.add_argument(
        "--max-iterations",
        type=_int_arg(1, 100_000),
        default=100,
        help="Levenberg–Marquardt iteration limit (default 100)",
    )
    p.add_argument(
        "--max-samples",
        type=_int_arg(1),
        default=None,
        help="refuse records with more samples than this (default 200000)",
    )
    p.add_argument("--every", type=_int_arg(1), default=1, help="keep every k-th data row (default 1: all)")
    p.add_argument("--quiet", action="store_true", help="no per-iteration progress")
    p.set_defaults(func=run_fit)
    return p


FIT_FIGURES = ("fit_data.png", "fit_ratio.png")
"""The figures `jaxnh fit --out` draws."""


# --- checks before fitting ----------------------------------------------------------------------


def check_outputs(json_path, out_dir, data_path=None) -> None:
    """Raise BadInput when `--json` or `--out` cannot be written (before any fitting)."""
    if json_path is not None:
        why = check_writable_file(json_path, "--json")
        if why:
            raise BadInput(why)
        if (
            data_path is not None
            and os.path.exists(json_path)
            and os.path.exists(data_path)
            and os.path.samefile(json_path, data_path)
        ):
            raise BadInput(f"--json {json_path}: is the input file; choose another name")
        why = probe_writable_dir(os.path.dirname(os.path.abspath(json_path)), "--json")
        if why:
            raise BadInput(why)
    if out_dir is not None:
        why = (
            check_writable_dir(out_dir, "--out")
            or probe_writable_dir(out_dir, "--out")
            or occupied_outputs(out_dir, FIT_FIGURES, "--out")
        )
        if why:
            raise BadInput(why)


def _count_check(n_samples: int, n_channels: int, n_unknowns: int, what: str) -> None:
    if n_unknowns >= n_samples * n_channels:
        raise BadInput(
            f"{what}: {n_unknowns} unknowns but only {n_samples} samples × {n_channels} channel(s) = "
            f"{n_samples * n_channels} measured values; fewer unknowns than values are needed "
            "(use fewer knots or free parameters, or more samples)"
        )


def _magnitude_check(record, source) -> None:
    """Values so large that their squares overflow cannot be fitted in double precision."""
    for name, v in {"t": record.t, **record.channels, **record.inputs}.items():
        big = float(np.max(np.abs(v))) if v.size else 0.0
        if big > MAX_ABS:
            raise BadInput(
                f"{source}: column {name!r} has values up to {big:.3g} in magnitude; "
                f"beyond {MAX_ABS:.0e} squares and sums overflow in double precision — express the "
                "data in other units"
            )


def _shooting_check(n: int, shooting: int) -> None:
    if shooting > 1:
        length = math.ceil((n - 1) / shooting) + 1
        if length < 2 * RATE_WINDOW:
            raise BadInput(
                f"--shooting {shooting}: segments of {length} samples are too short for {n} samples; "
                f"use at most {max(1, (n - 1) // (2 * RATE_WINDOW))} segments"
            )


class _ProgressPrinter:
    """Reading progress on stderr, one line rewritten in place (for files above PROGRESS_BYTES)."""

    def __init__(self, path: str):
        self.path, self.open = path, False

    def __call__(self, done, total):
        if total:
            print(
                f"\r  reading {self.path}: {100 * done / total:3.0f} % ({done / 1e6:.0f} of {total / 1e6:.0f} MB)",
                end="",
                file=sys.stderr,
                flush=True,
            )
            self.open = True

    def close(self):
        if self.open:
            print(file=sys.stderr, flush=True)
            self.open = False


def _read(path, coordinates, inputs, args):
    try:
        size = os.path.getsize(path)
    except OSError:
        size = 0
    progress = _ProgressPrinter(path) if size > PROGRESS_BYTES else None
    try:
        return read_csv(
            path,
            coordinates=coordinates,
            inputs=inputs,
            max_samples=MAX_SAMPLES if args.max_samples is None else args.max_samples,
            every=args.every,
            progress=progress,
        )
    finally:
        if progress is not None:
            progress.close()


# --- the command --------------------------------------------------------------------------------


@dataclasses.dataclass
class _Plan:
    """What to fit, decided and checked before fitting."""

    kind: str  # "variator" or "model"
    record: Any
    source: str
    observe: tuple
    knots: int | None = None
    spec: Any = None
    params: Any = None


def _plan_variator(args):
    observe = tuple(args.observe) if args.observe else ("phi1", "phi2")
    bad = [c for c in observe if c not in ("phi1", "phi2")]
    if bad or len(set(observe)) != len(observe):
        raise BadInput(f"--observe: expected phi1 and/or phi2 (each once); got {list(observe)}")
    if args.data is None:
        record, source = load_default(), "embedded variator record (jaxnh/data/variator_record.csv)"
        if args.every > 1:
            record = record.every(args.every)
    else:
        record, source = _read(args.data, observe, ("M1", "M2"), args), args.data
    _magnitude_check(record, source)
    knots = DEFAULT_KNOTS if args.knots is None else args.knots
    if knots > record.n:
        raise BadInput(
            f"--knots {knots}: more knots than the {record.n} samples of the record; use at most "
            f"{min(record.n, MAX_KNOTS)} (the default is {DEFAULT_KNOTS})"
        )
    # unknowns: J1, J2, the knots, the observed initial angles and phi1'(0)
    _count_check(record.n, len(observe), 2 + knots + len(observe) + 1, f"--knots {knots}")
    _shooting_check(record.n, args.shooting)
    return _Plan(kind="variator", record=record, source=source, observe=observe, knots=knots, spec=None)


def _plan_model(args):
    if args.knots is not None:
        raise BadInput("--knots applies to --model variator only; a user's model sets its own profiles' knots")
    if args.data is None:
        raise BadInput(
            f"--model {args.model}: give the CSV file of measurements (the embedded record is the variator's)"
        )
    spec = load_model(args.model)
    observed = tuple(spec.observed or ())  # load_model filled it in (default: every coordinate)
    observe = tuple(args.observe) if args.observe else observed
    bad = [c for c in observe if c not in observed]
    if bad or len(set(observe)) != len(observe):
        raise BadInput(
            f"--observe: expected names among the model's observed coordinates {list(observed)} "
            f"(each once); got {list(observe)}"
        )
    record = _read(args.data, observe, tuple(spec.inputs), args)
    _magnitude_check(record, args.data)
    try:
        params = spec.params_for(record)
    except Exception as e:
        raise BadInput(
            f"--model {args.model}: FitSpec.params(record) raised {type(e).__name__}: {e}{_where_in_user_code(e)}"
        ) from None
    try:
        par = Parametrisation(params, spec.free, spec.positive)
    except (ValueError, TypeError) as e:
        raise BadInput(f"--model {args.model}: {e}") from None
    n_coords = len(spec.mechanism.names)
    _count_check(record.n, len(observe), par.size + len(observe) + n_coords, f"--model {args.model}")
    _shooting_check(record.n, args.shooting)
    return _Plan(kind="model", record=record, source=args.data, observe=observe, knots=None, spec=spec, params=params)


def run_fit(args) -> int:
    """Handler of `jaxnh fit`: check everything, fit, print the table, write JSON and figures.
    Returns the exit status (0 fitted, 1 the fit failed, 2 bad input)."""
    try:
        check_outputs(args.json, args.out, args.data)
        if args.noise is not None and args.observe is not None and len(args.noise) not in (1, len(args.observe)):
            raise BadInput(
                f"--noise: give 1 or {len(args.observe)} values (one per observed channel); got {len(args.noise)}"
            )
        plan = _plan_variator(args) if args.model == "variator" else _plan_model(args)
        if args.noise is not None and len(args.noise) not in (1, len(plan.observe)):
            raise BadInput(
                f"--noise: give 1 or {len(plan.observe)} values (one per observed channel "
                f"{', '.join(plan.observe)}); got {len(args.noise)}"
            )
    except (BadInput, ModelError, ValueError) as e:
        return _bad(e)
    except OSError as e:
        return _bad(f"{e.filename or args.data}: {e.strerror or e}")
    figures_dir = args.out
    if figures_dir is not None and not plotting_available("fit", f"no figures are drawn into --out {figures_dir}"):
        figures_dir = None
    noise = (
        None
        if args.noise is None
        else dict(zip(plan.observe, np.broadcast_to(args.noise, (len(plan.observe),)).tolist()))
    )
    record = plan.record
    print(f"jaxnh fit — model {args.model}, data: {plan.source}")
    desc = f"U21 spline with {plan.knots} knots" if plan.kind == "variator" else f"free {', '.join(plan.spec.free)}"
    print(
        f"  {record.n} samples over {record.t[-1] - record.t[0]:.3g} s, channels {', '.join(plan.observe)}, "
        f"inputs {', '.join(record.inputs) or 'none'}; {desc}",
        flush=True,
    )
    try:
        with warnings.catch_warnings(record=True):  # the table below says the same in context
            warnings.simplefilter("always")
            result = _fit(plan, args, noise)
    except (BadInput, ModelError) as e:
        return _bad(e)
    except ValueError as e:
        if not isinstance(e, (np.linalg.LinAlgError, FloatingPointError)):  # numerical breakdown: the fit failed
            return _bad(e)  # an argument check inside fit: still bad input
        return _failed(e, args, plan)
    except KeyboardInterrupt:
        print("\njaxnh fit: interrupted; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:  # the solver or optimiser broke down: the fit failed
        return _failed(e, args, plan)
    truth = None
    try:
        rep = _print_and_write(
            result, plan.source, args.json, figures_dir, record, truth, model=args.model, kind=plan.kind
        )
    except OSError as e:
        print(f"jaxnh fit: writing the results failed: {e}", file=sys.stderr)
        return EXIT_FAILED
    if rep["status"] != "fitted":
        print(f"  status: {rep['status']} — exit status 1 (the fit failed)")
    return EXIT_FITTED if rep["status"] == "fitted" else EXIT_FAILED


def _failed(e, args, plan) -> int:
    """The fit raised: say so in one line (JAXNH_DEBUG=1 re-raises), write a JSON saying so, exit 1."""
    if os.environ.get("JAXNH_DEBUG"):
        raise e
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    msg = f"{type(e).__name__}: {first}"
    print(f"jaxnh fit: the fit failed: {msg} (JAXNH_DEBUG=1 shows the traceback)", file=sys.stderr)
    rep = {
        "status": "error",
        "ok": False,
        "message": f"the fit failed: {msg}",
        "model": args.model,
        "data": plan.source,
    }
    try:
        _write_json(rep, args.json)
    except OSError as e2:
        print(f"jaxnh fit: could not write {args.json}: {e2}", file=sys.stderr)
    return EXIT_FAILED


def _bad(e) -> int:
    msg = str(e)
    print(f"jaxnh fit: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _fit(plan, args, noise):
    if plan.kind == "variator":
        return fit_variator(
            plan.record,
            knots=plan.knots,
            observe=plan.observe,
            noise=noise,
            shooting=args.shooting,
            max_iterations=args.max_iterations,
            progress=not args.quiet,
        )

    spec = plan.spec
    kw = dict(spec.options)
    if noise is not None:
        kw["noise"] = noise
    kw.update(shooting=args.shooting, max_iterations=args.max_iterations, progress=not args.quiet)
    if spec.q0 is not None:
        kw.setdefault("q0", spec.q0)
    if spec.qd0 is not None:
        kw.setdefault("qd0", spec.qd0)
    return fit(
        spec.mechanism, plan.params, plan.record, free=spec.free, positive=spec.positive, observe=plan.observe, **kw
    )


def _write_json(rep, path) -> None:
    """Write `rep` as JSON at `path` in one piece (non-finite numbers as null)."""
    if not path:
        return

    text = json.dumps(json_safe(rep), indent=1, allow_nan=False)  # whole text first: no partial file
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text + "\n")


def _figures(result, record, truth, kind):
    """(file name, Figure) pairs; the figures are closed by the caller."""
    if kind == "variator":
        figs = [
            (
                "fit_data.png",
                plot_fit(
                    result,
                    record,
                    ylabel="angle [rad]",
                    input_label="torque [N·m]",
                    title="encoder angles: measured (dots) and fitted simulation (lines)",
                ),
            )
        ]
    else:
        figs = [("fit_data.png", plot_fit(result, record))]
    if kind == "variator":
        tr = None
        if truth is not None:
            tr = CubicSpline(truth["U21_knots"], truth["U21_values"])
        figs.append(("fit_ratio.png", plot_ratio(result, truth=tr)))
    return figs


def _print_and_write(result, source, json_path, out_dir, record, truth=None, model="variator", kind="variator"):
    print()
    print(estimate_table(result, truth))
    if kind == "variator":
        rep = report(result, source=source)
    else:
        rep = json_safe({**result.to_dict(), "data": source})
    rep["model"] = model
    if out_dir:
        import matplotlib.pyplot as plt

        os.makedirs(out_dir, exist_ok=True)
        paths = []
        for name, fig in _figures(result, record, truth, kind):
            try:
                paths.append(atomic_save_figure(fig, os.path.join(out_dir, name), dpi=110))
            finally:
                plt.close(fig)
        rep["figures"] = paths
        print(f"  figures: {', '.join(paths)}")
    if json_path:
        _write_json(rep, json_path)
        print(f"  JSON: {json_path}")
    return rep


def estimate_table(result, truth=None) -> str:
    """The estimates ± standard errors with 95 % intervals (and the truth, when known), any mechanism:
    `FitResult.summary`, with the variator's units (kg·m², residuals in mrad)."""
    if set(result.problem.par.names) == {"J1", "J2", "U21"}:  # the variator: encoder angles in rad, shown in mrad
        return result.summary(truth, units={"J1": " kg·m²", "J2": " kg·m²"}, residual_unit=(1e3, " mrad"))
    return result.summary(truth)


def _truth():
    text = resources.files("jaxnh").joinpath("data", "variator_truth.json").read_text()
    return json.loads(text)


def demo_fit(out_dir: str = "jaxnh_out", figures: bool = True) -> dict:
    """The demo's last part: fit the embedded record, print progress and the
    table of estimates ± standard errors next to the true values, write
    `fit.json` (and, with `figures`, `fit_data.png` and `fit_ratio.png`) into
    `out_dir`; return the report dict (see `jaxnh.models.variator_fit.report`)
    with "truth_inside_95" added."""
    record = load_default()
    truth = _truth()
    print("\n5. Parameter identification on the embedded record (jaxnh fit)")
    print(
        f"   {record.n} samples over {record.t[-1]:.3g} s at {1 / np.median(np.diff(record.t)):.0f} Hz: "
        "two quantised encoders, motor and load torque, U21 changing from "
        f"{truth['U21_values'][0]} to {truth['U21_values'][-1]}"
    )
    print(
        "   unknowns: J1, J2, U21 at 7 knots, phi1(0), phi2(0), phi1'(0); Levenberg–Marquardt, "
        "Jacobian from forward sensitivities integrated with the solve (first call compiles)"
    )
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        result = fit_variator(record, progress=True)
    os.makedirs(out_dir, exist_ok=True)
    rep = _print_and_write(
        result, "embedded", os.path.join(out_dir, "fit.json"), out_dir if figures else None, record, truth
    )
    inside = {
        k: bool(abs(truth[k] - result.estimates[k]["value"]) <= Z95 * result.estimates[k]["std"]) for k in ("J1", "J2")
    }
    v, s = np.asarray(result.estimates["U21"]["value"]), np.asarray(result.estimates["U21"]["std"])
    inside["U21_knots"] = bool(np.all(np.abs(np.asarray(truth["U21_values"]) - v) <= Z95 * s))
    rep["truth_inside_95"] = inside
    print(
        f"   true values inside the 95 % intervals: J1 {inside['J1']}, J2 {inside['J2']}, "
        f"all U21 knots {inside['U21_knots']}"
    )
    return rep
