"""The `jaxnh` command line: `jaxnh demo`, `jaxnh fit`."""

from __future__ import annotations

import argparse
import os
import sys


def use_compilation_cache() -> str | None:
    """Keep compiled XLA programs on disk between runs of the command line.

    The first `jaxnh fit` or `jaxnh demo` in a fresh process spends most of its
    time tracing and compiling (benchmarks/FIT_COST.md); JAX's persistent
    compilation cache lets later runs load the compiled programs instead (measured:
    `jaxnh fit` on the embedded record 24.6 s, then 20.2 s with a warm cache; the
    rest is Python tracing, which no cache saves). Folder: `$JAXNH_CACHE_DIR`, else
    `$XDG_CACHE_HOME/jaxnh` or `~/.cache/jaxnh`; `JAXNH_CACHE_DIR=off` disables
    it. Only the command line turns it on: importing the library changes no
    cache setting. Returns the folder, or None when disabled or unusable.
    """
    path = os.environ.get("JAXNH_CACHE_DIR")
    if path is not None and path.strip().lower() in ("", "0", "off", "none"):
        return None
    if path is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        path = os.path.join(base, "jaxnh")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxnh", description="Mechanisms with nonholonomic constraints in JAX")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="the variator derived three ways, simulated, checked (and fitted)")
    demo.add_argument("--out", default="jaxnh_out", help="folder for the figures (default: jaxnh_out)")
    demo.add_argument("--no-fit", action="store_true", help="skip the parameter fit")
    from .identify.cli import add_fit_parser, run_fit

    add_fit_parser(sub)
    args = parser.parse_args(argv)
    use_compilation_cache()
    if args.command == "demo":
        from .demo import run

        run(args.out, fit=not args.no_fit)
        return 0
    return run_fit(args)


if __name__ == "__main__":
    sys.exit(main())
