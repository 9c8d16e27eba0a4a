"""Rigid bodies and rolling wheels: kinetic energies and contact constraints built from poses.

The public names of `jaxnh._model.rigid`; see there for the implementation."""

from jaxnh._model.rigid import (  # noqa: F401
    angular_velocity as angular_velocity,
    RigidBodies as RigidBodies,
    rot_axis as rot_axis,
    rot_x as rot_x,
    rot_y as rot_y,
    rot_z as rot_z,
    skew as skew,
    time_derivative as time_derivative,
    vee as vee,
    Wheel as Wheel,
)


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
