"""The `jaxnh` command line: `jaxnh demo`, `jaxnh fit`, `jaxnh design`.

    jaxnh demo [--out DIR] [--no-fit]
    jaxnh design [--out DIR] ...   (`jaxnh._cli.design`)
    jaxnh fit [DATA.csv] [--model variator | module:function] [--json OUT.json] [--out DIR] ...

`jaxnh fit --help` describes the fit's options, the CSV format and the
`--model module:function` contract (`jaxnh._cli.fit`).

Exit status (both commands):
    0  success (`fit`: fitted — converged, every parameter determined, every
       number finite);
    1  the fit failed (not converged, not identifiable, simulation failed or
       non-finite numbers; results are still written with a "status" saying why);
    2  bad input or arguments (a message on stderr, no traceback; nothing is written).

Output files are written whole or not at all (a temporary file in the same
folder, renamed when complete). Figures are drawn with matplotlib's Agg
backend, chosen here for the command line only (the library never changes
the backend). Compiled programs are kept in JAX's persistent compilation
cache (`jaxnh._base.cache`: `~/.cache/jaxnh`, `JAXNH_CACHE_DIR=off` disables it).
"""

from __future__ import annotations

import argparse
import os
import sys

from jaxnh._base.atomic import check_writable_dir
from jaxnh._base.cache import enable_compilation_cache
from jaxnh._cli.demo import run
from jaxnh._cli.design import main as design_main
from jaxnh._cli.fit import add_fit_parser, run_fit


EPILOG = """\
exit status: 0 success (fit: fitted); 1 the fit failed (results written with a failure
status); 2 bad input (a message says what is wrong; nothing written).
compiled programs are cached in ~/.cache/jaxnh ($JAXNH_CACHE_DIR; JAXNH_CACHE_DIR=off disables).
"""


def _use_agg() -> None:
    """Figures of the command line go to files: the Agg backend, unless pyplot is already in use."""
    if "matplotlib.pyplot" in sys.modules:
        return
    if "matplotlib" in sys.modules:
        sys.modules["matplotlib"].use("Agg")
    else:  # read by matplotlib when (if) it is imported: a run that draws nothing does not import it (0.2 s)
        os.environ["MPLBACKEND"] = "Agg"


def main(argv=None) -> int:
    """Run `jaxnh` with `argv` (default: sys.argv[1:]); returns the exit status (0, 1 or 2)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["design"]:  # its own parser and options (`jaxnh design --help`)
        _use_agg()
        return design_main(argv[1:])
    parser = argparse.ArgumentParser(
        prog="jaxnh",
        description="Mechanisms with nonholonomic constraints in JAX",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="the variator derived three ways, simulated, checked (and fitted)",
        epilog=EPILOG,
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
    except SystemExit as e:  # --help (0) or an argument error (2, message already printed)
        return int(e.code) if isinstance(e.code, int) else (0 if e.code is None else 2)

    enable_compilation_cache()  # the command line owns its process: compiled programs kept between runs
    _use_agg()
    if args.command == "demo":
        return _demo(args)
    return run_fit(args)


def _demo(args) -> int:
    why = check_writable_dir(args.out, "--out")
    if why:
        print(f"jaxnh demo: {why}", file=sys.stderr)
        return 2
    try:
        import matplotlib  # noqa: F401

        figures = True
    except ImportError:
        figures = False
        print(
            "jaxnh demo: matplotlib is not installed: no figures (pip install matplotlib, or jaxnh[plot])",
            file=sys.stderr,
        )

    try:
        report = run(args.out, fit=not args.no_fit, figures=figures)
    except KeyboardInterrupt:
        print("\njaxnh demo: interrupted", file=sys.stderr)
        return 130
    fit = report.get("fit")
    if fit is not None and fit.get("status") != "fitted":
        print(f"jaxnh demo: the fit's status is {fit.get('status')!r} (exit status 1)", file=sys.stderr)
        return 1
    return 0


def fit_main(argv=None) -> int:
    """`jaxnh fit ...` as a function: parse `argv` (without "fit") and run; returns the exit status."""
    return main(["fit", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
