"""Time profiles: laws of time (a ratio U21(t), a torque) as differentiable pytrees.

The public names of `jaxnh._model.profiles`; see there for the implementation."""

from jaxnh._model import profiles as _implementation
from jaxnh._model.profiles import *  # noqa: F403 (the public names of one implementation module)


__all__: list[str] = []
__all__ += _implementation.__all__  # (this form, not `__all__ = ...`, is one that type checkers follow)
