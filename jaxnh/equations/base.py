"""The interface shared by all formulations of the equations of motion."""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp

from ..linalg import mm, solve_psd_min_norm
from .._mechanism import Mechanism
from .terms import constraint_terms, mass_and_velocity_terms


class Formulation(eqx.Module):
    """A way to turn a `Mechanism` into accelerations.

    A formulation fixes the integrated state `y` (a tuple of arrays), how the
    coordinates and velocities are recovered from it, and its vector field
    `dy/dt`. `simulate`, `linearize` and `fit` only use this interface.
    """

    mech: Mechanism

    @abc.abstractmethod
    def state(self, q, qd, t, params):
        """Integrated state y from coordinates q (s,) and velocities qd (s,)."""

    @abc.abstractmethod
    def unpack(self, y, t, params):
        """Coordinates q (s,) and all velocities qd (s,) from the state y."""

    @abc.abstractmethod
    def accelerations(self, q, qd, t, params, multipliers: bool = False):
        """Accelerations qdd (s,) and, if asked, multipliers λ (m,), else None."""

    @abc.abstractmethod
    def vector_field(self, t, y, params):
        """dy/dt for the integrated state y."""


def multipliers_from_accelerations(mech, q, qd, qdd, t, params):
    """Multipliers λ with `M qdd + h − Q = Aᵀ λ` (least squares, minimum norm).

    λ_k is the generalized constraint force of constraint k divided by
    `∂c_k/∂qd`: for the variator it is the tangential contact force times
    the lever arm r (N·m).
    """
    M, h = mass_and_velocity_terms(mech, q, qd, t, params)
    R = mm(M, qdd) + h - mech.generalized_forces(q, qd, t, params)
    A, _ = constraint_terms(mech, q, qd, t, params)
    return solve_psd_min_norm(mm(A, A.T), mm(A, R))


def as_float(x):
    """`x` as an array of a floating dtype (the default float for integer input)."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def as_time(t, like):
    """Time as a scalar array with the floating dtype of `like`."""
    return jnp.asarray(t, dtype=jnp.result_type(like, jnp.float32))
