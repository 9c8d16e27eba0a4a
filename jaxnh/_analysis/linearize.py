"""Linearised equations of motion about an operating point, by `jax.jacfwd`.

The state is `x = (q_C, v)`: a chosen subset q_C of the coordinates (leave
out ignorable ones — a bicycle's position and heading, a wheel's rotation
angle — whose values do not enter the dynamics) and the independent
velocities v (speeds, for a mechanism with `kinematics`); the dependent
velocities follow from the constraints, `q̇ = B(q, t) v + β0(q, t)`, and the
other coordinates stay at their operating values.

A unit quaternion e (a `quaternions=` group of the mechanism) has three
degrees of freedom for four coordinates: it enters q_C as a rotation vector
δθ (3,), rad, in local coordinates of the rotation group,
`e = e0 ⊗ exp(δθ/2)` (δθ in the body axes of the operating orientation e0,
`frame="body"`) or `e = exp(δθ/2) ⊗ e0` (space axes, `frame="space"`), and
its value in x0 is 0. When the operating motion turns the body (a top
spinning about its axis), the chart is carried along by it: δθ measures the
orientation against the operating one, `exp(δθ/2) = e0(t)* ⊗ e(t)` (body;
`e(t) ⊗ e0(t)*` space), so that its rows of A are those of the error's
motion, `δθ̇ = δω − ω0 × δθ` for body-axes speeds ω with `frame="body"` —
not those of a chart held at e0, `δθ̇ = δω − ½ ω0 × δθ`, whose eigenvalues
are not the motion's (the top's nutation would come out wrong). At an
equilibrium the two coincide. Coordinates without a group are their own
chart (q_C = q_C0 + δq_C): the special case of one speed per coordinate.

The equations of motion projected on the independent velocities,

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

The derivatives are taken in parts, joined by the chain rule: the
configuration completed by `complete` and its derivatives in the kept
coordinates; the kinematics (q̇ = B v + β0 and β = q̈ at v̇ = 0, with their
Jacobians in (q, v), by one forward pass); and the dynamics (F = M q̈ + h − Q,
or ∂S/∂q̈ − Q, with its Jacobians in q, q̇ and q̈, by one forward pass).
Nested automatic differentiation makes large programs: for the Whipple
bicycle (8 coordinates, 5 constraints) the kinematics are some 9k traced
operations, the dynamics 7k, the checks of a concrete call 5k and the
configuration 1.4k. A concrete call compiles each part as a program of its own with
XLA's cheapest settings (`jaxnh._base.compile.ONE_SHOT`). They are compiled
once per structure and later calls reuse them (about 5 ms for the bicycle);
under a caller's `jit` the parts are traced into its program, and `jax.vmap`
over speeds or parameters works as usual.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Optional, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float

from jaxnh._base.compile import one_shot_jit
from jaxnh._base.host import as_data, as_float, as_time
from jaxnh._base.linalg import solve_spd, value_and_jacfwd
from jaxnh._base.status import is_traced
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._equations.split import (
    best_partition,
    choose_independent,
    partition_quality,
    pick,
    resolve_independent,
    VelocitySplit,
)
from jaxnh._equations.terms import mass_and_velocity_terms
from jaxnh._model.checks import constraints_affine
from jaxnh._model.mechanism import _state_terms, Mechanism
from jaxnh._model.rigid import quat_multiply, quaternion_from_axis_angle
from jaxnh._solve.diagnose import acceleration_energy_agrees, holonomic_consistent


__all__ = ["Linearization", "linearize"]

LINEAR_METHODS = ("lagrange", "appell")
FRAMES = ("body", "space")


class Linearization(eqx.Module):
    """The linearised motion about an operating point.

    Attributes:
        A: state matrix (n, n) for the state `x = (q_C, v)`; its rows for
            q_C are in units of 1/s (or rates of the coordinates), those for
            v in units of accelerations. A unit quaternion kept in q_C is
            three entries of x, the rotation vector δθ (rad) of the chart
            `e0 ⊗ exp(δθ/2)` (or `exp(δθ/2) ⊗ e0`, `linearize`'s `frame`).
        mass: `∂E/∂v̇` (k, k), the mass matrix for the independent velocities.
        damping: `∂E/∂v` (k, k), gyroscopic and non-conservative velocity terms.
        stiffness: `∂E/∂q_C` (k, n_C).
        rates: the state's rates of change ẋ at the operating point (n,):
            zero when it is an equilibrium or a steady motion. For a
            quaternion group, the angular velocity (rad/s) at which the
            operating orientation turns, in the chart's axes
            (`2 vec(e0* ⊗ ė0)` body, `2 vec(ė0 ⊗ e0*)` space): the chart
            follows it (a sleeping top: (0, 0, n)).
        state: the operating state x0 (n,) (0 for a quaternion's δθ).
        states: state names: coordinates (`"θx(<group>)"`, `"θy(…)"`, `"θz(…)"`
            for a quaternion group), then the independent speeds (`"d<name>"`
            when the speeds are q̇ or one per coordinate, else `speed_names`
            or `"u<i>"`).
        coordinates: indices of q_C in q (a quaternion group's four among
            them); speeds: indices of the independent velocities (speeds).
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

    def eigenvalues(self) -> jax.Array:
        """Eigenvalues of A (complex, unsorted), 1/s."""
        return jnp.linalg.eigvals(self.A)


def _indices(name, idx, s):
    out = tuple(int(i) for i in idx)
    if len(set(out)) != len(out) or not all(0 <= i < s for i in out):
        raise ValueError(f"linearize: `{name}` must be distinct indices in 0..{s - 1}; got {tuple(idx)!r}")
    return out


def _chart(mech: Mechanism, coordinates: tuple) -> tuple:
    """The kept coordinates as the entries of the local chart, in the order of `coordinates`: a
    1-tuple (i,) for a coordinate of its own (one entry of x), the 4-tuple of its group for a unit
    quaternion (three entries of x, δθ), placed where its first index appears. A group kept in
    part raises a ValueError naming `coordinates` (its four numbers are one orientation)."""
    groups = {i: tuple(g) for g in mech.quaternions for i in g}
    chart, seen = [], set()
    for i in coordinates:
        g = groups.get(i)
        if g is None:
            chart.append((i,))
        elif g not in seen:
            missing = tuple(j for j in g if j not in coordinates)
            if missing:
                raise ValueError(
                    f"linearize: `coordinates` keeps part of the unit quaternion {g} (quaternions=) but not "
                    f"{missing}: a quaternion is one orientation, three entries δθ of the state; keep all four "
                    "of its indices, or none (an orientation that does not enter the dynamics)."
                )
            seen.add(g)
            chart.append(g)
    return tuple(chart)


def _chart_size(chart: tuple) -> int:
    """The number of entries of x for the kept coordinates (3 per quaternion group)."""
    return sum(1 if len(c) == 1 else 3 for c in chart)


def _unit(dtype) -> np.ndarray:
    """The pure unit quaternions (0, e_a) (3, 4), a = x, y, z."""
    return np.eye(4, dtype=dtype)[1:]


def _turn(e, rotation, frame: str):
    """e ⊗ exp(δθ/2) (body) or exp(δθ/2) ⊗ e (space): e (4,) turned by the rotation vector δθ (3,),
    rad, through `jaxnh.rigid.quaternion_from_axis_angle`. Its axis δθ/|δθ| is taken at a safe
    norm (1 at δθ = 0, where the value is e and the derivative ½ e ⊗ (0, δθ̇), exactly)."""
    a2 = jnp.sum(rotation * rotation)
    zero = a2 == 0
    a = jnp.sqrt(jnp.where(zero, 1.0, a2))
    # at δθ = 0 the axis is undefined: there (1, δθ/2), exp's value and first derivative
    turn = quaternion_from_axis_angle(rotation / a, jnp.where(zero, 0.0, a))
    turn = jnp.where(zero, jnp.concatenate([jnp.ones((1,), e.dtype), 0.5 * rotation]), turn)
    return quat_multiply(e, turn) if frame == "body" else quat_multiply(turn, e)


def _retract(q, chart: tuple, xc, frame: str):
    """The configuration (n_q,) at the chart's entries xc: q with its kept coordinates set to
    xc's and its kept quaternion groups turned by their δθ (`_turn`)."""
    j = 0
    for c in chart:
        if len(c) == 1:
            q = q.at[c[0]].set(xc[j])
            j += 1
        else:
            q = q.at[np.asarray(c)].set(_turn(pick(q, c), xc[j : j + 3], frame))
            j += 3
    return q


def _local(q, chart: tuple):
    """The chart's entries at q itself (its operating point): the kept coordinates, 0 for δθ."""
    parts = [q[c[0]][None] if len(c) == 1 else jnp.zeros((3,), q.dtype) for c in chart]
    return jnp.concatenate(parts) if parts else q[:0]


def _tangent(q, chart: tuple, frame: str):
    """∂q/∂x_C (n_q, n_C) without holonomic completion: a unit column for a coordinate of its own,
    the columns ½ e ⊗ (0, e_a) (body) or ½ (0, e_a) ⊗ e (space) on a quaternion's group. With no
    quaternion groups, a constant (unit columns)."""
    n = q.shape[0]
    eye = np.eye(n, dtype=q.dtype)
    if all(len(c) == 1 for c in chart):
        return eye[:, [c[0] for c in chart]]
    cols = []
    for c in chart:
        if len(c) == 1:
            cols.append(eye[:, c[0] : c[0] + 1])
        else:
            e = pick(q, c)
            turned = [0.5 * (quat_multiply(e, w) if frame == "body" else quat_multiply(w, e)) for w in _unit(q.dtype)]
            cols.append(jnp.zeros((n, 3), q.dtype).at[np.asarray(c)].set(jnp.stack(turned, axis=1)))
    return jnp.concatenate(cols, axis=1)


def _multiplier(a, side: str):
    """The matrix (4, 4) of quaternion multiplication by a: `a ⊗ b = L b` (side "left") or
    `b ⊗ a = R b` (side "right")."""
    columns = [quat_multiply(a, w) if side == "left" else quat_multiply(w, a) for w in np.eye(4, dtype=a.dtype)]
    return jnp.stack(columns, axis=1)


def _conjugate(e):
    return e * np.array([1, -1, -1, -1], dtype=e.dtype)


def _chart_rates(chart: tuple, q, qdot, dq, dqdot, frame: str):
    """The chart's rows of A (n_C, n) and its rates at x0 (n_C,), from the coordinates' rates
    q̇ (n_q,), their derivatives ∂q/∂x (n_q, n) and ∂q̇/∂x (n_q, n).

    A coordinate of its own: its rows. A quaternion group e, in the chart carried along by the
    operating motion (`exp(δθ/2) = e0(t)* ⊗ e(t)`, body): `δθ̇ = 2 vec(ė0* ⊗ δe + e0* ⊗ δė)` to first
    order (space: `2 vec(δė ⊗ e0* + δe ⊗ ė0*)`), with δe = ∂e/∂x δx and δė = ∂ė/∂x δx; its rate, the
    angular velocity `2 vec(e0* ⊗ ė0)` (body) or `2 vec(ė0 ⊗ e0*)` (space), rad/s."""
    rows, rates = [], []
    side = "left" if frame == "body" else "right"
    for c in chart:
        if len(c) == 1:
            rows.append(dqdot[c[0]][None])
            rates.append(qdot[c[0]][None])
        else:
            e, ed = pick(q, c), pick(qdot, c)
            de, ded = pick(dq, c), pick(dqdot, c)
            turn = _multiplier(_conjugate(ed), side) @ de + _multiplier(_conjugate(e), side) @ ded
            rows.append(2 * turn[1:])
            rates.append(2 * (_multiplier(_conjugate(e), side) @ ed)[1:])
    if not rows:
        return dqdot[:0], qdot[:0]
    return jnp.concatenate(rows, axis=0), jnp.concatenate(rates)


def _chart_names(names: tuple, chart: tuple) -> tuple:
    """Names of the chart's entries: the coordinate's own, or θx, θy, θz of a quaternion group."""
    out = []
    for c in chart:
        if len(c) == 1:
            out.append(names[c[0]])
        else:
            group = ",".join(names[i] for i in c)
            out += [f"θ{a}({group})" for a in "xyz"]
    return tuple(out)


def linearize(
    mech: Mechanism,
    params: PyTree,
    q: ArrayInput,
    qd: ArrayInput,
    t: ArrayLike = 0.0,
    *,
    coordinates: Optional[Iterable[int]] = None,
    speeds: Optional[Iterable[int]] = None,
    method: str = "lagrange",
    complete: Optional[Callable[..., Any]] = None,
    accelerations: Optional[ArrayInput] = None,
    frame: str = "body",
    speed_names: Optional[Sequence[str]] = None,
) -> Linearization:
    """Linearise the motion of `mech` about the state (q, qd) at time t.

    Arguments:
        mech: the `Mechanism`.
        params: its parameters (a pytree; differentiable, batchable).
        q: operating coordinates (n_q,); its `quaternions=` groups unit
            quaternions (to √eps, as `simulate` requires of q0).
        qd: operating velocities (n_u,) — the speeds u for a mechanism with
            `kinematics`, q̇ otherwise; only the independent ones (`speeds`)
            are used, the dependent ones follow from the constraints.
        t: time, s.
        coordinates: indices of the coordinates kept in the state (default
            all); leave out ignorable ones. A unit quaternion is kept with
            all four of its indices (or left out with all four) and is three
            entries of the state, the rotation vector δθ (rad) of the chart
            `e = e0 ⊗ exp(δθ/2)`, carried along by the operating motion
            (see `frame`).
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
            perturbed configuration, e.g. `Mechanism.restore` to
            keep holonomic constraints satisfied.
        accelerations: the independent accelerations v̇ (k,) at the
            operating point, if known (zero for an equilibrium or a steady
            motion); saves one of two passes. `rates` reports the actual
            ones, so a wrong value shows there.
        frame: the axes of a quaternion's δθ: "body" (the operating
            orientation's body axes, `e0 ⊗ exp(δθ/2)`) or "space" (inertial
            axes, `exp(δθ/2) ⊗ e0`). Choose the axes of the angular-velocity
            speeds (`jaxnh.rigid.quaternion_rate`'s `frame`): a body that
            turns in the operating motion (a spinning top) then has
            equations with constant coefficients in δθ, whose eigenvalues
            are those of its motion (in the other axes they are periodic,
            and A is their value at t only). No effect without quaternions.
        speed_names: names of the n_u speeds for `states` (default: "d<name>"
            of the coordinate when the speeds are q̇ or one per coordinate
            without quaternions, else "u<i>").

    Returns:
        A `Linearization`. Invalid input raises a ValueError naming it when
        the values are concrete; under `jit`/`vmap`/`grad` constraints
        declared linear that are not (and NaN input, a singular mass matrix)
        give NaN matrices, never a finite wrong one. Two checks `simulate`
        makes of its initial state are made here of the operating state, by
        the same functions, whichever `method`: the mechanism's acceleration
        energy S, if it gives one, must agree with T at (q, qd, t)
        (`acceleration_energy_agrees`: otherwise "appell" and "lagrange"
        linearise two different motions), and the operating configuration
        (after `complete`) must satisfy the holonomic constraints
        (`holonomic_consistent`). A failure raises a ValueError naming
        `acceleration_energy` or the holonomic constraints and the fix, or
        under `jit`/`vmap`/`grad` makes every output NaN.
    """
    if method not in LINEAR_METHODS:
        raise ValueError(f"linearize: method must be one of {LINEAR_METHODS}; got {method!r}")
    if frame not in FRAMES:
        raise ValueError(f"linearize: frame must be one of {FRAMES} (the axes of a quaternion's δθ); got {frame!r}")
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    params = as_data(params, q)
    m = mech.check_shapes(q, qd, t, params)  # raises, naming the argument, for wrong shapes
    mech.check_finite(q, qd, t, params)  # NaN/inf raise here, naming the argument
    nq, s = q.shape[0], qd.shape[0]  # coordinates, speeds
    coordinates = tuple(range(nq)) if coordinates is None else _indices("coordinates", coordinates, nq)
    chart = _chart(mech, coordinates)
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
    if speed_names is not None and len(speed_names) != s:
        raise ValueError(f"linearize: `speed_names` must name the {s} speeds; got {len(speed_names)} names")
    # concrete input: the program also returns the terms of `Mechanism.check_values` at (q, qd), which
    # are judged on the host after it (a ValueError naming the problem), and leaves out its in-graph
    # copy of the check for constraints declared linear that are not
    checked = not is_traced(q, qd, t, params)
    args = (mech, params, q, qd, t, chart, speeds, method, complete, accelerations, checked, frame)
    # compiled once per structure with XLA's cheapest settings, in parts; traced into a caller's jit
    out = _linearize_traced(*args)
    A, mass, damping, stiffness, rates, x0, quality, terms, (agrees, on, unit) = out
    if checked and not bool(unit):
        raise ValueError(QUATERNION_NOT_UNIT)
    if checked:  # a mass matrix that is not positive definite, constraints declared linear that are not, ...
        mech._judge_state_terms(terms, constraint_rtol=float("inf"))
    if checked and not bool(on):
        raise ValueError(HOLONOMIC_VIOLATED)
    if checked and not bool(agrees):
        raise ValueError(ACCELERATION_ENERGY_MISMATCH)
    if checked and speeds is not None and m and not float(quality) > 1e3 * float(jnp.finfo(q.dtype).eps):
        raise ValueError(
            f"linearize: speeds={speeds}: the dependent velocities cannot be solved from the constraints "
            "at this state (the dependent block of ∂c/∂qd is singular); choose other speeds or pass "
            "speeds=None for an automatic choice."
        )
    names = mech.coordinate_names(nq)
    if speed_names is None:
        own = mech.kinematics is None or (s == nq and not mech.quaternions)  # one speed per coordinate
        speed_names = tuple("d" + n for n in names) if own else tuple(f"u{i}" for i in range(s))
    dnames = tuple(speed_names[i] for i in speeds) if speeds is not None else tuple(f"dv{j}" for j in range(s - m))
    states = _chart_names(names, chart) + dnames
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


def _linearize_traced(
    mech, params, q, qd, t, chart, speeds, method, complete, accelerations, checked=False, frame="body"
):
    """The linearisation from its compiled parts (the whole of it under a caller's `jit`, where the
    parts are traced into one program). `checked`: the values are concrete and checked on the host
    after the call, so the in-graph affinity test is left out, and the last three outputs are the
    quality of the given `speeds`' dependent block at (q, qd) (1 otherwise), for `linearize` to
    refuse a singular one, `_state_terms` at (q, qd) for `Mechanism._judge_state_terms` (None
    otherwise), and the verdicts of two checks `simulate` makes of its initial state: whether a
    given acceleration energy S agrees with T at (q, qd) (`acceleration_energy_agrees`) and whether
    the operating configuration (after `complete`) satisfies the holonomic constraints
    (`holonomic_consistent`), and whether its quaternion groups are of unit norm. Traced values
    cannot be refused on the host: a failed check makes every output NaN, never a finite
    linearisation of other equations or of an impossible state. `chart`: the kept coordinates
    (`_chart`); `frame`: the axes of a quaternion's δθ."""
    if complete is not None:
        q_op, dq_dc = _configuration(params, q, t, chart, complete, frame)
    else:
        q_op, dq_dc = q, _tangent(q, chart, frame)
    if checked:
        quality, terms, verdicts = _checks(mech, params, q, q_op, qd, t, speeds)
    else:
        quality, terms = jnp.ones((), q.dtype), None
        verdicts = _simulate_checks(mech, params, q, q_op, qd, t)
    # traced values cannot be checked on the host: the kinematics check in-graph that constraints
    # declared linear are, and come out NaN (and so everything after them) if they are not
    x0, K, dK = _kinematics(mech, params, q_op, dq_dc, qd, t, chart, speeds, not checked)
    if accelerations is None:
        vd = np.zeros(K[2].shape[1], q.dtype)
    else:
        vd = accelerations
    A, mass, damping, stiffness, rates, vd_next = _dynamics(mech, params, K, dK, vd, t, method, chart, frame)
    if accelerations is None:
        # E is affine in v̇: the first pass gives the operating accelerations, the second the
        # matrices there (and `rates`, one more correction, to show that they are right)
        A, mass, damping, stiffness, rates, _ = _dynamics(mech, params, K, dK, vd_next, t, method, chart, frame)
    out = (A, mass, damping, stiffness, rates, x0)
    if not checked and (mech.acceleration_energy is not None or mech.holonomic is not None or mech.quaternions):
        good = verdicts[0] & verdicts[1] & verdicts[2]
        out = jax.tree_util.tree_map(lambda x: jnp.where(good, x, jnp.nan), out)
    return (*out, quality, terms, verdicts)


ACCELERATION_ENERGY_MISMATCH = (
    "linearize: the mechanism's acceleration energy S (`acceleration_energy`) disagrees with its kinetic "
    "energy T at the operating state (q, qd, t): Appell's equations need ∂S/∂qdd = d/dt(∂T/∂qd) − ∂T/∂q, "
    "that is ∂²S/∂qdd² = M (the mass matrix ∂²T/∂qd²) and ∂S/∂qdd at qdd = 0 equal to the velocity terms "
    "of Lagrange's equations, to √eps of their scale; they do not (a mass counted twice, a centripetal or "
    "Coriolis term left out, a sign). method='appell' would linearise the equations from S and "
    "method='lagrange' those from T: two different motions (`simulate` refuses this mechanism too, with "
    "the status acceleration_energy_mismatch). Correct `acceleration_energy`, or leave it out of the "
    "Mechanism (jaxnh then builds S from T)."
)


QUATERNION_NOT_UNIT = (
    "linearize: a unit quaternion of q (the mechanism's `quaternions=` groups) is off unit norm by more "
    "than √eps: its chart e ⊗ exp(δθ/2) would turn a vector that is no orientation (`simulate` refuses "
    "such a q0 too, with the status quaternion_not_unit). Pass q with each group divided by its norm "
    "(e / jnp.linalg.norm(e)), or build it with jaxnh.rigid.quaternion_from_axis_angle."
)


HOLONOMIC_VIOLATED = (
    "linearize: the operating coordinates q do not satisfy the mechanism's holonomic constraints "
    "g(q, t) = 0 (to √eps of their scale; `mech.holonomic_residual(q, t, params)` tells how far off): "
    "the linearisation would be about a configuration the mechanism cannot take (`simulate` refuses such "
    "a q0 too, with the status holonomic_violated). Pass a q on the constraints — solve g(q) = 0 for the "
    "dependent coordinates, e.g. `mech.restore(q, t, params)` — or pass complete=mech.restore."
)


def _simulate_checks(mech, params, q, q_op, qd, t):
    """The verdicts of three checks `simulate` makes of its initial state, by the same tests:
    (a given acceleration energy S agrees with T at (q, qd, t) — `acceleration_energy_agrees`;
    the operating configuration q_op lies on g = 0 — `holonomic_consistent`; each quaternion
    group of q_op has unit norm to √eps, as `diagnose.speeds_checks` asks of q0), each True when
    the mechanism has no S, no holonomic constraints or no quaternions. No derivative flows
    through them."""
    q, q_op, qd, t, params = jax.lax.stop_gradient((q, q_op, qd, t, params))
    yes = jnp.ones((), bool)
    agrees = yes if mech.acceleration_energy is None else acceleration_energy_agrees(mech, q, qd, t, params)
    on = yes if mech.holonomic is None else holonomic_consistent(mech, q_op, t, params)
    unit = yes
    for g in mech.quaternions:
        norm = jnp.linalg.norm(pick(q_op, tuple(g)))
        unit = unit & (jnp.abs(norm - 1) <= jnp.sqrt(jnp.finfo(q.dtype).eps))
    return agrees, on, unit


def _checks_traced(mech, params, q, q_op, qd, t, speeds):
    """What `linearize` checks on the host at a concrete state: the quality of the given `speeds`'
    dependent block at (q, qd) (1 when they are chosen automatically), `_state_terms`, and the
    verdicts of `_simulate_checks` (S against T at (q, qd); the completed q_op on g = 0)."""
    s = qd.shape[0]
    m = mech.n_constraints(q, qd, t, params)
    terms = _state_terms(mech, q, qd, t, params)
    quality = jnp.ones((), q.dtype)
    if speeds is not None and m:
        quality = partition_quality(mech, q, qd, t, params, speeds, s - m, A=terms[2])[0]
    return quality, terms, _simulate_checks(mech, params, q, q_op, qd, t)


def _configuration_traced(params, q, t, chart, complete, frame):
    """The operating configuration completed by `complete(q, t, params)` (holonomic constraints
    re-solved) and its derivatives ∂q/∂x_C (n_q, n_C) in the chart's entries (`_retract`), by
    forward mode."""
    q = complete(q, t, params)
    return value_and_jacfwd(lambda xc: complete(_retract(q, chart, xc, frame), t, params), _local(q, chart))


def _kinematics_traced(mech, params, q, dq_dc, qd, t, chart, speeds, check_affine=False):
    """The velocity map at the operating configuration q and its first derivatives in the state.

    `dq_dc`: ∂q/∂x_C (n_q, n_C), how the configuration moves with the chart's entries. Returns the
    state x0 = (x_C, v) (n,), K = (q, u, B, β) (u the s velocities or speeds, β: u̇ at v̇ = 0) and
    their Jacobians dK/dx (`(n_q, n)`, `(s, n)`, `(s, n, k)`, `(s, n)`): what the constraints
    contribute, by one forward-mode pass over the n_q + k directions of (q, v), and the chain rule.
    `check_affine`: all of them NaN when constraints declared linear in the velocities are not
    (values that cannot be checked on the host: a finite, wrong linearisation otherwise)."""
    nq, s = q.shape[0], qd.shape[0]
    m = mech.n_constraints(q, qd, t, params)
    k = s - m
    split = VelocitySplit(mech, s, m)
    part = speeds if speeds is not None else best_partition(mech, q, qd, t, params, s, m)[0]

    # a constraint nonlinear in the velocities may have several roots: Newton's method starts at
    # the operating point's own dependent velocities, so the linearisation is about its root
    start = split.dependent_of(qd, part) if mech.nonlinear_constraints else None

    def velocities(z):
        return split.velocities_and_rates(z[:nq], z[nq:], t, params, part, start)

    v0 = split.independent_of(qd, part)
    (qdot, B, beta), (Jqdot, JB, Jbeta) = value_and_jacfwd(velocities, jnp.concatenate([q, v0]))
    nc = dq_dc.shape[1]
    # ∂(q, v)/∂x for x = (q_C, v)
    dz = jnp.concatenate(
        [
            jnp.concatenate([dq_dc, jnp.zeros((nq, k), q.dtype)], axis=1),
            jnp.concatenate([jnp.zeros((k, nc), q.dtype), jnp.eye(k, dtype=q.dtype)], axis=1),
        ],
        axis=0,
    )
    dK = (dz[:nq], Jqdot @ dz, jnp.einsum("sjk,jn->snk", JB, dz), Jbeta @ dz)
    out = (jnp.concatenate([_local(q, chart), v0]), (q, qdot, B, beta), dK)
    if check_affine and m and not mech.nonlinear_constraints:
        affine = constraints_affine(mech, q, qd, t, params)
        out = jax.tree_util.tree_map(lambda x: jnp.where(affine, x, jnp.nan), out)
    return out


def _dynamics_traced(mech, params, K, dK, vd, t, method, chart, frame="body"):
    """The linearised equations from the kinematics (`_kinematics_traced`) at independent
    accelerations v̇ (k,).

    With F(q, q̇, q̈) = M q̈ + h − Q (Lagrange's expression from T, or ∂S/∂q̈ − Q for "appell"),
    the projected equations are E(x, v̇) = Bᵀ F(q, q̇, B v̇ + β), and by the chain rule

        ∂E/∂x = Σ (∂B/∂x)ᵀ F + Bᵀ (F_q ∂q/∂x + F_q̇ ∂q̇/∂x + F_q̈ (∂B/∂x v̇ + ∂β/∂x)),
        ∂E/∂v̇ = Bᵀ F_q̈ B,

    with F's Jacobians from one forward-mode pass over (q, q̇, q̈) (in speeds: (q, u, u̇)). The rows of
    A for the chart's entries are those of `_chart_rates`. Returns the state matrix A, mass,
    damping, stiffness, the rates ẋ and the corrected accelerations v̇ − mass⁻¹ E."""
    q, qdot, B, beta = K
    dq, dqdot, dB, dbeta = dK
    nq, s = q.shape[0], qdot.shape[0]
    nc = _chart_size(chart)
    use_S = method == "appell" and mech.acceleration_energy is not None

    def F(z):
        qq, qd_, qdd = z[:nq], z[nq : nq + s], z[nq + s :]
        if use_S:
            lhs = jax.grad(mech.acceleration_energy, argnums=2)(qq, qd_, qdd, t, params)
        else:
            lhs = lagrange_expression(mech, qq, qd_, qdd, t, params)
        return lhs - mech.generalized_forces(qq, qd_, t, params)

    F0, JF = value_and_jacfwd(F, jnp.concatenate([q, qdot, B @ vd + beta]))
    Fq, Fqd, Fqdd = JF[:, :nq], JF[:, nq : nq + s], JF[:, nq + s :]
    E = B.T @ F0
    dqdd = jnp.einsum("snk,k->sn", dB, vd) + dbeta
    dE = jnp.einsum("snk,s->kn", dB, F0) + B.T @ (Fq @ dq + Fqd @ dqdot + Fqdd @ dqdd)
    mass = B.T @ Fqdd @ B
    stiffness, damping = dE[:, :nc], dE[:, nc:]
    vd_next = vd - solve_spd(mass, E)  # exact already unless the given accelerations were wrong
    if mech.kinematics is None:
        rate, drate = qdot, dqdot  # ∂q̇/∂x (unit rows for kept coordinates that are independent)
    else:  # q̇ = r(q, u): ∂q̇/∂x = r_q ∂q/∂x + r_u ∂u/∂x
        rate, (Rq, Ru) = mech.rate(q, qdot, t, params), jax.jacfwd(mech.rate, argnums=(0, 1))(q, qdot, t, params)
        drate = Rq @ dq + Ru @ dqdot
    P, chart_rates = _chart_rates(chart, q, rate, dq, drate, frame)
    A = jnp.concatenate([P, -solve_spd(mass, dE)], axis=0)
    rates = jnp.concatenate([chart_rates, vd_next])
    return A, mass, damping, stiffness, rates, vd_next


# evaluated a handful of times: XLA's cheapest settings, each part a program of its own; under a
# caller's jit they are one program
_checks = one_shot_jit(_checks_traced)
_configuration = one_shot_jit(_configuration_traced)
_kinematics = one_shot_jit(_kinematics_traced)
_dynamics = one_shot_jit(_dynamics_traced)


def lagrange_expression(mech: Mechanism, q, qd, qdd, t, params):
    """`d/dt ∂T/∂q̇ − ∂T/∂q = M q̈ + h` along (q̇, q̈), without forming M (s,). With speeds
    (`kinematics`), the Boltzmann–Hamel expression `M u̇ + h` (`speed_terms`)."""
    if mech.kinematics is not None:
        M, h = mass_and_velocity_terms(mech, q, qd, t, params)
        return M @ qdd + h

    def gradients(q_, qd_, t_):  # ∂T/∂q and ∂T/∂q̇ from one reverse pass
        return jax.grad(mech.kinetic, argnums=(0, 1))(q_, qd_, t_, params)

    (dT_dq, _), (_, dp) = jax.jvp(gradients, (q, qd, t), (qd, qdd, jnp.ones_like(t)))
    return dp - dT_dq
