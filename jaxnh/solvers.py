"""Explicit Runge–Kutta solvers for diffrax with their stages unrolled (`DOP853`, `UnrolledTsit5`).

The public names of `jaxnh._solve.rk`; see there for the implementation."""

from jaxnh._solve import rk as _implementation
from jaxnh._solve.rk import *  # noqa: F403 (the public names of one implementation module)


__all__: list[str] = []
__all__ += _implementation.__all__  # (this form, not `__all__ = ...`, is one that type checkers follow)
