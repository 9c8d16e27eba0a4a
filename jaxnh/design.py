"""Gradient-based design: optimise a loss of a simulation over parameters (`optimize`, `multistart`).

The public names of `jaxnh.identify.design`; see there for the implementation."""

from jaxnh.identify import design as _implementation
from jaxnh.identify.design import *  # noqa: F403 (the public names of one implementation module)


__all__: list[str] = []
__all__ += _implementation.__all__  # (this form, not `__all__ = ...`, is one that type checkers follow)
