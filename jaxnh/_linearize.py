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
bicycle (8 coordinates, 5 constraints) tracing and compiling one
linearisation takes tens of seconds on a CPU, evaluating it milliseconds.
Compile once (`jax.jit`, `jax.vmap` over speeds or parameters) and reuse.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .equations.base import as_float, as_time
from .equations.split import VelocitySplit, check_split, choose_independent, pick, solve_square
from .linalg import mm, solve_spd
from ._mechanism import Mechanism, check_independent

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
    speeds: tuple = eqx.field(static=True)

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
            (q, qd) — needs concrete values; pass it under `jit`/`vmap`).
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
        A `Linearization`.
    """
    if method not in LINEAR_METHODS:
        raise ValueError(f"linearize: method must be one of {LINEAR_METHODS}; got {method!r}")
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    m = mech.check_shapes(q, qd, t, params)  # raises, naming the argument, for wrong shapes
    mech.check_finite(q, qd, t, params)  # and for concrete NaN/inf
    s = q.shape[0]
    coordinates = tuple(range(s)) if coordinates is None else _indices("coordinates", coordinates, s)
    if speeds is None:
        speeds = mech.independent
    if speeds is None:
        speeds = choose_independent(mech, q, qd, t, params)
    speeds = check_independent(_indices("speeds", speeds, s), s, m)
    if complete is not None:
        q = complete(q, t, params)
    split = VelocitySplit.make(mech, s, m, speeds)
    check_split(mech, speeds, q, qd, t, params)
    nc = len(coordinates)
    use_S = method == "appell" and mech.acceleration_energy is not None

    def configuration(xc):
        qq = q
        for j, i in enumerate(coordinates):
            qq = qq.at[i].set(xc[j])
        return complete(qq, t, params) if complete is not None else qq

    velocities_and_rates = split.velocities_and_rates if mech.nonlinear_constraints else _LinearSplit(split).velocities_and_rates

    def E(xc, v, vd):
        """Bᵀ (M q̈ + h − Q) (or Bᵀ (∂S/∂q̈ − Q)) at q̈ = B v̇ + β."""
        qq = configuration(xc)
        qdot, B, beta = velocities_and_rates(qq, v, t, params)
        qdd = mm(B, vd) + beta
        if use_S:
            lhs = jax.grad(mech.acceleration_energy, argnums=2)(qq, qdot, qdd, t, params)
        else:
            lhs = lagrange_expression(mech, qq, qdot, qdd, t, params)
        return mm(B.T, lhs - mech.generalized_forces(qq, qdot, t, params))

    def coordinate_rates(x):
        qq = configuration(x[:nc])
        return pick(velocities_and_rates(qq, x[nc:], t, params)[0], coordinates)

    xc0, v0 = pick(q, coordinates), split.independent_of(qd)
    x0 = jnp.concatenate([xc0, v0])
    n, k = x0.shape[0], v0.shape[0]
    if accelerations is None:
        # E is affine in v̇: its value at v̇ = 0 and the mass matrix give the operating accelerations
        E0, mass = _value_and_jacobian(lambda vd: E(xc0, v0, vd), jnp.zeros_like(v0))
        vd0 = solve_spd(mass, -E0)
    else:
        vd0 = jnp.asarray(accelerations, dtype=q.dtype)
        if vd0.shape != (k,):
            raise ValueError(f"linearize: `accelerations` must have shape ({k},) (one per independent speed); got {vd0.shape}")
    E1, J = _value_and_jacobian(lambda z: E(z[:nc], z[nc:n], z[n:]), jnp.concatenate([x0, vd0]))
    stiffness, damping, mass = J[:, :nc], J[:, nc:n], J[:, n:]
    vd0 = vd0 - solve_spd(mass, E1)  # exact already unless `accelerations` was wrong
    qc_rate, P = _value_and_jacobian(coordinate_rates, x0)
    A = jnp.concatenate([P, -solve_spd(mass, J[:, :n])], axis=0)
    rates = jnp.concatenate([qc_rate, vd0])
    names = mech.coordinate_names(s)
    states = tuple(names[i] for i in coordinates) + tuple("d" + names[i] for i in speeds)
    return Linearization(
        A=A, mass=mass, damping=damping, stiffness=stiffness, rates=rates, state=x0,
        states=states, coordinates=coordinates, speeds=speeds,
    )


class _LinearSplit(eqx.Module):
    """Velocities from constraints linear in q̇, `A q̇ + a = 0`, with B and β written out.

    `q̇ = B v + β0` with `B = [I; −A_D⁻¹ A_I]` and the dependent part of β
    solving `A_D β_D = −b`, `b = (∂c/∂q) q̇ + ∂c/∂t` (so `A q̈ + b = 0`): the
    solve is never differentiated, which keeps nested derivatives small.
    """

    split: VelocitySplit

    def velocities_and_rates(self, q, v, t, params):
        split, mech = self.split, self.split.mech
        ind, dep = split.independent, split.dependent
        s = len(ind) + len(dep)
        if not dep:  # no constraints: q̇ = v
            return v, jnp.eye(s, dtype=q.dtype), jnp.zeros_like(v)
        zero = jnp.zeros((s,), q.dtype)
        a = mech.constraint(q, zero, t, params)
        A = jax.jacfwd(lambda u: mech.constraint(q, u, t, params))(zero)
        AD = jnp.stack([A[:, i] for i in dep], axis=1)
        AI = jnp.stack([A[:, i] for i in ind], axis=1)
        x = solve_square(AD, -(mm(AI, v) + a))
        qd = split.assemble(v, x)
        B = jax.vmap(lambda col, xcol: split.assemble(col, xcol), in_axes=(1, 1), out_axes=1)(
            jnp.eye(len(ind), dtype=q.dtype), solve_square(AD, -AI)
        )
        _, b = jax.jvp(lambda q_, t_: mech.constraint(q_, qd, t_, params), (q, t), (qd, jnp.ones_like(t)))
        beta = split.assemble(jnp.zeros_like(v), solve_square(AD, -b))
        return qd, B, beta


def lagrange_expression(mech: Mechanism, q, qd, qdd, t, params):
    """`d/dt ∂T/∂q̇ − ∂T/∂q = M q̈ + h` along (q̇, q̈), without forming M (s,)."""

    def momentum(q_, qd_, t_):
        return jax.grad(mech.kinetic, argnums=1)(q_, qd_, t_, params)

    _, dp = jax.jvp(momentum, (q, qd, t), (qd, qdd, jnp.ones_like(t)))
    return dp - jax.grad(mech.kinetic, argnums=0)(q, qd, t, params)


def _value_and_jacobian(f, x):
    """f(x) and ∂f/∂x by forward mode (one linearisation, n tangents)."""
    y, jvp = jax.linearize(f, x)
    return y, jax.vmap(jvp, in_axes=1, out_axes=1)(jnp.eye(x.shape[0], dtype=x.dtype))
