"""Formulations of the equations of motion: "lagrange", "appell", "substituted"."""

from __future__ import annotations

import jax.numpy as jnp

from .._mechanism import Mechanism
from .appell import Appell
from .base import Formulation, as_float, as_time, multipliers_from_accelerations
from .lagrange import Lagrange
from .split import VelocitySplit, check_split, choose_independent
from .substituted import Substituted

METHODS = ("lagrange", "appell", "substituted")

__all__ = [
    "Appell", "Formulation", "Lagrange", "Substituted", "VelocitySplit",
    "METHODS", "accelerations", "choose_independent", "formulation",
    "multipliers_from_accelerations",
]


def formulation(mech: Mechanism, method: str, q, qd, t, params, independent=None) -> Formulation:
    """Build the formulation `method` for `mech`, validating shapes at trace time.

    `q`, `qd`, `t`, `params` are a sample state (only their shapes are used,
    and their values when concrete for the automatic split).
    """
    if not isinstance(mech, Mechanism):
        raise TypeError(f"mech must be a jaxnh.Mechanism; got {type(mech).__name__}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    m = mech.check_shapes(q, qd, t, params)
    if method == "lagrange":
        return Lagrange(mech)
    s = jnp.shape(q)[0]
    if independent is None:
        independent = mech.independent
    if independent is None:
        independent = choose_independent(mech, q, qd, t, params)
    split = VelocitySplit.make(mech, s, m, independent)
    check_split(mech, split.independent, q, qd, t, params)
    return (Appell if method == "appell" else Substituted)(mech, split)


def accelerations(mech: Mechanism, q, qd, t, params, method: str = "lagrange", independent=None):
    """Accelerations and multipliers of a mechanism at one state.

    Arguments:
        mech: the `Mechanism`.
        q: coordinates, shape (s,).
        qd: velocities, shape (s,); should satisfy the constraints.
        t: time, s.
        params: parameters pytree passed to the user functions.
        method: "lagrange" (multipliers), "appell" (Gibbs–Appell in the
            independent velocities) or "substituted" (the paper's naive and
            wrong method, for comparison only).
        independent: indices of independent velocities for "appell" and
            "substituted" (default: chosen from the constraint matrix).

    Returns:
        `(qdd, multipliers)`: accelerations (s,) in units of q per s², and
        multipliers λ (m,) such that the constraint forces are `Aᵀ λ` with
        `A = ∂c/∂qd` (`None` for "substituted", which has none).
    """
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    form = formulation(mech, method, q, qd, t, params, independent)
    # concrete input: non-finite values or a mass matrix that is not positive
    # definite raise here instead of returning NaN (qd need not be consistent)
    mech.check_values(q, qd, t, params, constraint_rtol=float("inf"))
    return form.accelerations(q, qd, t, params, multipliers=method != "substituted")
