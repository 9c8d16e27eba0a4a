"""Small dense linear algebra written for the sizes of mechanisms (a few to a few tens).

The public names of `jaxnh._base.linalg`; see there for the implementation."""

from jaxnh._base.linalg import *  # noqa: F403 (the public names of one implementation module)


# written out, as type checkers need a literal list (its names come from the star import: hence
# F405 off); tests/test_layers.py checks it equals the implementation's
# ruff: noqa: F405
__all__ = [
    "UNROLL_MAX",
    "mm",
    "cholesky",
    "solve_lower",
    "solve_upper_t",
    "solve_spd",
    "pivot_rtol",
    "solve_psd_min_norm",
    "solve_square",
    "value_and_jacfwd",
    "pick",
]
