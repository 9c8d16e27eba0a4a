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

Both are differentiable: Baumgarte is a term of the vector field; the
projection is a differentiable map applied after each step, and with forward
sensitivities (`jaxnh.ForwardSensitivity`, `simulate`'s automatic choice for
small parameter counts) the sensitivities are projected with its derivative
(`ProjectedSolver.for_sensitivities`), so the result is the derivative of the
projected computed solution in every differentiation mode.

The Appell formulation integrates only independent velocities and cannot
drift; it needs neither. Measured drift, accuracy and cost of each option:
benchmarks/STABILITY.md.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp

from ._consistent import consistent_velocities
from .solvers import DOP853, Tsit5

__all__ = ["ProjectedSolver", "VelocityProjection", "ParamsOf", "default_baumgarte_rate"]


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


class ParamsOf(eqx.Module):
    """`project(t, y, args[index])`: a projection written for `params`, used by a solve
    whose `args` bundle more than the parameters (the forward-sensitivity solve passes
    `(formulation, params)`)."""

    project: Callable
    index: int = eqx.field(static=True, default=1)

    def __call__(self, t, y, args):
        return self.project(t, y, args[self.index])


class _SensitivityProjection(eqx.Module):
    """The projection of a forward-sensitivity state z = ravel(y, S).

    y is projected, and every sensitivity column s_j (with its parameter
    direction e_j) is mapped by the projection's derivative,
    `dP/dy s_j + dP/dp e_j`: the derivative of the projected step.
    """

    project: Callable
    unravel: Callable
    p_rest: Any

    def __call__(self, t, z, args):
        y, S = self.unravel(z)
        p_diff, E = args
        y1, lin = jax.linearize(lambda y_, p_: self.project(t, y_, eqx.combine(p_, self.p_rest)), y, p_diff)
        return jax.flatten_util.ravel_pytree((y1, jax.vmap(lin)(S, E)))[0].astype(z.dtype)


class ProjectedSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """A diffrax solver whose every step ends with a projection of the state.

    Arguments:
        solver: the wrapped adaptive solver (its error estimate is kept).
        project: `project(t, y, args) -> y`, a differentiable map onto the
            constraint manifold.
    """

    solver: diffrax.AbstractAdaptiveSolver
    project: Callable
    # diffrax's ForwardMode sets `scan_kind` on every solver it takes for a Runge–Kutta
    # method (this wrapper passes that test) so that its stages can be forward-
    # differentiated; it is handed on to the wrapped solver in `step`.
    scan_kind: Optional[str] = None

    def _inner(self):
        if self.scan_kind is not None and getattr(self.solver, "scan_kind", "") is None:
            return eqx.tree_at(lambda s: s.scan_kind, self.solver, self.scan_kind, is_leaf=lambda x: x is None)
        return self.solver

    def for_sensitivities(self, unravel: Callable, p_rest) -> "ProjectedSolver":
        """The same solver for the augmented state of `jaxnh.sensitivity` (y and its
        sensitivity columns raveled into one vector by `unravel`'s inverse; args
        `(differentiated params, their column directions)`, `p_rest` the other params)."""
        return ProjectedSolver(self.solver, _SensitivityProjection(self.project, unravel, p_rest), self.scan_kind)

    @property
    def stages_per_step(self) -> Optional[int]:
        """Vector-field evaluations per step: the wrapped solver's, plus one for FSAL
        solvers (their last stage is at the unprojected end point, so the next step
        re-evaluates its first stage)."""
        tab = getattr(self.solver, "tableau", None)
        if tab is not None:
            return tab.num_stages
        if isinstance(self.solver, (Tsit5, DOP853)):  # jaxnh's unrolled FSAL solvers
            return self.solver.stages_per_step + 1
        return None

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
        y1, y_error, dense_info, solver_state, result = self._inner().step(
            terms, t0, t1, y0, args, solver_state, True
        )
        y1_projected = self.project(t1, y1, args)
        # The correction is part of the step's error: the step size controller
        # rejects a step that drifted off the constraints by more than the tolerance.
        y_error = jax.tree_util.tree_map(lambda e, a, b: e + (a - b), y_error, y1_projected, y1)
        return y1_projected, y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
