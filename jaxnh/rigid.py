"""Rigid bodies and rolling wheels: kinetic energies and contact constraints built from poses.

The public names of `jaxnh._model.rigid`; see there for the implementation."""

from jaxnh._model.rigid import *  # noqa: F403 (the public names of one implementation module)


# written out, as type checkers need a literal list (its names come from the star import: hence
# F405 off); tests/test_layers.py checks it equals the implementation's
# ruff: noqa: F405
__all__ = [
    "RigidBodies",
    "Wheel",
    "rot_x",
    "rot_y",
    "rot_z",
    "rot_axis",
    "skew",
    "vee",
    "time_derivative",
    "angular_velocity",
]
