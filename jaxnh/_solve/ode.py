"""`ode`: the equations of motion as a diffrax problem, for users who call `diffeqsolve` themselves."""

from __future__ import annotations

from typing import Any, Iterable, Optional

import diffrax
import equinox as eqx
import jax.flatten_util
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxnh._base.host import as_float, as_time
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._equations import as_formulation, Formulation, formulation
from jaxnh._model.mechanism import Mechanism
from jaxnh._solve.sensitivity import _flat_mask, _masked_rms
from jaxnh._solve.simulate import eliminate, field
from jaxnh._solve.solution import Expansion
from jaxnh._solve.stepping import MappedSolver


__all__ = ["ODE", "ode"]


class ODE(eqx.Module):
    """A mechanism's equations of motion as a diffrax problem.

    Attributes:
        term: `diffrax.ODETerm` of the formulation's vector field; call it with
            `args=ode.args`.
        y0: the initial state of the formulation, one flat vector: for Appell's
            equations [q, v, dependent indices] (the indices only when the partition
            is chosen automatically), for Lagrange's [q, qd].
        args: the vector field's arguments: (formulation, params, True).
        form: the bound formulation.
        expand: for a mechanism with `dependent` coordinates, the map back to
            all s coordinates (the formulation integrates the others, as in
            `simulate`, and `args[1]` is then `(params, start)`); None otherwise.

    Use `ode.solver(diffrax.Tsit5())` in `diffeqsolve`: it applies the
    formulation's maps around every step (Appell's re-choice of independent
    velocities, Lagrange's projection); a bare solver keeps the partition chosen
    at the start. `ode.unpack(y, t)` maps a state back to (q, qd) (rad, m,
    and their rates); `ode.error_norm` is a norm for `PIDController(norm=...)`
    that leaves bookkeeping entries of the state out of the error control.
    """

    term: diffrax.ODETerm
    y0: Any
    args: Any
    form: Formulation
    expand: Optional[Expansion] = None

    def unpack(self, y: PyTree, t: Any) -> tuple[jax.Array, jax.Array]:
        """Coordinates q (s,) and velocities qd (s,) from a state y at time t (s)."""
        q, qd = self.form.unpack(y, t, self.args[1])
        if self.expand is not None:
            q, qd, _ = self.expand(q, qd, t, self.args[1])
        return q, qd

    def solver(self, solver: diffrax.AbstractAdaptiveSolver[Any]) -> diffrax.AbstractAdaptiveSolver[Any]:
        """`solver` with the formulation's step maps applied (or unchanged if it has none)."""
        maps = self.form.solve_maps()
        return solver if maps is None else MappedSolver(solver, maps)

    def error_norm(self, err: PyTree) -> jax.Array:
        """RMS norm over the state entries that count in the error control."""

        flat = jax.flatten_util.ravel_pytree(err)[0]
        return _masked_rms(flat, _flat_mask(self.form.error_mask(), self.y0))


def ode(
    mech: Mechanism,
    params: PyTree,
    q0: ArrayInput,
    qd0: ArrayInput,
    t0: ArrayLike = 0.0,
    method: str | Formulation = "lagrange",
    *,
    independent: Optional[Iterable[int]] = None,
) -> ODE:
    """The equations of motion of `mech` as a diffrax term, initial state and unpacking.

    Arguments:
        mech: the `Mechanism`.
        params: parameter pytree.
        q0, qd0: initial coordinates and velocities (s,) (qd0 consistent with
            the constraints; unlike `simulate`, no checks are made).
        t0: initial time, s.
        method: a formulation object or name, as in `simulate`.
        independent: fixed independent velocities for "appell"/"substituted".

    A mechanism with `dependent` coordinates is integrated in the others, as
    by `simulate`; `unpack` gives all of them.

    Returns:
        An `ODE`. Example::

            o = nh.ode(mech, p, q0, qd0, 0.0)
            sol = diffrax.diffeqsolve(o.term, o.solver(diffrax.Tsit5()), 0.0, 10.0, None, o.y0,
                                      args=o.args, saveat=diffrax.SaveAt(ts=ts),
                                      stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10,
                                                                                norm=o.error_norm))
            q, qd = jax.vmap(o.unpack)(sol.ys, sol.ts)
    """
    q0 = as_float(q0)
    qd0 = jnp.asarray(qd0, dtype=q0.dtype)
    t0 = as_time(t0, q0)
    expand = None
    if mech.dependent is not None:  # as in simulate: the dependent coordinates are eliminated
        mech, method, params, q0, qd0, expand = eliminate(mech, as_formulation(method, independent), params, q0, qd0)  # pyright: ignore[reportArgumentType]
        independent = None
    form = formulation(mech, method, q0, qd0, t0, params, independent)  # pyright: ignore[reportArgumentType]
    y0 = form.state(q0, qd0, t0, params)
    return ODE(term=diffrax.ODETerm(field), y0=y0, args=(form, params, jnp.asarray(True)), form=form, expand=expand)
