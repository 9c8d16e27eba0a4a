"""Formulations of the equations of motion: `Lagrange`, `Appell`, `Substituted`.

The public names of `jaxnh._equations`; see there for the implementation."""

from jaxnh._equations import *  # noqa: F403 (the public names of one implementation module)


# written out, as type checkers need a literal list (its names come from the star import: hence
# F405 off); tests/test_layers.py checks it equals the implementation's
# ruff: noqa: F405
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
