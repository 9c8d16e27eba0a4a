"""Gradient-based design: optimise a loss of a simulation over parameters (`optimize`, `multistart`).

The public names of `jaxnh.identify.design`; see there for the implementation."""

from jaxnh.identify.design import (  # noqa: F401
    Bounded as Bounded,
    Chebyshev as Chebyshev,
    fd_gradient as fd_gradient,
    multistart as multistart,
    optimize as optimize,
)


__all__ = [
    "Chebyshev",
    "Bounded",
    "optimize",
    "multistart",
    "fd_gradient",
]
