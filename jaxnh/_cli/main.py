"""The `jaxnh` command line: `jaxnh demo`, `jaxnh fit`, `jaxnh design`.

    jaxnh --version
    jaxnh demo [--out DIR] [--no-fit]
    jaxnh design [--out DIR] ...   (`jaxnh._cli.design`)
    jaxnh fit [DATA.csv] [--model variator | module:function] [--json OUT.json] [--out DIR] ...

`jaxnh fit --help` describes the fit's options, the CSV format and the
`--model module:function` contract (`jaxnh._cli.fit`); `jaxnh design --help`
the design's.

Exit status (every sub-command; each one's --help says what 0 and 1 mean for it):
    0    success (`demo`, `fit`: the fit is "fitted" — converged, every
         parameter determined, every number finite; `design`: a design within
         every limit was found);
    1    failed, results still written with a status saying why (`fit`: not
         converged, not identifiable, simulation failed or non-finite numbers;
         `design`: no design within the limits, the best attempt is written
         marked infeasible; `demo`: its fit did not end "fitted");
    2    bad input or arguments (a message on stderr, no traceback; nothing is written);
    130  interrupted (Ctrl-C).
A missing matplotlib never changes the exit status: the figures are left out
and a note on stderr says so (`jaxnh._cli.common`).

Output files are written whole or not at all (a temporary file in the same
folder, renamed when complete). Figures are drawn with matplotlib's Agg
backend, chosen here for the command line only (the library never changes
the backend). Compiled programs are kept in JAX's persistent compilation
cache (`jaxnh._base.cache`: `~/.cache/jaxnh`, `JAXNH_CACHE_DIR=off` disables it).
"""

from __future__ import annotations

import argparse
import sys
from importlib import metadata
from typing import Sequence

from jaxnh._base.atomic import check_writable_dir
from jaxnh._base.cache import enable_compilation_cache
from jaxnh._cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    occupied_outputs,
    plotting_available,
    probe_writable_dir,
    use_agg,
)
from jaxnh._cli.demo import run
from jaxnh._cli.design import main as design_main
from jaxnh._cli.fit import add_fit_parser, run_fit


EPILOG = """\
exit status (`jaxnh COMMAND --help` says what 0 and 1 mean for each command):
  0    success (demo, fit: the fit is "fitted"; design: a design within every limit found)
  1    failed, results still written with a status saying why (fit: not converged, not
       identifiable or not finite; design: no design within the limits; demo: its fit)
  2    bad input or arguments (a message says what is wrong; nothing is written)
  130  interrupted (Ctrl-C)
without matplotlib the results are written without figures (a note on stderr says so);
the exit status is the same.
compiled programs are cached in ~/.cache/jaxnh ($JAXNH_CACHE_DIR; JAXNH_CACHE_DIR=off disables).
"""

DEMO_OUTPUTS = ("variator_methods.png", "fit.json", "fit_data.png", "fit_ratio.png")
"""The files `jaxnh demo` writes into --out."""

DEMO_EPILOG = """\
exit status:
  0    done: the derivations and simulations ran and the fit (unless --no-fit) is "fitted"
  1    the fit did not end "fitted" (fit.json in --out says why)
  2    bad arguments, or --out cannot be written (a message says why; nothing is written)
  130  interrupted (Ctrl-C)
without matplotlib the demo runs and writes fit.json, without figures (a note on stderr
says so); the exit status is the same.
compiled programs are cached in ~/.cache/jaxnh ($JAXNH_CACHE_DIR; JAXNH_CACHE_DIR=off disables).
"""


def version() -> str:
    """The running jaxnh's version: its `__version__` (the installed metadata's if that is missing)."""
    # the package is always imported before its submodules; the command line may not import it by
    # name (tests/test_layers.py: layers import downwards only)
    found = getattr(sys.modules.get("jaxnh"), "__version__", None)
    if found:
        return str(found)
    try:
        return metadata.version("jaxnh")
    except metadata.PackageNotFoundError:
        return "unknown"


def main(argv: Sequence[str] | None = None) -> int:
    """Run `jaxnh` with `argv` (default: sys.argv[1:]); returns the exit status (0, 1, 2 or 130)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["design"]:  # its own parser, options and set-up (`jaxnh design --help`)
        return design_main(argv[1:])
    parser = argparse.ArgumentParser(
        prog="jaxnh",
        description="Mechanisms with nonholonomic constraints in JAX",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="the variator derived three ways, simulated, checked (and fitted)",
        description="The seed paper's friction variator: its equations derived three ways by automatic "
        "differentiation, integrated against the closed form, and fitted to the embedded record.",
        epilog=DEMO_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument("--out", default="jaxnh_out", help="folder for the figures and fit.json (default: jaxnh_out)")
    demo.add_argument("--no-fit", action="store_true", help="skip the parameter fit")
    sub.add_parser(
        "design",
        help="design the identification experiment (inputs) before measuring; `jaxnh design --help` for its options",
        add_help=False,
    )

    add_fit_parser(sub)
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version (0) or an argument error (2, message already printed)
        return int(e.code) if isinstance(e.code, int) else (EXIT_OK if e.code is None else EXIT_BAD_INPUT)

    enable_compilation_cache()  # the command line owns its process: compiled programs kept between runs
    use_agg()
    if args.command == "demo":
        return _demo(args)
    return run_fit(args)


def _demo(args) -> int:
    why = (
        check_writable_dir(args.out, "--out")
        or probe_writable_dir(args.out, "--out")
        or occupied_outputs(args.out, DEMO_OUTPUTS, "--out")
    )
    if why:
        print(f"jaxnh demo: {why}", file=sys.stderr)
        return EXIT_BAD_INPUT
    figures = plotting_available("demo", "no figures are drawn")
    try:
        report = run(args.out, fit=not args.no_fit, figures=figures)
    except KeyboardInterrupt:
        print("\njaxnh demo: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    fit = report.get("fit")
    if fit is not None and fit.get("status") != "fitted":
        print(f"jaxnh demo: the fit's status is {fit.get('status')!r} (exit status 1)", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def fit_main(argv=None) -> int:
    """`jaxnh fit ...` as a function: parse `argv` (without "fit") and run; returns the exit status."""
    return main(["fit", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
