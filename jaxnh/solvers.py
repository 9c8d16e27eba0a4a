"""Explicit Runge–Kutta solvers for diffrax with their stages unrolled (`DOP853`, `UnrolledTsit5`).

The public names of `jaxnh._solve.rk`; see there for the implementation."""

from jaxnh._solve.rk import *  # noqa: F403 (the public names of one implementation module)


# written out, as type checkers need a literal list (its names come from the star import: hence
# F405 off); tests/test_layers.py checks it equals the implementation's
# ruff: noqa: F405
__all__ = ["DOP853", "UnrolledTsit5"]
