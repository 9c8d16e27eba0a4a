"""`stick_margin`: how far a friction drive is from slipping, as a smooth design objective.

The motion with every friction contact held (the mechanism with its contacts
removed, a smooth solve without transitions) gives the force each contact
needs; its stick margin is `1 − ‖λ‖/(μs N)`: 1 with no load, 0 on the edge of
the static cone, negative where the real drive would slip. For a drive that
starts sticking, the first onset of slip in the friction solve is where this
margin first reaches 0, so "keeps rolling" is "the smallest margin over the
motion is ≥ 0" — a condition on a smooth function of the parameters, with
none of the discontinuities of the number of transitions.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._model.mechanism import Mechanism
from jaxnh._solve.simulate import simulate


__all__ = ["StickMargin", "stick_margin"]


class StickMargin(eqx.Module):
    """The stick margins of a mechanism's friction contacts along its rolling motion.

    Attributes:
        names: the contact names.
        utilisation: (n, c), ‖λ‖/(μs N) at the report times, with every contact held.
        margin: (n, c), 1 − utilisation: ≥ 0 where the contact can hold.
        minimum: (c,), the smallest margin over the report times.
        soft_minimum: (c,), `−τ log Σ_i exp(−margin_i/τ)` (τ = `temperature`): a smooth
            lower bound of `minimum`, within τ log n of it; use it as a constraint
            `soft_minimum ≥ 0` (or a penalty) in gradient-based design.
        solution: the rolling solve (`Solution`, multipliers recorded).
    """

    names: tuple = eqx.field(static=True)
    utilisation: Float[Array, "n c"]
    margin: Float[Array, "n c"]
    minimum: Float[Array, " c"]
    soft_minimum: Float[Array, " c"]
    solution: Any


def stick_margin(
    mech: Mechanism,
    params: PyTree,
    q0: ArrayInput,
    qd0: ArrayInput,
    ts: ArrayInput,
    *,
    temperature: float = 0.01,
    **simulate_kwargs: Any,
) -> StickMargin:
    """The stick margin of each friction contact of `mech` along its motion with every contact held.

    Arguments:
        mech: a `Mechanism` with `contacts`.
        params, q0, qd0, ts: as for `simulate` (qd0 must satisfy every constraint, the
            friction-held rows too: the motion is the rolling one).
        temperature: τ of the soft minimum (dimensionless, like the margin).
        **simulate_kwargs: passed to `simulate` (method, rtol, atol, ...).

    Returns:
        A `StickMargin`. Differentiable in params, q0 and qd0 (`jax.grad` of
        `.soft_minimum` or `.minimum`), and usable under `jit` and `vmap`.
    """
    if not isinstance(mech, Mechanism) or not mech.contacts:
        raise ValueError("stick_margin: `mech` must be a jaxnh.Mechanism with friction `contacts`")
    if not temperature > 0:
        raise ValueError(f"stick_margin: temperature must be > 0; got {temperature!r}")
    record = tuple(simulate_kwargs.pop("record", ()))
    rolling = dataclasses.replace(mech, contacts=())
    sol = simulate(rolling, params, q0, qd0, ts, record=(*record, "multipliers"), **simulate_kwargs)
    ts_ = jnp.asarray(ts, sol.q.dtype)

    def one(q, qd, t, lam):
        out = []
        for c in mech.contacts:
            N, mus, _ = c.values(q, qd, t, params, multipliers=lam)
            f = jnp.stack([lam[r] for r in c.rows])
            norm = jnp.sqrt(jnp.sum(f * f) + jnp.finfo(f.dtype).tiny)
            out.append(norm / (mus * N))
        return jnp.stack(out)

    utilisation = jax.vmap(one)(sol.q, sol.u, ts_, sol.multipliers)  # (the speeds, with `kinematics`)
    margin = 1.0 - utilisation
    soft = -temperature * jax.scipy.special.logsumexp(-margin / temperature, axis=0)
    return StickMargin(
        names=tuple(c.label(i) for i, c in enumerate(mech.contacts)),
        utilisation=utilisation,
        margin=margin,
        minimum=jnp.min(margin, axis=0),
        soft_minimum=soft,
        solution=sol,
    )
