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
