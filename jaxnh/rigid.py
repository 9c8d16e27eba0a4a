"""Rigid bodies and rolling wheels: kinetic energies and contact constraints built from poses.

The public names of `jaxnh._model.rigid`; see there for the implementation."""

from jaxnh._model import rigid as _implementation
from jaxnh._model.rigid import *  # noqa: F403 (the public names of one implementation module)


__all__: list[str] = []
__all__ += _implementation.__all__  # (this form, not `__all__ = ...`, is one that type checkers follow)
