"""Formulations of the equations of motion: `Lagrange`, `Appell`, `Substituted`.

The public names of `jaxnh._equations`; see there for the implementation."""

from jaxnh._equations import (  # noqa: F401
    accelerations as accelerations,
    Appell as Appell,
    as_formulation as as_formulation,
    choose_independent as choose_independent,
    Formulation as Formulation,
    formulation as formulation,
    Lagrange as Lagrange,
    METHODS as METHODS,
    multipliers_from_accelerations as multipliers_from_accelerations,
    Substituted as Substituted,
    VelocitySplit as VelocitySplit,
)


__all__ = [
    "Appell",
    "Formulation",
    "Lagrange",
    "Substituted",
    "VelocitySplit",
    "METHODS",
    "accelerations",
    "choose_independent",
    "formulation",
    "as_formulation",
    "multipliers_from_accelerations",
]
