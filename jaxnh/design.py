"""Gradient-based design: optimise a loss of a simulation over parameters (`optimize`, `multistart`).

The public names of `jaxnh.identify.design`; see there for the implementation."""

from jaxnh.identify import design as _implementation
from jaxnh.identify.design import *  # noqa: F403 (the public names of one implementation module)


__all__ = _implementation.__all__
