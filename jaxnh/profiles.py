"""Time profiles: laws of time (a ratio U21(t), a torque) as differentiable pytrees.

The public names of `jaxnh._model.profiles`; see there for the implementation."""

from jaxnh._model.profiles import (  # noqa: F401
    Bounded as Bounded,
    Constant as Constant,
    CubicSpline as CubicSpline,
    Fourier as Fourier,
    PiecewiseLinear as PiecewiseLinear,
    Positive as Positive,
    Profile as Profile,
    Sampled as Sampled,
    SmoothStep as SmoothStep,
    trainable as trainable,
)


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
