"""Constraint drift control for the "lagrange" formulation.

Lagrange's equations with multipliers integrate the constraint only through
its time derivative, so the velocity constraint `c(q, qd, t) = 0` drifts
with the integration error. Two remedies, selected in `simulate` by
`stabilization=`:

* "baumgarte" — `A qdd + b = −α c` (see `jaxnh.equations.lagrange`); cheap,
  but a large α makes the system stiff.
* "projection" — after every accepted or rejected step the velocities are
  projected back onto the constraints, minimum-norm in the kinetic-energy
  metric (`jaxnh.consistent_velocities`). The projected state restarts the
  next step (one extra right-hand-side evaluation per step for FSAL solvers).
  The size of the correction is added to the step's error estimate: a step
  that left the constraints by more than the tolerance is rejected rather
  than silently pulled back (a step that jumped over a fast change of the
  constraint, e.g. a steep ratio law, would otherwise look exact).

The Appell formulation integrates only independent velocities and cannot
drift; it needs neither.
"""

from __future__ import annotations

from typing import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .consistent import consistent_velocities

__all__ = ["ProjectedSolver", "VelocityProjection", "default_baumgarte_rate"]


def default_baumgarte_rate(ts):
    """Default Baumgarte rate α = 1 / (report interval), 1/s.

    Users sample the report times finely enough to resolve the motion, so
    the report interval is a time scale of interest that is known without
    solving; a violation then decays by a factor e per report interval,
    while α h stays well inside an explicit solver's stability region.
    """
    return 1.0 / jnp.median(jnp.diff(ts))


class VelocityProjection(eqx.Module):
    """(q, qd) → (q, consistent qd) for a mechanism, as used by "projection".

    A Module (not a closure), so two projections of the same mechanism compare
    equal and a repeated `simulate` call reuses its compiled solve.
    """

    mech: object

    def __call__(self, t, y, params):
        q, qd = y
        return (q, consistent_velocities(self.mech, q, qd, t, params))


class ProjectedSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """A diffrax solver whose every step ends with a projection of the state.

    Arguments:
        solver: the wrapped adaptive solver (its error estimate is kept).
        project: `project(t, y, args) -> y`, a differentiable map onto the
            constraint manifold.
    """

    solver: diffrax.AbstractAdaptiveSolver
    project: Callable

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # made_jump=True: the FSAL derivative of the previous (unprojected) end
        # point is stale after projection, so the first stage is re-evaluated.
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, True
        )
        y1_projected = self.project(t1, y1, args)
        # The correction is part of the step's error: the step size controller
        # rejects a step that drifted off the constraints by more than the tolerance.
        y_error = jax.tree_util.tree_map(lambda e, a, b: e + (a - b), y_error, y1_projected, y1)
        return y1_projected, y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
