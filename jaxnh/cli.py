"""The `jaxnh` command line: `jaxnh demo`, `jaxnh fit`."""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxnh", description="Mechanisms with nonholonomic constraints in JAX")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="the variator derived three ways, simulated, checked (and fitted)")
    demo.add_argument("--out", default="jaxnh_out", help="folder for the figures (default: jaxnh_out)")
    demo.add_argument("--no-fit", action="store_true", help="skip the parameter fit")
    from .identify.cli import add_fit_parser, run_fit

    add_fit_parser(sub)
    args = parser.parse_args(argv)
    if args.command == "demo":
        from .demo import run

        run(args.out, fit=not args.no_fit)
        return 0
    return run_fit(args)


if __name__ == "__main__":
    sys.exit(main())
