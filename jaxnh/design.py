"""Gradient-based design: optimise a loss of a simulation over parameters (`optimize`, `multistart`).

The public names of `jaxnh.identify.design`; see there for the implementation."""

from jaxnh.identify.design import *  # noqa: F403 (the public names of one implementation module)


# written out, as type checkers need a literal list (its names come from the star import: hence
# F405 off); tests/test_layers.py checks it equals the implementation's
# ruff: noqa: F405
__all__ = ["Chebyshev", "Bounded", "optimize", "multistart", "fd_gradient"]
