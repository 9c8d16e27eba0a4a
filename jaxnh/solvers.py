"""Explicit Runge–Kutta solvers for diffrax with their stages unrolled (`DOP853`, `UnrolledTsit5`).

The public names of `jaxnh._solve.rk`; see there for the implementation."""

from jaxnh._solve.rk import (  # noqa: F401
    DOP853 as DOP853,
    UnrolledTsit5 as UnrolledTsit5,
)


__all__ = [
    "DOP853",
    "UnrolledTsit5",
]
