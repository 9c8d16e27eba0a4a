"""Small dense linear algebra written for the sizes of mechanisms (a few to a few tens).

The public names of `jaxnh._base.linalg`; see there for the implementation."""

from jaxnh._base.linalg import (  # noqa: F401
    cholesky as cholesky,
    mm as mm,
    pivot_rtol as pivot_rtol,
    solve_lower as solve_lower,
    solve_psd_min_norm as solve_psd_min_norm,
    solve_spd as solve_spd,
    solve_square as solve_square,
    solve_upper_t as solve_upper_t,
    UNROLL_MAX as UNROLL_MAX,
    value_and_jacfwd as value_and_jacfwd,
)


__all__ = [
    "UNROLL_MAX",
    "mm",
    "cholesky",
    "solve_lower",
    "solve_upper_t",
    "solve_spd",
    "pivot_rtol",
    "solve_psd_min_norm",
    "solve_square",
    "value_and_jacfwd",
]
