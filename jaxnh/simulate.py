"""Integration of the equations of motion with diffrax."""

from __future__ import annotations

from typing import Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .equations import METHODS, formulation
from .equations.base import as_float
from .mechanism import Mechanism

__all__ = ["Solution", "simulate", "RECORDABLE", "default_solver"]

RECORDABLE = ("multipliers", "energy", "residual")


class Solution(eqx.Module):
    """A simulated motion, reported at the requested times.

    Attributes:
        ts: report times (n,), s.
        q: coordinates (n, s) at `ts`.
        qd: velocities (n, s) at `ts` (dependent ones from the constraints for
            "appell"/"substituted").
        multipliers: constraint multipliers λ (n, m), when recorded: the
            constraint forces are `Aᵀ λ` with `A = ∂c/∂qd` (for the variator
            λ is the tangential contact force times the roller radius, N·m).
        energy: T + V (n,), J, when recorded.
        residual: constraint values c(q, qd, t) (n, m), when recorded; zero
            for an exact solution.
        stats: dict with `num_steps` (attempted), `num_accepted_steps`,
            `num_rejected_steps`, `rhs_evaluations` (vector-field calls:
            stages per step times attempted steps), `max_steps`.
        status: `diffrax.RESULTS` item: `RESULTS.successful`, or why the
            solve failed (step limit, step size collapse). After a failure
            the values past the failure time are not a solution.
        names: coordinate names.
    """

    ts: Float[Array, " n"]
    q: Float[Array, "n s"]
    qd: Float[Array, "n s"]
    multipliers: Optional[Float[Array, "n m"]]
    energy: Optional[Float[Array, " n"]]
    residual: Optional[Float[Array, "n m"]]
    stats: dict
    status: diffrax.RESULTS
    names: tuple = eqx.field(static=True)

    @property
    def success(self):
        """Boolean (array under vmap): did the solve reach the last report time."""
        return self.status == diffrax.RESULTS.successful

    @property
    def message(self) -> str:
        """Why the solve failed, or "success" (concrete, un-batched solutions only)."""
        if bool(np.all(np.asarray(self.success))):
            return "success"
        return f"solve failed: {diffrax.RESULTS[self.status]}"


def default_solver(rtol: float):
    """The explicit solver used when `simulate(solver=None)`: Tsit5 (5th order)."""
    return diffrax.Tsit5()


def _stages_per_step(solver) -> Optional[int]:
    tab = getattr(solver, "tableau", None)
    if tab is None:
        return getattr(solver, "stages_per_step", None)
    return tab.num_stages - (1 if tab.fsal else 0)


def _check_ts(ts):
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"ts must be a 1-D array of at least 2 report times (ts[0] is the start); got shape {ts.shape}")
    if not isinstance(ts, jax.core.Tracer):
        a = np.asarray(ts)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"ts must be finite; got non-finite entries at {np.nonzero(~np.isfinite(a))[0]}")
        if not np.all(np.diff(a) > 0):
            bad = int(np.nonzero(np.diff(a) <= 0)[0][0])
            raise ValueError(f"ts must be strictly increasing; ts[{bad}]={a[bad]} ≥ ts[{bad + 1}]={a[bad + 1]}")


def simulate(
    mech: Mechanism,
    params,
    q0,
    qd0,
    ts,
    method: str = "appell",
    solver=None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    record=(),
    *,
    independent=None,
    max_steps: int = 100_000,
    dt0=None,
    adjoint: Optional[diffrax.AbstractAdjoint] = None,
    throw: bool = True,
) -> Solution:
    """Integrate the equations of motion of `mech` from (q0, qd0) at ts[0].

    Arguments:
        mech: the `Mechanism`.
        params: parameter pytree passed to every user function; its arrays
            are traced, so `jax.grad`/`jax.vmap` over it work.
        q0: initial coordinates (s,).
        qd0: initial velocities (s,); must satisfy the constraints.
        ts: report times (n,), strictly increasing, s; ts[0] is the start.
        method: "appell" (default; state (q, independent velocities), the
            constraints hold exactly), "lagrange" (multipliers, state (q, qd))
            or "substituted" (the paper's wrong method, for comparison).
        solver: a diffrax solver; default `default_solver(rtol)`.
        rtol, atol: relative and absolute tolerances of the PID step control.
        record: any of "multipliers", "energy", "residual" — computed at the
            report times only when asked.
        independent: indices of independent velocities ("appell",
            "substituted"); default from `mech.independent` or chosen from
            the constraint matrix at the initial state (needs concrete
            values: pass it under `jit`/`vmap`).
        max_steps: step limit; reaching it is a failed solve.
        dt0: initial step, s (default: chosen automatically).
        adjoint: diffrax adjoint for reverse-mode gradients (default
            `RecursiveCheckpointAdjoint`; use `diffrax.ForwardMode()` with
            `jax.jacfwd`).
        throw: raise an error when the solve fails (default). With
            `throw=False` (recommended under `vmap`) check `sol.status`.

    Returns:
        A `Solution`.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    record = (record,) if isinstance(record, str) else tuple(record)
    for r in record:
        if r not in RECORDABLE:
            raise ValueError(f"record entries must be among {RECORDABLE}; got {r!r}")
    if method == "substituted" and "multipliers" in record:
        raise ValueError("record='multipliers' is not available for method='substituted' (it has no multipliers)")
    q0 = as_float(q0)
    qd0 = jnp.asarray(qd0, dtype=q0.dtype)
    ts = jnp.asarray(ts, dtype=q0.dtype)
    _check_ts(ts)
    t0 = ts[0]
    mech.check_shapes(q0, qd0, t0, params)
    mech.check_values(q0, qd0, t0, params)
    form = formulation(mech, method, q0, qd0, t0, params, independent)
    y0 = form.state(q0, qd0, t0, params)

    solver = default_solver(rtol) if solver is None else solver
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    ys, result, stats, out = _integrate(
        form, params, y0, ts, solver, rtol, atol, record, max_steps, dt0, adjoint, throw
    )
    q, qd = ys
    return Solution(
        ts=ts,
        q=q,
        qd=qd,
        multipliers=out.get("multipliers"),
        energy=out.get("energy"),
        residual=out.get("residual"),
        stats=stats,
        status=result,
        names=mech.coordinate_names(q0.shape[0]),
    )


@eqx.filter_jit
def _integrate(form, params, y0, ts, solver, rtol, atol, record, max_steps, dt0, adjoint, throw):
    """The compiled part of `simulate`: solve, unpack, and the recorded quantities."""
    mech = form.mech

    def vector_field(t, y, p):
        dy = form.vector_field(t, y, p)
        return jax.tree_util.tree_map(lambda d, x: d.astype(x.dtype), dy, y)

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=dt0,
        y0=y0,
        args=params,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        adjoint=adjoint,
        throw=throw,
    )
    q, qd = jax.vmap(lambda y, t: form.unpack(y, t, params))(sol.ys, ts)
    out = {}
    if "multipliers" in record:
        out["multipliers"] = jax.vmap(lambda a, b, t: form.accelerations(a, b, t, params, multipliers=True)[1])(q, qd, ts)
    if "energy" in record:
        out["energy"] = jax.vmap(lambda a, b, t: mech.energy(a, b, t, params))(q, qd, ts)
    if "residual" in record:
        out["residual"] = jax.vmap(lambda a, b, t: mech.constraint(a, b, t, params))(q, qd, ts)
    stats = dict(sol.stats)
    stages = _stages_per_step(solver)
    if stages is not None:
        stats["rhs_evaluations"] = stats["num_steps"] * stages
    return (q, qd), sol.result, stats, out
