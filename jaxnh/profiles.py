"""Time profiles: laws of time (a ratio U21(t), a torque) as differentiable pytrees.

The public names of `jaxnh._model.profiles`; see there for the implementation."""

from jaxnh._model.profiles import *  # noqa: F403 (the public names of one implementation module)


# written out, as type checkers need a literal list (its names come from the star import: hence
# F405 off); tests/test_layers.py checks it equals the implementation's
# ruff: noqa: F405
__all__ = [
    "Profile",
    "Constant",
    "Fourier",
    "SmoothStep",
    "PiecewiseLinear",
    "CubicSpline",
    "Sampled",
    "Positive",
    "Bounded",
    "trainable",
]
