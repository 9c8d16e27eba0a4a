"""Formulations of the equations of motion: `Lagrange`, `Appell`, `Substituted`.

The public names of `jaxnh._equations`; see there for the implementation."""

from jaxnh import _equations as _implementation
from jaxnh._equations import *  # noqa: F403 (the public names of one implementation module)


__all__: list[str] = []
__all__ += _implementation.__all__  # (this form, not `__all__ = ...`, is one that type checkers follow)
