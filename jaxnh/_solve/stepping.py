"""Maps applied around every step of an integrator, and the diffrax solver that applies them.

Two things a formulation may need from the integrator that an ODE solver does
not do by itself:

* before a step, re-choose how the state is represented (Appell's equations
  integrate the independent velocities; which velocities are independent is
  re-chosen when the dependent block of the constraint matrix becomes
  ill-conditioned: generalized coordinate partitioning);
* after a step, map the state back onto the constraints (velocity projection
  for Lagrange's equations), with the size of the correction counted as error
  so that a step that left the constraints by more than the tolerance is
  rejected, or reject a step outright (a dependent block whose determinant
  changed sign during the step passed through singular).

`StepMaps` (`jaxnh._equations.step_maps`, where the formulations define them) states
those maps; `MappedSolver` applies them to any diffrax
adaptive solver; `SensitivityMaps` lifts them to a state augmented with
forward sensitivities, mapping each sensitivity column by the derivative of
the map, so that sensitivities stay the derivatives of the mapped solution.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp

from jaxnh._equations.step_maps import REJECT_ERROR, StepMaps


__all__ = ["coarse_interpolant", "MappedSolver", "SensitivityMaps"]


class SensitivityMaps(StepMaps):
    """`maps` for the state z = ravel(y, S) of a forward-sensitivity solve.

    y is mapped by `maps`, and every sensitivity column s_j (with its parameter
    direction e_j) by the derivative of the map, `dM/dy s_j + dM/dp e_j`.
    Solve args are `(differentiated params, their directions E)`; `p_rest` are
    the other params.
    """

    maps: StepMaps
    unravel: Callable
    p_rest: Any

    def _lift(self, fn, z, args):
        y, S = self.unravel(z)
        p_diff, E = args
        out, lin, aux = jax.linearize(lambda y_, p_: fn(y_, eqx.combine(p_, self.p_rest)), y, p_diff, has_aux=True)
        return jax.flatten_util.ravel_pytree((out, jax.vmap(lin)(S, E)))[0].astype(z.dtype), aux

    def pre(self, t, z, args):
        def fn(y, p):
            y1, jumped = self.maps.pre(t, y, p)
            return y1, jumped

        return self._lift(fn, z, args)

    def post(self, t0, z0, t1, z1, args):
        y0, _ = self.unravel(z0)

        def fn(y, p):
            y1, corr, reject, fail = self.maps.post(t0, jax.lax.stop_gradient(y0), t1, y, p)
            return y1, (corr, reject, fail)

        z1_new, (corr, reject, fail) = self._lift(fn, z1, args)
        if corr is not None:
            # the correction of y counts; the columns' own correction is part of their error too
            corr = z1_new - z1
        return z1_new, corr, reject, fail


class MappedSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """A diffrax adaptive solver with `StepMaps` applied around every step.

    Arguments:
        solver: the wrapped adaptive solver (its error estimate is kept).
        maps: the `StepMaps`.
    """

    solver: diffrax.AbstractAdaptiveSolver
    maps: StepMaps
    # diffrax's ForwardMode sets `scan_kind` on every solver it takes for a Runge–Kutta
    # method (this wrapper passes that test) so that its stages can be forward-
    # differentiated; it is handed on to the wrapped solver in `step`.
    scan_kind: Optional[str] = None

    def _inner(self):
        if self.scan_kind is not None and getattr(self.solver, "scan_kind", "") is None:
            return eqx.tree_at(lambda s: s.scan_kind, self.solver, self.scan_kind, is_leaf=lambda x: x is None)
        return self.solver

    @property
    def stages_per_step(self) -> Optional[int]:
        """Vector-field evaluations per step of the wrapped solver (an FSAL solver
        re-evaluates its first stage after a step whose state was mapped)."""
        tab = getattr(self.solver, "tableau", None)
        if tab is not None:
            return tab.num_stages - (1 if tab.fsal else 0)
        return getattr(self.solver, "stages_per_step", None)

    @property
    def term_structure(self) -> Any:
        return self.solver.term_structure

    # An implicit wrapped solver makes this one implicit too (diffrax forwards `isinstance` through
    # `AbstractWrappedSolver`), and diffrax then reads and sets the root finder's tolerances on it.
    @property
    def root_finder(self) -> Any:
        return self.solver.root_finder  # pyright: ignore[reportAttributeAccessIssue]

    @property
    def root_find_max_steps(self) -> int:
        return self.solver.root_find_max_steps  # pyright: ignore[reportAttributeAccessIssue]

    @property
    def interpolation_cls(self) -> Callable[..., diffrax.AbstractLocalInterpolation]:  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self) -> Any:
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms: Any) -> int | None:
        return self.solver.order(terms)

    def error_order(self, terms: Any) -> Any:
        return self.solver.error_order(terms)

    def init(self, terms: Any, t0: Any, t1: Any, y0: Any, args: Any) -> Any:
        return self.solver.init(terms, t0, t1, y0, args)

    def step(
        self,
        terms: Any,
        t0: Any,
        t1: Any,
        y0: Any,
        args: Any,
        solver_state: Any,
        made_jump: Any,
    ) -> tuple[Any, Any | None, dict[str, Any], Any, diffrax.RESULTS]:
        y0, jumped = self.maps.pre(t0, y0, args)
        if jumped is not False:
            made_jump = jnp.logical_or(made_jump, jumped)
        y1, y_error, dense_info, solver_state, result = self._inner().step(
            terms, t0, t1, y0, args, solver_state, made_jump
        )
        y1_mapped, corr, reject, fail = self.maps.post(t0, y0, t1, y1, args)
        if corr is not None:
            y_error = jax.tree_util.tree_map(lambda e, c: e + c, y_error, corr)
        project_error = getattr(self.maps, "project_error", None)
        if project_error is not None and y_error is not None:
            y_error = project_error(y1_mapped, y_error, args)
        # a map that can never reject or fail says so with a Python False: the step then carries no
        # select on its error, and its result stays diffrax's static one (a traced result is a
        # loop-carried value that costs about a microsecond per step on a CPU)
        if reject is not False:
            y_error = jax.tree_util.tree_map(
                lambda e: jnp.where(reject, jnp.asarray(REJECT_ERROR, e.dtype) * (jnp.abs(e) + 1), e), y_error
            )
        if fail is not False:
            # (equinox types Enumerations as enum.Enum: RESULTS, inheriting from optimistix, looks like its)
            if isinstance(fail, type(diffrax.RESULTS.successful)):  # the failure itself (successful: none)
                result = diffrax.RESULTS.where(fail == diffrax.RESULTS.successful, result, fail)  # pyright: ignore[reportArgumentType]
            else:
                result = diffrax.RESULTS.where(fail, diffrax.RESULTS.singular, result)  # pyright: ignore[reportArgumentType]
        return y1_mapped, y_error, dense_info, solver_state, result

    def func(self, terms: Any, t0: Any, y0: Any, args: Any) -> Any:
        return self.solver.func(terms, t0, y0, args)


def coarse_interpolant(solver) -> bool:
    """Whether `solver` reports between its steps by an interpolant of lower order than its own
    (diffrax's third-order Hermite for a method of order > 3: the implicit Kvaerno4/5)."""
    if solver is None:
        return False
    try:
        order = solver.order(None)
    except Exception:  # a solver whose order depends on its terms: no claim made
        return False
    interp = solver.interpolation_cls
    interp = getattr(interp, "__self__", interp)  # diffrax gives a classmethod constructor for some
    hermite = isinstance(interp, type) and issubclass(interp, diffrax.ThirdOrderHermitePolynomialInterpolation)
    return hermite and order > 3
