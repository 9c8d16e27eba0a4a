"""Linearised equations of motion about an operating point, by `jax.jacfwd`.

The state is `x = (q_C, v)`: a chosen subset q_C of the coordinates (leave
out ignorable ones — a bicycle's position and heading, a wheel's rotation
angle — whose values do not enter the dynamics) and the independent
velocities v; the dependent velocities follow from the constraints,
`q̇ = B(q, t) v + β0(q, t)`, and the other coordinates stay at their
operating values. The equations of motion projected on the independent
velocities,

    E(q_C, v, v̇) = Bᵀ (M q̈ + h − Q) = 0,     q̈ = B v̇ + β,

(Lagrange's equations with the multipliers eliminated, `Bᵀ Aᵀ = 0`, or
Appell's `Bᵀ (∂S/∂q̈ − Q)`) are differentiated once by forward mode at the
operating point into the second-order form

    mass · δv̇ + damping · δv + stiffness · δq_C = 0,

whose coefficients are those a textbook writes (for the Whipple bicycle:
`M`, `v C1` and `g K0 + v² K2` of Meijaard et al. 2007), and the state
matrix follows as

    A = [[∂q̇_C/∂q_C, ∂q̇_C/∂v], −mass⁻¹ [stiffness, damping]].

The operating point may be a steady motion rather than an equilibrium (a
bicycle running straight: the wheels turn, the position advances) as long
as the chosen state is steady there; `Linearization.rates` holds `ẋ` at the
operating point to check that it is.

Nested automatic differentiation makes large graphs: for the Whipple
bicycle (8 coordinates, 5 constraints) one linearisation is some 20k traced
operations, which take 1.5–2 s to trace and 3–4 s to compile on a 2-core CPU
(with `jaxnh._export.ONE_SHOT`, XLA's cheapest settings), and about 1 ms to
evaluate. It is compiled once per structure: later calls, and `jax.vmap` over
speeds or parameters, reuse it.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._checks import constraints_affine
from ._export import one_shot_jit
from ._mechanism import _state_terms, Mechanism
from ._status import is_traced
from .equations.base import as_data, as_float, as_time
from .equations.split import (
    best_partition,
    choose_independent,
    partition_quality,
    pick,
    resolve_independent,
    VelocitySplit,
)
from .linalg import mm, solve_spd, value_and_jacfwd


__all__ = ["Linearization", "linearize"]

LINEAR_METHODS = ("lagrange", "appell")


class Linearization(eqx.Module):
    """The linearised motion about an operating point.

    Attributes:
        A: state matrix (n, n) for the state `x = (q_C, v)`; its rows for
            q_C are in units of 1/s (or rates of the coordinates), those for
            v in units of accelerations.
        mass: `∂E/∂v̇` (k, k), the mass matrix for the independent velocities.
        damping: `∂E/∂v` (k, k), gyroscopic and non-conservative velocity terms.
        stiffness: `∂E/∂q_C` (k, n_C).
        rates: the state's rates of change ẋ at the operating point (n,):
            zero when it is an equilibrium or a steady motion.
        state: the operating state x0 (n,).
        states: state names, coordinates then `"d<name>"` for velocities.
        coordinates: indices of q_C; speeds: indices of the independent velocities.
    """

    A: Float[Array, "n n"]
    mass: Float[Array, "k k"]
    damping: Float[Array, "k k"]
    stiffness: Float[Array, "k c"]
    rates: Float[Array, " n"]
    state: Float[Array, " n"]
    states: tuple = eqx.field(static=True)
    coordinates: tuple = eqx.field(static=True)
    speeds: Optional[tuple] = eqx.field(static=True)

    def eigenvalues(self):
        """Eigenvalues of A (complex, unsorted), 1/s."""
        return jnp.linalg.eigvals(self.A)


def _indices(name, idx, s):
    out = tuple(int(i) for i in idx)
    if len(set(out)) != len(out) or not all(0 <= i < s for i in out):
        raise ValueError(f"linearize: `{name}` must be distinct indices in 0..{s - 1}; got {tuple(idx)!r}")
    return out


def linearize(
    mech: Mechanism,
    params,
    q,
    qd,
    t=0.0,
    *,
    coordinates=None,
    speeds=None,
    method: str = "lagrange",
    complete: Optional[Callable] = None,
    accelerations=None,
) -> Linearization:
    """Linearise the motion of `mech` about the state (q, qd) at time t.

    Arguments:
        mech: the `Mechanism`.
        params: its parameters (a pytree; differentiable, batchable).
        q: operating coordinates (s,).
        qd: operating velocities (s,); only the independent ones (`speeds`)
            are used, the dependent ones follow from the constraints.
        t: time, s.
        coordinates: indices of the coordinates kept in the state (default
            all); leave out ignorable ones.
        speeds: indices of the independent velocities (default
            `mech.independent`, else chosen from the constraint matrix at
            (q, qd); under `jit`/`vmap` with traced values the choice is made
            inside the program and `speeds` of the result is None).
        method: which equations are linearised: "lagrange" — Lagrange's
            expression from T, `E = Bᵀ (d/dt ∂T/∂q̇ − ∂T/∂q − Q)` (the
            multipliers drop out, as `Bᵀ Aᵀ = 0`); "appell" — Appell's,
            `E = Bᵀ (∂S/∂q̈ − Q)` with the mechanism's acceleration energy S
            (the same as "lagrange" when it has none).
        complete: optional `complete(q, t, params) -> q` applied to every
            perturbed configuration, e.g. `HolonomicMechanism.restore` to
            keep holonomic constraints satisfied.
        accelerations: the independent accelerations v̇ (k,) at the
            operating point, if known (zero for an equilibrium or a steady
            motion); saves one of two passes. `rates` reports the actual
            ones, so a wrong value shows there.

    Returns:
        A `Linearization`. Invalid input raises a ValueError naming it when
        the values are concrete; under `jit`/`vmap`/`grad` constraints
        declared linear that are not (and NaN input, a singular mass matrix)
        give NaN matrices, never a finite wrong one.
    """
    if method not in LINEAR_METHODS:
        raise ValueError(f"linearize: method must be one of {LINEAR_METHODS}; got {method!r}")
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    params = as_data(params, q)
    m = mech.check_shapes(q, qd, t, params)  # raises, naming the argument, for wrong shapes
    mech.check_finite(q, qd, t, params)  # NaN/inf raise here, naming the argument
    s = q.shape[0]
    coordinates = tuple(range(s)) if coordinates is None else _indices("coordinates", coordinates, s)
    speeds = resolve_independent(mech, None if speeds is None else _indices("speeds", speeds, s), s, m)
    if speeds is None and not is_traced(q, qd, t, params):
        speeds = choose_independent(mech, q, qd, t, params)
    if accelerations is not None:
        accelerations = jnp.asarray(accelerations, dtype=q.dtype)
        if accelerations.shape != (s - m,):
            raise ValueError(
                f"linearize: `accelerations` must have shape ({s - m},) (one per independent speed); "
                f"got {accelerations.shape}"
            )
    # concrete input: the program also returns the terms of `Mechanism.check_values` at (q, qd), which
    # are judged on the host after it (a ValueError naming the problem), and leaves out its in-graph
    # copy of the check for constraints declared linear that are not
    checked = not is_traced(q, qd, t, params)
    args = (mech, params, q, qd, t, coordinates, speeds, method, complete, accelerations, checked)
    # compiled once per structure with XLA's cheapest settings; for jaxnh's own models (the bicycle)
    # kept on disk and shipped as an exported program (jaxnh._export); traced into a caller's jit
    out = _linearize(*args)
    A, mass, damping, stiffness, rates, x0, quality, terms = out
    if checked:  # a mass matrix that is not positive definite, constraints declared linear that are not, ...
        mech._judge_state_terms(terms, constraint_rtol=float("inf"))
    if checked and speeds is not None and m and not float(quality) > 1e3 * float(jnp.finfo(q.dtype).eps):
        raise ValueError(
            f"linearize: speeds={speeds}: the dependent velocities cannot be solved from the constraints "
            "at this state (the dependent block of ∂c/∂qd is singular); choose other speeds or pass "
            "speeds=None for an automatic choice."
        )
    names = mech.coordinate_names(s)
    dnames = tuple("d" + names[i] for i in speeds) if speeds is not None else tuple(f"dv{j}" for j in range(s - m))
    states = tuple(names[i] for i in coordinates) + dnames
    return Linearization(
        A=A,
        mass=mass,
        damping=damping,
        stiffness=stiffness,
        rates=rates,
        state=x0,
        states=states,
        coordinates=coordinates,
        speeds=speeds,
    )


def _linearize_traced(mech, params, q, qd, t, coordinates, speeds, method, complete, accelerations, checked=False):
    """The compiled part of `linearize` (once per mechanism, shapes and options). `checked`: the
    values are concrete and checked on the host after the call, so the in-graph affinity test is
    left out, and the last two outputs are the quality of the given `speeds`' dependent block at
    (q, qd) (1 otherwise), for `linearize` to refuse a singular one, and `_state_terms` at (q, qd)
    for `Mechanism._judge_state_terms` (None otherwise)."""
    s = q.shape[0]
    m = mech.n_constraints(q, qd, t, params)
    split = VelocitySplit(mech, s, m)
    quality = jnp.ones((), q.dtype)
    terms = _state_terms(mech, q, qd, t, params) if checked else None
    if checked and speeds is not None and m:
        quality = partition_quality(mech, q, qd, t, params, speeds, s - m, A=terms[2] if terms else None)[0]
    if complete is not None:
        q = complete(q, t, params)
    part = speeds if speeds is not None else best_partition(mech, q, qd, t, params, s, m)[0]
    nc = len(coordinates)
    use_S = method == "appell" and mech.acceleration_energy is not None

    def configuration(xc):
        qq = q
        for j, i in enumerate(coordinates):
            qq = qq.at[i].set(xc[j])
        return complete(qq, t, params) if complete is not None else qq

    def E(xc, v, vd):
        """Bᵀ (M q̈ + h − Q) (or Bᵀ (∂S/∂q̈ − Q)) at q̈ = B v̇ + β."""
        qq = configuration(xc)
        qdot, B, beta = split.velocities_and_rates(qq, v, t, params, part)
        qdd = mm(B, vd) + beta
        if use_S:
            lhs = jax.grad(mech.acceleration_energy, argnums=2)(qq, qdot, qdd, t, params)
        else:
            lhs = lagrange_expression(mech, qq, qdot, qdd, t, params)
        return mm(B.T, lhs - mech.generalized_forces(qq, qdot, t, params))

    # a kept coordinate that is an independent one moves at its speed: its row of ∂q̇_C/∂x is a
    # unit vector, whatever the state (known when the partition is); the others by forward mode
    given = isinstance(part, tuple)
    slaved = tuple(j for j, i in enumerate(coordinates) if not (given and i in part))

    def coordinate_rates(x):
        qq = configuration(x[:nc])
        return pick(pick(split.velocities(qq, x[nc:], t, params, part), coordinates), slaved)

    xc0, v0 = pick(q, coordinates), split.independent_of(qd, part)
    x0 = jnp.concatenate([xc0, v0])
    n = x0.shape[0]
    if accelerations is None:
        # E is affine in v̇: its value at v̇ = 0 and the mass matrix give the operating accelerations
        E0, mass = value_and_jacfwd(lambda vd: E(xc0, v0, vd), jnp.zeros_like(v0))
        vd0 = solve_spd(mass, -E0)
    else:
        vd0 = accelerations
    E1, J = value_and_jacfwd(lambda z: E(z[:nc], z[nc:n], z[n:]), jnp.concatenate([x0, vd0]))
    stiffness, damping, mass = J[:, :nc], J[:, nc:n], J[:, n:]
    vd0 = vd0 - solve_spd(mass, E1)  # exact already unless `accelerations` was wrong
    qc_rate = jnp.zeros((nc,), x0.dtype)
    P = jnp.zeros((nc, n), x0.dtype)
    if given:
        for j, i in enumerate(coordinates):
            if i in part:
                qc_rate = qc_rate.at[j].set(v0[part.index(i)])
                P = P.at[j, nc + part.index(i)].set(1.0)
    if slaved:
        rate, jac = value_and_jacfwd(coordinate_rates, x0)
        qc_rate = qc_rate.at[jnp.asarray(slaved)].set(rate)
        P = P.at[jnp.asarray(slaved)].set(jac)
    A = jnp.concatenate([P, -solve_spd(mass, J[:, :n])], axis=0)
    rates = jnp.concatenate([qc_rate, vd0])
    out = (A, mass, damping, stiffness, rates, x0)
    if m and not mech.nonlinear_constraints and not checked:
        # constraints declared linear that are not would give a finite, wrong matrix: NaN instead
        # (the eager path raises a ValueError for this before, via `check_values`)
        affine = constraints_affine(mech, q, qd, t, params)
        out = tuple(jnp.where(affine, x, jnp.nan) for x in out)
    return (*out, quality, terms)


# evaluated a handful of times: XLA's cheapest settings
_linearize = one_shot_jit(_linearize_traced)


def lagrange_expression(mech: Mechanism, q, qd, qdd, t, params):
    """`d/dt ∂T/∂q̇ − ∂T/∂q = M q̈ + h` along (q̇, q̈), without forming M (s,)."""

    def gradients(q_, qd_, t_):  # ∂T/∂q and ∂T/∂q̇ from one reverse pass
        return jax.grad(mech.kinetic, argnums=(0, 1))(q_, qd_, t_, params)

    (dT_dq, _), (_, dp) = jax.jvp(gradients, (q, qd, t), (qd, qdd, jnp.ones_like(t)))
    return dp - dT_dq
