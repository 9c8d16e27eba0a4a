"""Small dense linear algebra written for the sizes of mechanisms (a few to a few tens).

The public names of `jaxnh._base.linalg`; see there for the implementation."""

from jaxnh._base import linalg as _implementation
from jaxnh._base.linalg import *  # noqa: F403 (the public names of one implementation module)


__all__: list[str] = []
__all__ += _implementation.__all__  # (this form, not `__all__ = ...`, is one that type checkers follow)
