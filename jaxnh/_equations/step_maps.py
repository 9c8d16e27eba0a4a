"""Maps a formulation asks to be applied around every step of an integrator.

Two things a formulation may need from the integrator that an ODE solver does not do by
itself: re-choose how the state is represented before a step (Appell's partition of the
velocities), and map the state back onto the constraints after a step (Lagrange's velocity
projection), or reject a step outright. `StepMaps` states those maps; the solve layer
applies them (`jaxnh._solve.stepping.MappedSolver`).
"""

from __future__ import annotations

from typing import Any, Optional, Union

import equinox as eqx
import jax
import jax.numpy as jnp


__all__ = ["StepMaps", "REJECT_ERROR", "UnitQuaternions", "normalize_quaternions", "with_quaternions"]

REJECT_ERROR = 1e10
"""Error estimate (in units of the tolerance) given to a step that must be rejected."""


class StepMaps(eqx.Module):
    """Maps applied around each step; the defaults change nothing.

    Both receive the solve's `args` (for simulate: `(formulation, params, ok)`).

    `pre(t, y, args) -> (y, jumped)`: the state a step starts from; `jumped`
    (bool) says that it differs from the one given, so a first-same-as-last
    solver must re-evaluate its first stage.

    `post(t0, y0, t1, y1, args) -> (y1, correction, reject, fail)`: the state a
    step ends at; `correction` (like y, or None) is added to the error estimate;
    `reject` (bool) forces a rejection; `fail` (bool) stops the solve as failed
    (diffrax's `RESULTS.singular`, which the formulation explains), or is itself the
    `diffrax.RESULTS` item to stop with (`RESULTS.successful`: no failure). A map that
    can never reject, or never fail, returns the Python `False` there: the
    integrator then leaves that test out of the step.

    """

    # positional-only: the integrators call the maps positionally, and overrides name their states as they like
    def pre(self, t: jax.typing.ArrayLike, y: Any, args: Any, /) -> tuple[Any, Union[jax.Array, bool]]:
        return y, False

    def post(
        self, t0: jax.typing.ArrayLike, y0: Any, t1: jax.typing.ArrayLike, y1: Any, args: Any, /
    ) -> tuple[Any, Optional[Any], Union[jax.Array, bool], Union[jax.Array, bool]]:
        return y1, None, False, False


class UnitQuaternions(StepMaps):
    """Keep groups of coordinates at unit norm: `inner`'s maps, with the unit quaternions named by
    `groups` rescaled to |e| = 1 at the end of every step.

    The state is a flat vector that starts with the nq coordinates (every formulation's). The field
    of a quaternion's kinematics is tangent to the sphere |e| = const, so the exact flow keeps the
    norm; an integrator leaves it by its local error, which the rescaling removes at each accepted
    step (the correction is not counted as error: it is the part of the error the constraint
    |e| = 1 takes away). `project_error` takes the norm direction out of the step's error
    estimate as well, so the step-size control spends nothing on it.
    """

    inner: Optional[StepMaps]
    groups: tuple = eqx.field(static=True)

    def pre(self, t, y, args, /):
        return (y, False) if self.inner is None else self.inner.pre(t, y, args)

    def post(self, t0, y0, t1, y1, args, /):
        y1 = normalize_quaternions(y1, self.groups)
        if self.inner is None:
            return y1, None, False, False
        return self.inner.post(t0, y0, t1, y1, args)

    def project_error(self, y1, y_error, args, /):
        """The step's error estimate without its components along each quaternion (radial)."""
        for g in self.groups:
            idx = jnp.asarray(g)
            e = y1[idx]
            n = e / jnp.sqrt(jnp.sum(e * e))
            err = y_error[idx]
            y_error = y_error.at[idx].set(err - jnp.sum(err * n) * n)
        return y_error


def normalize_quaternions(y: jax.Array, groups: tuple) -> jax.Array:
    """y with each group of entries (a quaternion) divided by its norm."""
    for g in groups:
        idx = jnp.asarray(g)
        e = y[idx]
        y = y.at[idx].set(e / jnp.sqrt(jnp.sum(e * e)))
    return y


def with_quaternions(maps: Optional[StepMaps], groups: tuple) -> Optional[StepMaps]:
    """`maps` extended to keep the unit quaternions `groups` at unit norm (unchanged without groups)."""
    return maps if not groups else UnitQuaternions(maps, tuple(groups))
