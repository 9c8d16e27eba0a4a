"""Maps a formulation asks to be applied around every step of an integrator.

Two things a formulation may need from the integrator that an ODE solver does not do by
itself: re-choose how the state is represented before a step (Appell's partition of the
velocities), and map the state back onto the constraints after a step (Lagrange's velocity
projection), or reject a step outright. `StepMaps` states those maps; the solve layer
applies them (`jaxnh._solve.stepping.MappedSolver`).
"""

from __future__ import annotations

from typing import Any, Optional

import equinox as eqx
import jax
import jax.numpy as jnp


__all__ = ["StepMaps", "REJECT_ERROR"]

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
    (diffrax's `RESULTS.singular`, which the formulation explains).
    """

    # positional-only: the integrators call the maps positionally, and overrides name their states as they like
    def pre(self, t, y, args, /) -> tuple[Any, jax.Array]:
        return y, jnp.asarray(False)

    def post(self, t0, y0, t1, y1, args, /) -> tuple[Any, Optional[Any], jax.Array, jax.Array]:
        return y1, None, jnp.asarray(False), jnp.asarray(False)
