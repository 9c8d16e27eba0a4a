"""The solve of a mechanism with friction-held contacts: stick, slip, and the transitions between.

A `Mechanism(contacts=...)` names rows of its nonholonomic constraints that are
held by Coulomb friction (`jaxnh.FrictionContact`; each row is the slip
velocity of a contact point, m/s, its multiplier the tangential force, N).
The motion is piecewise smooth: between transitions every contact either

* **sticks**: its rows hold like any constraint, with the force the
  equations need, as long as that force is inside the static cone
  `‖λ‖ ≤ μs N`; or
* **slips**: its rows are released, and the kinetic force `−F ŵ` acts
  along them (ŵ the direction of the slip velocity w), of the size its law
  gives (`jaxnh.ContactLaw`): `F = μk N` for Coulomb's law, the default, or a
  function of the slip speed along ŵ (`_Friction.law_forces`).

How the equations change with the mode, with every shape fixed:

* Lagrange (`state (q, qd)`): the KKT system keeps all m rows; a released row
  is replaced by `λ_r = F_r`, the prescribed kinetic force (`_Friction.kkt`).
* Appell (`state (q, v, u)`): the dependent velocities are solved from all m
  rows written as `c(q, qd, t) = S u`, where u holds the slip velocities of
  the released friction rows (zero for engaged ones). The independent set of
  Appell's equations is then the independent velocities v *and* the slip
  velocities of the released rows (quasi-velocities); an engaged row's u stays
  0 (its equation is replaced by u̇ = 0). The partition of the real velocities
  is chosen afresh from ∂c/∂qd at the start of every segment.

A transition is an event of a diffrax solve, located by Newton's method on the
solver's interpolant: the guard of a sticking contact is its normalised
margin `(μs N − ‖λ‖)/(μs N + ‖λ‖)`, that of a slipping one its slip speed
along the segment's slip direction (normalised by the contact's velocity
scale); the event is the first time the smallest guard goes from ≥ 0 to < 0. At the
event the modes are decided again (`_Friction.resolve`): a contact whose
force left the cone slips, with the direction of the impending slip; a
contact whose slip stopped sticks if the force needed to hold it is inside
the cone, else slips on in the direction the force gives (reversed, for a
line contact). The solve is a `lax.scan` over `max_transitions + 1` segments,
each a `diffrax.diffeqsolve` from the traced event time of the previous one:
shapes are fixed, so it runs under `jit`, `vmap` (members with different
numbers of transitions) and `grad`, and the derivatives of event times pass
through the restarts (the saltation terms of the piecewise-smooth flow).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from jaxnh._base.compat import status_code
from jaxnh._base.compile import lean_jit, SOLVE
from jaxnh._base.linalg import (
    cholesky,
    mm,
    pick,
    solve_lower,
    solve_psd_min_norm,
    solve_spd,
    solve_square,
    solve_upper_t,
    value_and_jacfwd,
)
from jaxnh._base.status import error_for, is_traced, raise_in_graph, STATUS
from jaxnh._equations import Appell, Formulation, Lagrange
from jaxnh._equations.split import (
    best_partition,
    block_determinant,
    partition_from_dependent,
    partition_quality,
    permutation,
    place,
    select,
    split_regular,
    SWITCH_BELOW,
)
from jaxnh._equations.step_maps import normalize_quaternions, StepMaps, UnitQuaternions
from jaxnh._equations.terms import constraint_terms, mass_and_velocity_terms, projected_terms
from jaxnh._model.checks import (
    consistency_tolerance,
    constraint_row_checks,
    constraint_scale,
)
from jaxnh._model.contacts import ContactLaw, Coulomb
from jaxnh._model.mechanism import Mechanism
from jaxnh._solve.diagnose import first_failure, state_checks
from jaxnh._solve.outputs import all_finite, bcast, input_sum, nan_link, no_grad, run_checked
from jaxnh._solve.sensitivity import diffrax_solve, forward_mode_outputs, ForwardSensitivity
from jaxnh._solve.solution import Solution
from jaxnh._solve.stepping import coarse_interpolant


__all__ = [
    "ContactDiagnostics",
    "simulate_friction",
    "TRANSITION_KINDS",
    "STOP_CAUSES",
    "MAX_TRANSITIONS",
]

MAX_TRANSITIONS = 32
"""Default cap on the number of restarts of a friction solve (`simulate(max_transitions=...)`)."""

TRANSITION_KINDS = ("none", "stick→slip", "slip→stick", "slip reversal")
"""Names of the codes in `ContactDiagnostics.transition_kinds`: 1 the contact starts to slip, 2 it
locks again, 3 its slip stops and restarts in another direction (reversed, for a line contact)."""

ONSET, LOCK, REVERSAL = 1, 2, 3

STOP_CAUSES = (
    "none",
    "transition cap",
    "normal force reached zero",
    "normal force not finite",
    "μs not finite or below μk",
    "μk not finite or negative",
    "slip force of the contact law not finite or negative",
)
"""Names of the codes in `ContactDiagnostics.stop_cause`: why the contact `stopped_contact` stopped the solve."""

CAP, N_LOST, LAW_INVALID = 1, 2, 6

LOST_BELOW = 1e-6
"""At an event, a contact whose normal force is below this fraction of its value at the segment's start
(the normal-force guard) has lost it: the event is that guard's zero, located in time to ROOT_TOLERANCE."""

ROOT_TOLERANCE = 1e3
"""Transition times are located to ROOT_TOLERANCE · eps (relative and absolute, s)."""

NEWTON_NORMAL = 6
"""Newton steps for normal forces that are multipliers (`Multiplier`) when a contact's law is not affine in N
(`ContactLaw.affine_in_normal_force`); from N = 0, quadratic convergence."""

STOP_BELOW = 1e-4
"""A two-row contact whose slip speed along its slip direction reaches 0 has stopped when the rest of
its slip velocity is below this fraction of its velocity scale; otherwise its slip has turned by 90°
and goes on in the new direction (a slip reversal)."""


# --- results ----------------------------------------------------------------------------------------


class ContactDiagnostics(eqx.Module):
    """Per-contact diagnostics of a friction solve (`sol.contacts`); c = number of contacts.

    Arrays gain a leading batch axis under `vmap`. The methods that return lists
    (`transitions`, `slip_intervals`, `summary`) are for one unbatched solution.

    Attributes:
        KINDS: the names of the transition kinds, by code (`TRANSITION_KINDS`).
        STOP_CAUSES: the names of the codes of `stop_cause`.
        names: contact names (`FrictionContact.name`, or `contact <i>`).
        transition_times: (c, max_transitions), s: the times at which each
            contact changed mode, in order; +inf where unused.
        transition_kinds: (c, max_transitions) int: 1 stick→slip, 2 slip→stick,
            3 slip reversal (`TRANSITION_KINDS`); 0 where unused.
        segment_start, segment_end: (max_transitions + 1,), s: the time
            interval of each smooth segment of the solve (NaN for unused).
        segment_slipping: (max_transitions + 1, c) bool: which contacts slip
            during each segment.
        slip_time: (c,), s: total time slipping (differentiable: a sum of
            differences of event times).
        slip_fraction: (c,): slip_time over the duration of the run.
        slip_distance: (c,), m: ∫‖w‖ dt over the slip, w the slip velocity.
        dissipated_energy: (c,), J: energy dissipated by kinetic friction,
            ∫ F ‖w‖ dt, F the size of the kinetic force (μk N for Coulomb's law),
            integrated with the motion.
        peak_utilisation: (c,): the largest ‖λ‖/(μs N) while sticking, over
            the report times and the start and end of every segment (1 at a
            stick→slip transition); NaN for a contact that never sticks.
        min_margin: (c,), N: the smallest stick margin μs N − ‖λ‖ over the
            same instants (0 at a stick→slip transition).
        stopped_at: s, the time at which a contact stopped the solve (NaN if
            none did): the transition cap, or a contact value that became
            unphysical (`stop_cause`).
        stopped_contact: int, the contact that stopped the solve (−1 if none).
        stop_cause: int, why (`STOP_CAUSES`): 1 the transition cap, 2 the
            normal force fell to zero, 3 the normal force, 4 μs, 5 μk became
            NaN, inf or unphysical, 6 the contact's law gave a slip force that is
            NaN, inf or negative (0 if the solve was not stopped by a contact).
        initial_slipping: (c,) bool: which contacts slip at the start (the
            start is not a transition: `transitions` lists changes of mode only,
            and `slip_intervals` starts at ts[0] for such a contact).
        transitions_used: int, the number of restarts.
    """

    KINDS: ClassVar[tuple] = TRANSITION_KINDS
    STOP_CAUSES: ClassVar[tuple] = STOP_CAUSES

    names: tuple = eqx.field(static=True)
    transition_times: Float[Array, "c k"]
    transition_kinds: Int[Array, "c k"]
    segment_start: Float[Array, " K"]
    segment_end: Float[Array, " K"]
    segment_slipping: Bool[Array, "K c"]
    slip_time: Float[Array, " c"]
    slip_fraction: Float[Array, " c"]
    slip_distance: Float[Array, " c"]
    dissipated_energy: Float[Array, " c"]
    peak_utilisation: Float[Array, " c"]
    min_margin: Float[Array, " c"]
    stopped_at: Float[Array, ""]
    stopped_contact: Int[Array, ""]
    transitions_used: Int[Array, ""]
    stop_cause: Int[Array, ""]
    initial_slipping: Bool[Array, " c"]

    def _index(self, contact: int | str) -> int:
        if isinstance(contact, str):
            if contact not in self.names:
                raise ValueError(f"no contact named {contact!r}; the contacts are {self.names}")
            return self.names.index(contact)
        return int(contact)

    def transitions(self, contact: int | str = 0) -> list:
        """`[(time s, kind name), ...]` of one contact (index or name), in order: its changes of mode
        (a contact slipping at the start has no entry for it: see `initial_slipping`)."""
        j = self._index(contact)
        times = np.asarray(self.transition_times)[j]
        kinds = np.asarray(self.transition_kinds)[j]
        return [(float(t), TRANSITION_KINDS[int(k)]) for t, k in zip(times, kinds) if int(k) != 0]

    def slip_intervals(self, contact: int | str = 0) -> list:
        """`[(start s, end s), ...]`: the maximal time intervals during which a contact slips
        (a slip reversal does not end an interval)."""
        j = self._index(contact)
        t0, t1 = np.asarray(self.segment_start), np.asarray(self.segment_end)
        slipping = np.asarray(self.segment_slipping)[:, j]
        out: list = []
        for a, b, s in zip(t0, t1, slipping):
            if not (np.isfinite(a) and np.isfinite(b)) or not s:
                continue
            if out and out[-1][1] == a:
                out[-1] = (out[-1][0], float(b))
            else:
                out.append((float(a), float(b)))
        return out

    def summary(self) -> str:
        """A table of the diagnostics of each contact, one line each: transitions (changes),
        time slipping (s) and its share of the run (%), slip distance (m), energy dissipated by
        slip (J), peak |λ|/(μs N) while rolling, and the smallest stick margin (N)."""
        # (at most 90 columns for one contact named in 10 characters: a page or a terminal shows it whole)
        lines = [
            f"{'contact':<10} {'changes':>7} {'slip s':>9} {'slip %':>6} {'slip m':>9} "
            f"{'lost J':>9} {'peak |λ|/μsN':>12} {'margin N':>10}"
        ]
        for j, name in enumerate(self.names):
            n = len(self.transitions(j))
            lines.append(
                f"{name:<10} {n:>7d} {float(self.slip_time[j]):>9.4g} {100 * float(self.slip_fraction[j]):>6.3g} "
                f"{float(self.slip_distance[j]):>9.4g} {float(self.dissipated_energy[j]):>9.4g} "
                f"{float(self.peak_utilisation[j]):>12.4g} {float(self.min_margin[j]):>10.4g}"
            )
        return "\n".join(lines)

    def annotate(self, message: str, status: STATUS) -> str:
        """`message`, with the time, the contact and the cause when a contact stopped the solve."""
        if np.ndim(status_code(status)) != 0 or np.ndim(self.stop_cause) != 0:
            return message
        cause = int(np.asarray(self.stop_cause))
        if cause == 0:
            return message
        j = int(np.asarray(self.stopped_contact))
        name = self.names[j] if 0 <= j < len(self.names) else "?"
        return (
            f"{message} Stopped at t = {float(np.asarray(self.stopped_at)):.12g} s by contact {j} ({name!r}): "
            f"{STOP_CAUSES[cause]}."
        )


class Mode(eqx.Module):
    """The mode of every contact during one segment (c contacts, f friction rows in all).

    Attributes:
        slipping: (c,) bool.
        direction: (f,) the unit slip direction of each slipping contact, over its rows
            (for a line contact ±1); the kinetic force is −F along it (F = μk N for Coulomb's law).
        tau: (c,) m/s, a regularisation of the slip direction of a two-row contact
            (√eps of its velocity scale): the direction used is that of
            `(|w·d| + tau) d + w⊥`, exact where ‖w‖ ≫ tau and equal to d at w = 0.
        scale: (c,) m/s, the contact's velocity scale (`constraint_scale` of its rows).
        force_scale: (c,) N, |N| at the start of the segment (plus the smallest normal
            number): the scale of the normal-force guard.
    """

    slipping: Bool[Array, " c"]
    direction: Float[Array, " f"]
    tau: Float[Array, " c"]
    scale: Float[Array, " c"]
    force_scale: Float[Array, " c"]


# --- the equations of motion in a mode ------------------------------------------------------------


def _safe_norm(x):
    """‖x‖ with a finite derivative at x = 0 (its value there is √tiny, not 0)."""
    return jnp.sqrt(jnp.sum(x * x) + jnp.finfo(x.dtype).tiny)


def _law_force(law: ContactLaw, speed, N, mus, muk, q, qd, t, params):
    """(F, bad): the size of a law's kinetic force (N) at the slip speed `speed` (m/s), and whether the
    law's value there is NaN, inf or negative.

    The law is called at speeds ≥ 0 only. Below 0 (past the stop that ends a slip, where the steps that
    locate the stop evaluate the field) F is continued linearly with the law's slope at 0: value and slope
    agree at 0, so the field stays C¹ through the stop and the step that holds it is not cut by a kink.
    The slope is taken at a constant 0, so that a parameter derivative of it asks no derivative of the law
    in the speed beyond the first (v^δ with 1 < δ < 2 has an infinite second one at 0); an infinite slope
    (a law that violates `ContactLaw`'s requirements) is continued flat instead.
    """
    dtype = speed.dtype

    def force(v):
        return jnp.asarray(law.slip_force(v, N, mus, muk, q, qd, t, params), dtype).reshape(())

    ahead = speed >= 0
    value = force(jnp.where(ahead, speed, 0.0))
    at_rest, slope = jax.jvp(force, (jnp.zeros((), dtype),), (jnp.ones((), dtype),))
    slope = jnp.where(jnp.isfinite(slope), slope, 0.0)
    size = jnp.where(ahead, value, at_rest + slope * speed)
    return size, ~jnp.isfinite(value) | (value < 0)


class _Friction(eqx.Module):
    """A mechanism with contacts, bound to its sizes and to a formulation ("lagrange" or "appell").

    s is the number of velocities: the speeds u with `kinematics` (then every "qd" below is u,
    the rows and their multipliers are written in u, and the coordinates move with
    `Mechanism.rate`), else q̇; nq the number of coordinates (s without `kinematics`)."""

    mech: Mechanism
    s: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    independent: Optional[tuple] = eqx.field(static=True, default=None)
    nq: int = eqx.field(static=True, default=-1)

    @property
    def switching(self) -> bool:
        """Whether Appell's partition may change within a segment (no fixed `independent`): it is
        then carried in the state, as the m dependent indices (floats), and re-chosen before a step
        at which its dependent block has become ill-conditioned, as simulate's Appell form does
        (a block that turns with the body, such as rows written with body-axes angular speeds,
        passes through singular within a segment)."""
        return self.kind == "appell" and self.independent is None and self.m > 0

    def perm_in(self, y, perm):
        """The partition in use for the state y of Appell's form: the one carried in y when
        `switching`, else `perm` (the segment's)."""
        if not self.switching:
            return perm
        return partition_from_dependent(jnp.round(y[3]).astype(jnp.int32), self.s)

    @property
    def n_coordinates(self) -> int:
        """The number of coordinates (nq; s when not given)."""
        return self.s if self.nq < 0 else self.nq

    def rate(self, q, qd, t, params):
        """dq/dt (nq,) from the velocities (speeds): `Mechanism.rate`, the velocities themselves
        without `kinematics`."""
        return self.mech.rate(q, qd, t, params).astype(q.dtype)

    # static layout of the contacts
    @property
    def contacts(self) -> tuple:
        return self.mech.contacts

    @property
    def nc(self) -> int:
        return len(self.contacts)

    @property
    def flat(self) -> tuple:
        """The friction-held constraint rows, contact after contact."""
        return tuple(r for c in self.contacts for r in c.rows)

    @property
    def nf(self) -> int:
        return len(self.flat)

    @property
    def local(self) -> tuple:
        """For each contact, the positions of its rows in `flat`."""
        out, i = [], 0
        for c in self.contacts:
            out.append(tuple(range(i, i + len(c.rows))))
            i += len(c.rows)
        return tuple(out)

    @property
    def owner(self) -> tuple:
        return tuple(j for j, c in enumerate(self.contacts) for _ in c.rows)

    @property
    def held(self) -> tuple:
        """Rows that are not held by friction (always engaged)."""
        return tuple(i for i in range(self.m) if i not in self.flat)

    @property
    def k(self) -> int:
        return self.s - self.m

    def scatter(self, dtype):
        """The (m, f) matrix that puts friction-row values into constraint rows."""
        E = np.zeros((self.m, self.nf))
        for i, r in enumerate(self.flat):
            E[r, i] = 1.0
        return jnp.asarray(E, dtype=dtype)

    def released(self, slipping, dtype):
        """(f,) of `dtype`: 1 on the rows of slipping contacts, 0 on the others."""
        sl = slipping.astype(dtype)
        return jnp.stack([sl[j] for j in self.owner])

    def values(self, q, qd, t, params, multipliers=None):
        """(N, μs, μk), each (c,). A normal force that is a multiplier (`Multiplier`) is read from
        `multipliers` (m,), or is 1 (a placeholder) without them: see `mode_values`."""
        if multipliers is None and self.multiplier_normals:
            multipliers = jnp.ones((self.m,), qd.dtype)
        vals = [c.values(q, qd, t, params, multipliers) for c in self.contacts]
        return tuple(jnp.stack([v[i] for v in vals]).astype(qd.dtype) for i in range(3))

    def mode_values(self, q, qd, t, params, mode: "Mode"):
        """(N, μs, μk), each (c,), in `mode`: normal forces that are multipliers from the masked
        KKT system in that mode (the others as `values`)."""
        if not self.multiplier_normals:
            return self.values(q, qd, t, params)
        return self.kkt(q, qd, t, params, mode)[3]

    @property
    def multiplier_normals(self) -> bool:
        """Whether a contact's normal force is the multiplier of a constraint row (`Multiplier`)."""
        return any(c.normal_row is not None for c in self.contacts)

    @property
    def has_laws(self) -> bool:
        """Whether a contact has a law other than Coulomb's (a scene of Coulomb contacts only runs the
        operations it ran before laws existed, and nothing of theirs)."""
        return any(type(c.law) is not Coulomb for c in self.contacts)

    @staticmethod
    def invalid(N, mus, muk, law_bad=None):
        """(c,) int: 0 where the contact's values are physical, else the `STOP_CAUSES` code of the first
        value that is not (the normal force's sign is the normal-force guard's, not checked here).
        `law_bad` (c,) bool, where each contact's law gave a slip force that is not finite or negative
        (`law_forces`), comes last (None: Coulomb contacts only, whose force is μk N)."""
        bad_mus = ~jnp.isfinite(mus) | (mus < muk)
        bad_muk = ~jnp.isfinite(muk) | (muk < 0)
        code = jnp.where(~jnp.isfinite(N), 3, jnp.where(bad_mus & jnp.isfinite(muk), 4, jnp.where(bad_muk, 5, 0)))
        if law_bad is None:
            return code
        return jnp.where((code == 0) & law_bad, LAW_INVALID, code)

    def law_forces(self, w, mode: Mode, N, mus, muk, q, qd, t, params):
        """The size of each contact's kinetic force (c,), N, at its slip speed along the slip direction
        (`directions`: smooth through 0 for a two-row contact), and (c,) bool where its law's force is
        not finite or negative (Coulomb's contacts: μk N, and never: their values are `invalid`'s)."""
        along = self.directions(w, mode) * w
        sizes, bad = [], []
        for j, (c, idx) in enumerate(zip(self.contacts, self.local)):
            if type(c.law) is Coulomb:
                sizes.append(muk[j] * N[j])
                bad.append(jnp.asarray(False))
                continue
            size, b = _law_force(c.law, jnp.sum(pick(along, idx)), N[j], mus[j], muk[j], q, qd, t, params)
            sizes.append(size)
            bad.append(b)
        return jnp.stack(sizes), jnp.stack(bad)

    def law_codes(self, q, qd, t, params, mode: Mode):
        """(c,) int: the `STOP_CAUSES` code of a law whose slip force at (q, qd, t) in `mode` is not
        finite or negative, else 0."""
        if self.multiplier_normals:
            bad = self.kkt(q, qd, t, params, mode)[4]
        else:
            N, mus, muk = self.values(q, qd, t, params)
            _, bad = self.law_forces(self.slip(q, qd, t, params), mode, N, mus, muk, q, qd, t, params)
        if bad is None:  # (Coulomb's contacts only: their values are `invalid`'s)
            return jnp.zeros((self.nc,), jnp.int32)
        return jnp.where(bad, LAW_INVALID, 0)

    def force_at_rest(self, j: int, N, mus, muk, q, qd, t, params):
        """The size of contact j's kinetic force at slip speed 0, N (its law's; μk N for Coulomb's)."""
        law = self.contacts[j].law
        if type(law) is Coulomb:
            return muk[j] * N[j]
        v = jnp.zeros((), N.dtype)
        return jnp.asarray(law.slip_force(v, N[j], mus[j], muk[j], q, qd, t, params), N.dtype).reshape(())

    def slip(self, q, qd, t, params):
        """Slip velocities w of the friction rows (f,), m/s."""
        constraints = self.mech.constraints
        assert constraints is not None  # a mechanism with contacts has constraints (checked)
        return pick(jnp.asarray(constraints(q, qd, t, params)), self.flat)

    def directions(self, w, mode: Mode):
        """The unit direction of the slip velocity of each contact's rows (f,): for a line contact
        the segment's ±1; for a two-row contact that of `(|w·d| + tau) d + w⊥` (`Mode`), which is
        w/‖w‖ where ‖w‖ ≫ tau and stays smooth through the stop at which the segment ends."""
        out = []
        for j, idx in enumerate(self.local):
            d = pick(mode.direction, idx)
            if len(idx) == 1:
                out.append(d)
                continue
            wj = pick(w, idx)
            a = jnp.sum(wj * d)
            v = (jnp.abs(a) + mode.tau[j]) * d + (wj - a * d)
            # v/‖v‖ does not change with a positive factor: v is scaled to its largest entry first,
            # so that a slip released at rest (w = 0, tau = √eps × a velocity scale that is itself
            # ~√tiny there) gives d, not a vector that `_safe_norm`'s tiny shrinks towards 0
            v = v / jnp.maximum(jnp.max(jnp.abs(v)), jnp.finfo(v.dtype).tiny)
            out.append(v / _safe_norm(v))
        return jnp.concatenate(out)

    def kinetic(self, w, mode: Mode, N, mus, muk, q, qd, t, params):
        """Kinetic friction forces (f,), N, on the rows of slipping contacts (0 on the others), and (c,)
        bool where a contact's law gave a force that is not finite or negative (None when every contact
        follows Coulomb's law: then the force is −μk N along the slip direction, as it always was)."""
        law_bad = None
        if self.has_laws:
            sizes, law_bad = self.law_forces(w, mode, N, mus, muk, q, qd, t, params)
            size = jnp.stack([-sizes[j] for j in self.owner])
        else:
            size = jnp.stack([-muk[j] * N[j] for j in self.owner])
        # finite where a value is not: the field stays finite up to the guard that stops the solve there
        # (`validity`), so the step that meets the bad value is accepted and the event located
        size = jnp.where(jnp.isfinite(size), size, 0.0)
        return jnp.where(self.released(mode.slipping, w.dtype) > 0, size * self.directions(w, mode), 0.0), law_bad

    # Lagrange's equations with some rows released: the masked KKT system
    def kkt(self, q, qd, t, params, mode: Mode):
        """Accelerations qdd (s,), multipliers λ (m,) (the kinetic force on released rows),
        slip velocities w (f,), the contact values (N, μs, μk) and where the contacts' laws gave
        a bad force ((c,) bool, or None: `kinetic`).

        With M = L Lᵀ, W = L⁻¹ Aᵀ and the kinetic forces F as generalized forces
        `Aᵀ F`: `(WᵀW)_EE λ_E = −b_E − W_Eᵀ u`, `qdd = L⁻ᵀ (u + W_E λ_E)` over the
        engaged rows E (the others carry an identity so that every shape is fixed).

        A normal force that is the multiplier of an engaged row (`Multiplier`) depends on the
        kinetic forces, which depend on it: N = λ_n(F(N)). λ_n is affine in F, so for a law
        affine in N (Coulomb's, `Viscous`, `Stribeck`) the fixed point is one Newton step from
        N = 0, exact; other laws take `NEWTON_NORMAL` steps.
        """
        mech = self.mech
        M, h = mass_and_velocity_terms(mech, q, qd, t, params)
        L = cholesky(M)
        A, b = constraint_terms(mech, q, qd, t, params)
        w = self.slip(q, qd, t, params)
        E = self.scatter(qd.dtype)
        e = 1.0 - mm(E, self.released(mode.slipping, qd.dtype))
        u0 = solve_lower(L, mech.generalized_forces(q, qd, t, params) - h)
        W = solve_lower(L, A.T)
        S = mm(W.T, W) * e[:, None] * e[None, :] + jnp.diag(1.0 - e)

        def solve(Fm):  # (u, λ) with the kinetic forces Fm (m,) on the released rows
            u = u0 + mm(W, Fm)
            return u, solve_psd_min_norm(S, e * (-b - mm(W.T, u))) * e

        def forces(N, mus, muk):
            F, law_bad = self.kinetic(w, mode, N, mus, muk, q, qd, t, params)
            return mm(E, F), law_bad

        N, mus, muk = self.values(q, qd, t, params)
        if self.multiplier_normals:
            rows = [c.normal_row for c in self.contacts]
            taken = jnp.asarray([r is not None for r in rows])
            index = jnp.asarray([0 if r is None else r for r in rows])
            given = N

            def normals(Nm):  # the normal forces the motion needs when the kinetic forces follow Nm
                Nc = jnp.where(taken, Nm, given)
                lam = solve(forces(Nc, mus, muk)[0])[1]
                return jnp.where(taken, lam[index], given)

            affine = all(c.law.affine_in_normal_force for c in self.contacts)
            N = normals(jnp.zeros_like(given))
            eye = jnp.eye(self.nc, dtype=qd.dtype)
            for _ in range(1 if affine else NEWTON_NORMAL):
                r, J = value_and_jacfwd(normals, N)
                N = N - solve_square(eye - J, N - r)
            N = jnp.where(taken, N, given)
        Fm, law_bad = forces(N, mus, muk)
        if self.multiplier_normals and not affine and law_bad is not None:
            # a law not affine in N whose fixed point Newton's steps did not reach: reported as a bad law value
            eps = jnp.finfo(qd.dtype).eps
            off = jnp.abs(N - normals(N)) > jnp.sqrt(eps) * (jnp.abs(N) + jnp.finfo(qd.dtype).tiny)
            law_bad = law_bad | (taken & off)
        u, lam = solve(Fm)
        qdd = solve_upper_t(L, u + mm(W, lam))
        return qdd, lam + (1.0 - e) * Fm, w, (N, mus, muk), law_bad

    def contact_forces(self, lam):
        """λ of each contact's rows (list of (1,) or (2,) arrays), N."""
        return [pick(lam, c.rows) for c in self.contacts]

    def guards(self, q, qd, t, params, mode: Mode):
        """(2c,) normalised guards, positive while the mode holds. The first c: slip speed along the
        slip direction over the velocity scale (slipping); (μs N − ‖λ‖)/(μs N + ‖λ‖) (sticking).
        The last c, the contacts' validity: N over its scale at the segment's start where the values
        and the law's force are physical (`invalid`), else −1 (the solve stops there: a contact that
        loses its normal force has no lift-off in this model, and friction must never push)."""
        _, lam, w, (N, mus, muk), law_bad = self.kkt(q, qd, t, params, mode)
        bad = self.invalid(N, mus, muk, law_bad) != 0
        out = []
        for j, (lj, idx) in enumerate(zip(self.contact_forces(lam), self.local)):
            wj, d = pick(w, idx), pick(mode.direction, idx)
            along = jnp.sum(wj * d) / mode.scale[j]
            norm = jnp.abs(lj[0]) if lj.shape[0] == 1 else _safe_norm(lj)
            cone = mus[j] * N[j]
            margin = (cone - norm) / (cone + norm + jnp.finfo(q.dtype).tiny)
            out.append(jnp.where(bad[j], 1.0, jnp.where(mode.slipping[j], along, margin)))
        validity = jnp.where(bad, -1.0, N / mode.force_scale)
        return jnp.concatenate([jnp.stack(out), validity.astype(q.dtype)])

    def rates(self, w, F, mode: Mode):
        """(c, 2): slip speed (m/s) and dissipated power −F·w (W) of each slipping contact. The
        speed is w along the slip direction (`directions`): ‖w‖ during the slip, and smooth
        through the stop at which the segment ends (‖w‖ has a kink there that a step would see)."""
        along = self.directions(w, mode) * w
        out = []
        for j, idx in enumerate(self.local):
            speed = jnp.sum(pick(along, idx))
            power = -jnp.sum(pick(F, idx) * pick(w, idx))
            out.append(jnp.where(mode.slipping[j], jnp.stack([speed, power]), 0.0))
        return jnp.stack(out)

    # Appell's equations in the independent velocities and the released slip velocities
    def _appell_blocks(self, q, t, params, mode: Mode, perm):
        """a = c(q, 0, t) (m,), A (m, s), its independent and dependent columns, the scatter E and
        the released rows (f,)."""
        a, A = value_and_jacfwd(lambda x: self.mech.constraint(q, x, t, params), jnp.zeros((self.s,), q.dtype))
        AIt, ADt = select(A.T, perm, self.k)
        return a, A, AIt.T, ADt.T, self.scatter(q.dtype), self.released(mode.slipping, q.dtype)

    def appell_velocities(self, q, v, u, t, params, mode: Mode, perm):
        """qd (s,) from the independent velocities v (k,) and the slip velocities u (f,) of the
        released rows: `A_D qd_D = E u − A_I v − a`."""
        a, _, AI, AD, E, rel = self._appell_blocks(q, t, params, mode, perm)
        return place(v, solve_square(AD, mm(E, u * rel) - mm(AI, v) - a), perm)

    def appell_rates(self, q, v, u, t, params, mode: Mode, perm):
        """qd (s,), B (s, k + f) = ∂qd/∂(v, u), β = dqd/dt at fixed (v, u), and A = ∂c/∂qd (m, s)."""
        mech, k = self.mech, self.k
        a, A, AI, AD, E, rel = self._appell_blocks(q, t, params, mode, perm)
        rhs = (mm(E, u * rel) - mm(AI, v) - a)[:, None]
        X = solve_square(AD, jnp.concatenate([rhs, -AI, E * rel[None, :]], axis=1))
        qd = place(v, X[:, 0], perm)
        B = place(
            jnp.concatenate([jnp.eye(k, dtype=q.dtype), jnp.zeros((k, self.nf), q.dtype)], axis=1), X[:, 1:], perm
        )
        _, bvec = jax.jvp(
            lambda q_, t_: mech.constraint(q_, qd, t_, params), (q, t), (self.rate(q, qd, t, params), jnp.ones_like(t))
        )
        beta = place(jnp.zeros((k,), q.dtype), solve_square(AD, -bvec), perm)
        return qd, B, beta, A

    def appell_field(self, t, y, params, mode: Mode, perm):
        q, v, u = y[:3]
        perm = self.perm_in(y, perm)
        mech, k = self.mech, self.k
        qd, B, beta, A = self.appell_rates(q, v, u, t, params, mode, perm)
        rel = self.released(mode.slipping, q.dtype)
        w = u * rel
        N, mus, muk = self.values(q, qd, t, params)
        F, _ = self.kinetic(w, mode, N, mus, muk, q, qd, t, params)
        Q = mech.generalized_forces(q, qd, t, params) + mm(A.T, mm(self.scatter(q.dtype), F))
        if mech.acceleration_energy is None:
            K, r = projected_terms(mech, q, qd, t, params, B, beta)
            rhs = mm(B.T, Q) - r
        else:
            dS = jax.grad(mech.acceleration_energy, argnums=2)
            g0, H = jax.linearize(lambda a_: dS(q, qd, a_, t, params), beta)
            K = mm(B.T, jax.vmap(H, in_axes=1, out_axes=1)(B))
            rhs = mm(B.T, Q - g0)
        keep = jnp.concatenate([jnp.ones((k,), q.dtype), rel])
        K = K * keep[:, None] * keep[None, :] + jnp.diag(1.0 - keep)
        z = solve_spd(K, rhs * keep)
        code = (jnp.zeros_like(y[3]),) if self.switching else ()
        return (self.rate(q, qd, t, params), z[:k], z[k:], *code, self.rates(w, F, mode))

    def lagrange_field(self, t, y, params, mode: Mode):
        q, qd, _ = y
        qdd, lam, w, _, _ = self.kkt(q, qd, t, params, mode)
        F = pick(lam, self.flat) * self.released(mode.slipping, q.dtype)
        return (self.rate(q, qd, t, params), qdd, self.rates(w, F, mode))

    # the integrated state of a segment
    def state(self, q, qd, t, params, mode: Mode, perm, acc):
        if self.kind == "lagrange":
            return (q, qd, acc)
        w = self.slip(q, qd, t, params) * self.released(mode.slipping, q.dtype)
        code = (perm[self.k :].astype(q.dtype),) if self.switching else ()
        return (q, select(qd, perm, self.k)[0], w, *code, acc)

    def unpack(self, y, t, params, mode: Mode, perm):
        # unit quaternions rescaled, as simulate's formulations do (a report between steps: interpolated)
        q = normalize_quaternions(y[0], self.mech.quaternions)
        if self.kind == "lagrange":
            return q, y[1]
        return q, self.appell_velocities(q, y[1], y[2], t, params, mode, self.perm_in(y, perm))

    def partition(self, q, qd, t, params):
        if self.kind == "lagrange":
            return jnp.arange(self.s, dtype=jnp.int32)
        if self.independent is not None:
            return permutation(self.independent, self.s)
        return best_partition(self.mech, q, qd, t, params, self.s, self.m)[0]

    # the modes at a restart
    def _delassus(self, q, qd, t, params, engaged_rows, rows):
        """The effective compliance G (n, n) of the rows `rows` (1/kg in m/s per N·s) with the rows
        `engaged_rows` (m,) held: the inverse of the rows' block of the inverse of the masked WᵀW."""
        M, _ = mass_and_velocity_terms(self.mech, q, qd, t, params)
        L = cholesky(M)
        A, _ = constraint_terms(self.mech, q, qd, t, params)
        W = solve_lower(L, A.T)
        e = engaged_rows
        S = mm(W.T, W) * e[:, None] * e[None, :] + jnp.diag(1.0 - e)
        cols = jnp.stack([jax.nn.one_hot(r, self.m, dtype=q.dtype) for r in rows], axis=1)
        X = jax.vmap(lambda r: solve_psd_min_norm(S, r), in_axes=1, out_axes=1)(cols)
        P = jnp.stack([X[r] for r in rows])
        return jnp.linalg.inv(P)

    def resolve(self, q, qd, t, params, prev: Mode, fired, *, initial: bool):
        """The modes from (q, qd) at t (see the module docstring), and each contact's kind of
        transition (c,) int (0: unchanged).

        `fired` (c,) marks the contact whose guard crossed zero. At the start (`initial`),
        a contact whose rows are violated by more than the consistency tolerance slips
        along its slip velocity; the others stick unless the force they need is outside
        the static cone.
        """
        eps = float(jnp.finfo(q.dtype).eps)
        mech = self.mech
        c0, A = value_and_jacfwd(lambda x: mech.constraint(q, x, t, params), qd)
        a = mech.constraint(q, jnp.zeros_like(qd), t, params)
        row_scale = constraint_scale(A, qd, a)
        row_tol = consistency_tolerance(A, qd, a)
        w = pick(c0, self.flat)
        N, mus, muk = self.values(q, qd, t, params)  # (normal forces that are multipliers: from `kkt` below)
        tiny = jnp.finfo(q.dtype).tiny
        scale = jnp.stack([_safe_norm(pick(row_scale, c.rows)) for c in self.contacts]) + tiny
        tau = math.sqrt(eps) * scale
        force_scale = jnp.where(jnp.isfinite(N), jnp.abs(N), 1.0) + tiny
        rest, forced, direction = [], [], []
        for j, idx in enumerate(self.local):
            wj = pick(w, idx)
            nw = _safe_norm(wj)
            if initial:
                at_rest = nw <= _safe_norm(pick(row_tol, self.contacts[j].rows))
                rest.append(at_rest)
                forced.append(jnp.asarray(False))
                direction.append(jnp.where(at_rest, jnp.ones_like(wj) / math.sqrt(len(idx)), wj / nw))
                continue
            d = pick(prev.direction, idx)
            along = jnp.sum(wj * d)
            perp = _safe_norm(wj - along * d)
            was = prev.slipping[j]
            crossed = fired[j] | (along <= 0)
            # a two-row contact whose slip turned by 90° without stopping is redirected, not stopped
            stopped = was & crossed & ((len(idx) == 1) | (perp <= STOP_BELOW * scale[j]))
            redirected = was & crossed & ~stopped
            rest.append((~was & ~fired[j]) | stopped)
            forced.append(~was & fired[j])
            direction.append(jnp.where(redirected, wj / nw, d))
        rest, forced = jnp.stack(rest), jnp.stack(forced)
        engaged = rest | forced
        direction = list(direction)
        E = self.scatter(q.dtype)
        for it in range(self.nc + 1):
            mode = Mode(~engaged, jnp.concatenate(direction), tau, scale, force_scale)
            _, lam, _, (N, mus, muk), _ = self.kkt(q, qd, t, params, mode)
            forces = self.contact_forces(lam)
            viol = []
            for j, lj in enumerate(forces):
                norm = jnp.abs(lj[0]) if lj.shape[0] == 1 else _safe_norm(lj)
                out = engaged[j] & ((norm > mus[j] * N[j]) | (forced[j] if it == 0 else False))
                if lj.shape[0] == 1:
                    onset = jnp.where(lj != 0, -jnp.sign(lj), pick(jnp.concatenate(direction), self.local[j]))
                else:
                    rows_engaged = 1.0 - mm(E, self.released(~engaged, q.dtype))
                    G = self._delassus(q, qd, t, params, rows_engaged, self.contacts[j].rows)
                    onset = _onset_direction(lj, G, self.force_at_rest(j, N, mus, muk, q, qd, t, params))
                direction[j] = jnp.where(out, onset, direction[j])
                viol.append(out)
            engaged = engaged & ~jnp.stack(viol)
        new = Mode(~engaged, jnp.concatenate(direction), tau, scale, force_scale)
        if self.multiplier_normals:  # the normal forces' scale in the mode decided
            N = self.kkt(q, qd, t, params, new)[3][0]
            new = Mode(new.slipping, new.direction, tau, scale, jnp.where(jnp.isfinite(N), jnp.abs(N), 1.0) + tiny)
        if initial:
            return new, jnp.zeros((self.nc,), jnp.int32)
        changed_dir = jnp.stack([jnp.any(pick(new.direction, idx) != pick(prev.direction, idx)) for idx in self.local])
        kinds = jnp.where(
            ~prev.slipping & new.slipping,
            ONSET,
            jnp.where(prev.slipping & ~new.slipping, LOCK, jnp.where(new.slipping & changed_dir, REVERSAL, 0)),
        )
        return new, kinds.astype(jnp.int32)


def _onset_direction(lam, G, fk):
    """The direction d (unit, (2,)) in which a two-row contact starts to slip when released.

    With the force λ* it needed to hold and its compliance G, the slip acceleration under
    the kinetic force −fk d is G(−fk d − λ*), which must point along d:
    `(βI + fk G) d = −G λ*` for some β ≥ 0 with ‖d‖ = 1, a secular equation solved for β by
    Newton's method on 1/‖d(β)‖ − 1 (concave, so it converges monotonically from the lower
    bound it starts at). For an isotropic G, d = −λ*/‖λ*‖.
    """
    g = mm(G, lam)
    I2 = jnp.eye(2, dtype=lam.dtype)

    def x_of(beta):
        return -solve_square(beta * I2 + fk * G, g)

    beta0 = jnp.maximum(0.0, _safe_norm(g) - fk * jnp.sqrt(jnp.sum(G * G)))

    def newton(_, beta):
        x = x_of(beta)
        n = _safe_norm(x)
        dx = -solve_square(beta * I2 + fk * G, x)
        dphi = -jnp.sum(x * dx) / n**3
        step = (1.0 / n - 1.0) / jnp.where(dphi > 0, dphi, 1.0)
        return jnp.maximum(beta - step, 0.0)

    beta = jax.lax.fori_loop(0, 40, newton, beta0)
    x = x_of(beta)
    return x / _safe_norm(x)


# --- the solve ---------------------------------------------------------------------------------------


class _RootState(eqx.Module):
    lower: Any
    upper: Any
    positive_below: Any
    diff: Any
    done: Any


class _EventRootFinder(optx.AbstractRootFinder):
    """Newton's method on a scalar function of time, safeguarded by bisection, converged in t alone.

    diffrax gives the bracket [t_prev, t_next] of the step in which the guard changed sign.
    A Newton step that leaves the current bracket is replaced by its midpoint, so the
    iteration cannot diverge (grazing: a guard with a tiny slope at its root), and it stops
    when the step (or the bracket) is below `atol + rtol |t|` — with no test of the guard's
    value, whose scale is that of the contact (the optimistix root finders also ask
    |guard| < atol). The derivative of the root is optimistix's implicit one.
    """

    rtol: float
    atol: float
    norm: ClassVar[Any] = jnp.abs

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        lower = jnp.asarray(options["lower"], jnp.result_type(y))
        upper = jnp.asarray(options["upper"], jnp.result_type(y))
        f_lower, _ = fn(lower, args)
        inf = jnp.asarray(jnp.inf, jnp.result_type(y))
        return _RootState(lower, upper, f_lower > 0, inf, jnp.asarray(False))

    def step(self, fn, y, args, options, state: _RootState, tags):
        (f, aux), (df, _) = jax.jvp(lambda t: fn(t, args), (y,), (jnp.ones_like(y),))
        below = (f > 0) == state.positive_below
        lower = jnp.where(below, y, state.lower)
        upper = jnp.where(below, state.upper, y)
        newton = y - f / jnp.where(df != 0, df, 1.0)
        inside = (df != 0) & jnp.isfinite(newton) & (newton > lower) & (newton < upper)
        new_y = jnp.where(f == 0, y, jnp.where(inside, newton, 0.5 * (lower + upper)))
        scale = self.atol + self.rtol * jnp.abs(y)
        done = (f == 0) | (jnp.abs(new_y - y) < scale) | (upper - lower < scale)
        new_y = new_y.astype(jnp.result_type(y))
        return new_y, _RootState(lower, upper, state.positive_below, new_y - y, done), aux

    def terminate(self, fn, y, args, options, state: _RootState, tags):
        return state.done, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class _Args(eqx.Module):
    params: Any
    mode: Mode
    perm: Any
    ok: Any
    t_end: Any


class _Field(eqx.Module):
    system: _Friction

    def __call__(self, t, y, args: _Args):
        f = self.system
        if f.kind == "lagrange":
            dy = f.lagrange_field(t, y, args.params, args.mode)
        else:
            dy = f.appell_field(t, y, args.params, args.mode, args.perm)
        return jax.tree_util.tree_map(lambda d, x: jnp.where(args.ok, d, 0).astype(x.dtype), dy, y)


class _Guard(eqx.Module):
    system: _Friction

    def __call__(self, t, y, args: _Args, **kwargs):
        q, qd = self.system.unpack(y, t, args.params, args.mode, args.perm)
        g = self.system.guards(q, qd, t, args.params, args.mode)
        # the event is an up-crossing of −min(guards): from ≥ 0 (a guard exactly 0 at a restart
        # included) to < 0. A guard that starts at exactly 0 (the slip speed of a contact released
        # at rest) fires only if it then goes negative, never by growing from 0.
        # in the default float dtype: diffrax pairs it with a Python 0.0 in a `lax.cond`
        # a member that is not integrating (a failed check, or a finished solve whose segment runs under
        # vmap) gets a guard that never crosses zero (t ≤ t_end), with a nonzero slope
        idle = t - args.t_end - 1.0
        return jnp.where(args.ok, -jnp.min(g), idle).astype(jnp.result_type(float))


def _hermite_minimum(g0, g1, d0, d1):
    """The smallest value at an interior local minimum (s in (0, 1)) of the cubic Hermite polynomial
    with values g0, g1 and slopes d0, d1 (per unit s) at s = 0, 1; +inf where it has none. Elementwise."""
    # p'(s) = a s² + b s + d0
    a = 6 * (g0 - g1) + 3 * (d0 + d1)
    b = -6 * (g0 - g1) - 4 * d0 - 2 * d1
    disc = b * b - 4 * a * d0
    root = jnp.sqrt(jnp.maximum(disc, 0.0))
    safe_a = jnp.where(a != 0, a, 1.0)
    # the minimum is the root of p' where p'' = 2 a s + b > 0: s = (−b + √disc) / 2a (a ≠ 0), −d0/b (a = 0)
    s = jnp.where(a != 0, (-b + root) / (2 * safe_a), -d0 / jnp.where(b != 0, b, 1.0))
    has = (disc >= 0) & (s > 0) & (s < 1) & ((a != 0) | (b > 0))
    s = jnp.clip(s, 0.0, 1.0)
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    return jnp.where(has, h00 * g0 + h10 * d0 + h01 * g1 + h11 * d1, jnp.inf)


class _Watch(StepMaps):
    """Checks of every step of a segment.

    * No transition inside a step: a guard positive at both ends of a step may have crossed zero and
      come back within it (a slip that reverses and re-accelerates under the segment's frozen kinetic
      force, between two ends that both slip the old way; a force that leaves the cone and returns).
      Such a guard has a local minimum inside the step; the step is rejected unless the cubic through
      the guard's values and rates at both ends puts that minimum at no less than half the smaller end
      value. Steps near a guard's minimum so shrink until they resolve it: then a minimum below zero
      is an end of a step, where the event finds it, and a minimum above zero is accepted.
    * Appell's form: a step during which the dependent block changed sign (passed through
      singular) is rejected, and the partition re-chosen before a step at which the block has
      become ill-conditioned (`pre`), as in simulate's Appell form; with a fixed `independent`
      the partition cannot change, and such a step fails the solve.
    * Unit quaternions (`Mechanism.quaternions`): rescaled to unit norm at the end of every step,
      and the norm direction taken out of the step's error estimate, as in simulate's solve
      (`UnitQuaternions`, applied to the coordinates, the first part of the state).
    """

    system: _Friction

    def project_error(self, y1, y_error, args: _Args, /):
        """The step's error estimate without its components along each unit quaternion."""
        groups = self.system.mech.quaternions
        if not groups:
            return y_error
        dq = UnitQuaternions(None, groups).project_error(y1[0], y_error[0], args)
        return (dq, *y_error[1:])

    def pre(self, t, y, args: _Args, /):
        """Appell's form (`_Friction.switching`): the state with the partition re-chosen when the
        dependent block in use is below `SWITCH_BELOW` of the best one's volume (the independent
        velocities re-read from the velocities; the released rows' slip velocities are the rows'
        own and do not change), and whether it was."""
        f = self.system
        if not f.switching:
            return y, False
        q, v, w, _, acc = y
        perm = f.perm_in(y, args.perm)
        qd = f.appell_velocities(q, v, w, t, args.params, args.mode, perm)
        qs, qds, ts_, ps = no_grad((q, qd, t, args.params))
        ratio, _, best = partition_quality(f.mech, qs, qds, ts_, ps, perm, f.k)
        switch = (ratio < SWITCH_BELOW) & args.ok
        new = jnp.where(switch, best, perm)
        v_new = jnp.where(switch, select(qd, new, f.k)[0], v)
        return (q, v_new, w, new[f.k :].astype(y[3].dtype), acc), switch

    def _guards_and_rates(self, t, y, args: _Args):
        def g(t_, y_):
            q, qd = self.system.unpack(y_, t_, args.params, args.mode, args.perm)
            return self.system.guards(q, qd, t_, args.params, args.mode)

        ydot = _Field(self.system)(t, y, args)
        return jax.jvp(g, (t, y), (jnp.ones_like(t), ydot))

    def post(self, t0, y0, t1, y1, args: _Args, /):
        f = self.system
        if f.mech.quaternions:
            y1 = (normalize_quaternions(y1[0], f.mech.quaternions), *y1[1:])
        # a check: it decides a rejection, no derivative flows through it (and none is traced)
        t0s, y0s, t1s, y1s, args_s = no_grad((t0, y0, t1, y1, args))
        (g0, d0), (g1, d1) = self._guards_and_rates(t0s, y0s, args_s), self._guards_and_rates(t1s, y1s, args_s)
        h = jnp.asarray(t1s) - jnp.asarray(t0s)
        both = (g0 > 0) & (g1 > 0)
        low = _hermite_minimum(g0, g1, h * d0, h * d1)
        reject = jnp.any(both & (low < 0.5 * jnp.minimum(g0, g1))) & args_s.ok
        if f.kind != "appell":
            return y1, None, reject, False
        det = []
        perm = f.perm_in(y1s, args_s.perm)  # (the step's: a partition changes only before a step)
        for y, t in ((y0s, t0s), (y1s, t1s)):
            A = jax.jacfwd(lambda x: f.mech.constraint(y[0], x, t, args_s.params))(jnp.zeros((f.s,), y[0].dtype))
            det.append(block_determinant(A, perm, f.k))
        crossed = ((jnp.sign(det[0]) != jnp.sign(det[1])) | ~jnp.isfinite(det[1])) & args_s.ok
        if f.switching:  # rejected: the step shrinks until `pre` sees the block ill-conditioned
            return y1, None, reject | crossed, False
        return y1, None, reject, crossed


def _initial_checks(f: _Friction, q, qd, t, params):
    """(ok, STATUS) of the initial state: the checks every solve runs (`diagnose.state_checks`:
    mass matrix, S against T, speeds, q0 on g = 0), the constraint rows (all of them),
    consistency of the rows that friction does not hold, the contacts' values and, for Appell's
    form, a regular dependent block."""
    mech = f.mech
    checks, inertias = state_checks(mech, q, qd, t, params)
    rows = constraint_row_checks(mech, q, qd, t, params, f.held)
    A = rows.A
    N, mus, muk = f.values(q, qd, t, params)
    values_ok = jnp.all(f.invalid(N, mus, muk) == 0) & jnp.all(N >= 0)  # (the run's own check, and N ≥ 0)
    split_ok = jnp.asarray(True)
    if f.kind == "appell":  # (the test of simulate's Appell form: `Appell.check`)
        split_ok = split_regular(mech, q, qd, t, params, f.s, f.m, f.independent, A, inertias)
    return first_failure(
        (
            *checks,
            *rows.leading,
            (values_ok, STATUS.friction_values_invalid),
            (split_ok, STATUS.singular_split),
            *rows.trailing,
        )
    )


def _where_tree(cond, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(cond, x, y), a, b)


def _run_traced(
    f: _Friction,
    params,
    q0,
    qd0,
    ts,
    solver,
    controller,
    adjoint,
    dt0,
    *,
    record: tuple,
    max_steps: int,
    cap: int,
    graph_throw: bool,
):
    """The compiled friction solve (see the module docstring)."""
    dtype = q0.dtype
    n, nc = ts.shape[0], f.nc
    K = cap + 1
    finite = all_finite((q0, qd0, ts, params))
    increasing = jnp.all(jnp.diff(ts) > 0)
    q0r = jnp.where(finite, q0, 0.0)
    qd0r = jnp.where(finite, qd0, 0.0)
    tsr = jnp.where(finite & increasing, ts, jnp.arange(n, dtype=dtype))
    t0, t_end = tsr[0], tsr[-1]
    checked, check_status = _initial_checks(f, *no_grad((q0r, qd0r, t0, params)))
    ok = finite & increasing & checked
    status0 = STATUS.where(checked, STATUS.successful, check_status)  # pyright: ignore[reportArgumentType]
    status0 = STATUS.where(increasing, status0, STATUS.bad_report_times)
    status0 = STATUS.where(finite, status0, STATUS.non_finite_input)
    if graph_throw:
        q0r = raise_in_graph(q0r, status0)
    nan = jnp.full((), jnp.nan, dtype)
    ones = jnp.ones((nc,), dtype)
    dummy = Mode(jnp.zeros((nc,), bool), jnp.zeros((f.nf,), dtype), ones, ones, ones)
    # The modes carry no derivative: slipping flags are discrete, a line contact's direction is ±1,
    # and a two-row contact's direction enters the motion only where ‖w‖ ≲ tau (the kinetic force
    # follows w elsewhere) and the guard w·d only through w at its root, where w = 0.
    qs0, qds0, ts0, ps0 = no_grad((q0r, qd0r, t0, params))
    mode0, _ = f.resolve(qs0, qds0, ts0, ps0, dummy, jnp.zeros((nc,), bool), initial=True)
    if f.has_laws:  # the laws' forces at the start, in the modes the contacts start in
        laws_ok = jnp.all(f.law_codes(qs0, qds0, ts0, ps0, mode0) == 0)
        status0 = STATUS.where(ok & ~laws_ok, STATUS.friction_values_invalid, status0)  # pyright: ignore[reportArgumentType]
        ok = ok & laws_ok
        if graph_throw:
            q0r = raise_in_graph(q0r, status0)
    if f.multiplier_normals:  # normal forces from the motion: they press at the start, in the modes decided
        N0 = f.kkt(qs0, qds0, ts0, ps0, mode0)[3][0]
        pressing = jnp.all(jnp.isfinite(N0) & (N0 >= 0))
        status0 = STATUS.where(ok & ~pressing, STATUS.friction_values_invalid, status0)  # pyright: ignore[reportArgumentType]
        ok = ok & pressing
        if graph_throw:
            q0r = raise_in_graph(q0r, status0)
    mode0 = _where_tree(ok, mode0, dummy)
    if f.mech.quaternions:  # (unit to √eps, checked above: to rounding from here on, as in simulate)
        q0r = normalize_quaternions(q0r, f.mech.quaternions)
    tol = ROOT_TOLERANCE * float(jnp.finfo(dtype).eps)
    event = diffrax.Event(_Guard(f), root_finder=_EventRootFinder(rtol=tol, atol=tol), direction=True)
    maps = _Watch(f)
    field = _Field(f)
    acc0 = jnp.zeros((nc, 2), dtype)
    reports0 = (
        jnp.full((n, f.n_coordinates), jnp.nan, dtype),
        jnp.full((n, f.s), jnp.nan, dtype),
        jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), dummy),
        jnp.zeros((n,), bool),
    )
    carry0: dict[str, Any] = dict(
        t=t0,
        q=q0r,
        qd=qd0r,
        acc=acc0,
        mode=mode0,
        done=~ok,
        status=status0,
        reports=reports0,
        times=jnp.full((nc, cap), jnp.inf, dtype),
        kinds=jnp.zeros((nc, cap), jnp.int32),
        counts=jnp.zeros((nc,), jnp.int32),
        used=jnp.zeros((), jnp.int32),
        stopped_at=nan,
        stopped_contact=-jnp.ones((), jnp.int32),
        stop_cause=jnp.zeros((), jnp.int32),
        steps=jnp.zeros((3,), jnp.int32),
    )

    def work(carry: dict[str, Any], k) -> tuple[dict[str, Any], dict[str, Any]]:
        active = ~carry["done"]
        mode = carry["mode"]
        # a member that is not integrating (under vmap, `work` also runs for finished members) solves a
        # unit interval ending at t_end with a zero field and a guard that never fires (`_Field`, `_Guard`),
        # so no step of its discarded segment has zero length
        ta = jnp.where(active, carry["t"], t_end - 1.0)
        q, qd = carry["q"], carry["qd"]
        perm = f.partition(q, qd, ta, params)
        y0 = f.state(q, qd, ta, params, mode, perm, carry["acc"])
        args = _Args(params, mode, perm, ok & active, t_end)
        saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(ts=jnp.clip(tsr, ta, t_end)), diffrax.SubSaveAt(t1=True)])

        sol = diffrax_solve(
            field,
            solver,
            maps,
            y0,
            args,
            saveat,
            controller,
            t0=ta,
            t1=t_end,
            max_steps=max_steps,
            dt0=dt0,
            adjoint=adjoint,
            event=event,
        )
        # (with contacts, a ForwardSensitivity() given is served by ForwardMode: see simulate_friction)
        sol = forward_mode_outputs(sol, adjoint, "diffrax.ForwardMode() (or ForwardSensitivity(), which becomes it)")
        stats = jnp.stack(
            [sol.stats["num_steps"], sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"]]
        ).astype(jnp.int32)
        t1 = sol.ts[1][0]  # pyright: ignore[reportOptionalSubscript]
        y1 = jax.tree_util.tree_map(lambda x: x[0], sol.ys[1])  # pyright: ignore[reportOptionalSubscript]
        ys, result = sol.ys[0], STATUS.promote(sol.result)  # pyright: ignore[reportOptionalSubscript]
        fired = active & (result == STATUS.event_occurred)
        failed = active & ~fired & (result != STATUS.successful)
        # the reports that belong to this segment
        tr = jnp.clip(tsr, ta, t_end)
        reached = jnp.all(jnp.isfinite(ys[0]), axis=1)
        ysafe = jax.tree_util.tree_map(lambda x: jnp.where(bcast(reached, x), x, 0.0), ys)
        qr, qdr = jax.vmap(lambda y, t: f.unpack(y, t, params, mode, perm))(ysafe, tr)
        belong = active & ~failed & reached & (tsr >= ta) & jnp.where(fired, tsr < t1, tsr <= t1)
        old_q, old_qd, old_mode, old_in = carry["reports"]
        rep_mode = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), mode)
        reports = (
            jnp.where(belong[:, None], qr, old_q),
            jnp.where(belong[:, None], qdr, old_qd),
            jax.tree_util.tree_map(lambda a, b: jnp.where(bcast(belong, a), a, b), rep_mode, old_mode),
            old_in | belong,
        )
        # the end of the segment, and the modes after it
        t1s = jnp.where(jnp.isfinite(t1), t1, ta)
        y1s = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), y1)
        q1, qd1 = f.unpack(y1s, t1s, params, mode, perm)
        acc1 = y1s[-1]
        g = f.guards(q1, qd1, t1s, params, mode)
        j = jnp.argmin(g[:nc])  # the mode guards' scales differ (a slip released at rest: ~1/tiny)
        fired_mask = jnp.arange(nc) == j
        qs1, qds1, ts1, ps1, mode_s = no_grad((q1, qd1, t1s, params, mode))
        new_mode, kinds = f.resolve(qs1, qds1, ts1, ps1, mode_s, fired_mask, initial=False)
        # a validity guard (`guards`' last c) stops the solve: the normal force fell to zero, or a value
        # jumped to NaN, inf or an unphysical one (located to the root finder's tolerance, so it is read
        # at the event and just after it, where the value's own time dependence has crossed)
        probe = ts1 + 4 * tol * (1 + jnp.abs(ts1))
        bad = jnp.maximum(
            f.invalid(*f.mode_values(qs1, qds1, ts1, ps1, mode_s)),
            f.invalid(*f.mode_values(qs1, qds1, probe, ps1, mode_s)),
        )
        if f.has_laws:
            # a law's force can turn bad with the state (the slip speed) as well as with t: it is read at the
            # event and at the state carried on to the probe's time along the velocities and accelerations
            qdd1 = f.kkt(qs1, qds1, ts1, ps1, mode_s)[0]
            ahead = (qs1 + (probe - ts1) * f.rate(qs1, qds1, ts1, ps1), qds1 + (probe - ts1) * qdd1, probe)
            law = jnp.maximum(f.law_codes(qs1, qds1, ts1, ps1, mode_s), f.law_codes(*ahead, ps1, mode_s))
            bad = jnp.where(bad != 0, bad, law)
        any_bad = jnp.any(bad != 0)
        # N over its scale at the segment's start is 0 at its event to the root finder's tolerance in t
        zero_force = g[nc:] <= LOST_BELOW
        lost = fired & (any_bad | jnp.any(zero_force))
        lost_contact = jnp.where(any_bad, jnp.argmax(bad != 0), jnp.argmax(zero_force)).astype(jnp.int32)
        lost_cause = jnp.where(any_bad, jnp.max(bad), N_LOST).astype(jnp.int32)
        last = k == K - 1
        over = fired & last & ~lost
        apply = fired & ~last & ~lost
        counts = carry["counts"]
        slot = jnp.minimum(counts, cap - 1)
        changed = apply & (kinds != 0)
        rows = jnp.arange(nc)
        times = carry["times"].at[rows, slot].set(jnp.where(changed, t1s, carry["times"][rows, slot]))
        kinds_arr = carry["kinds"].at[rows, slot].set(jnp.where(changed, kinds, carry["kinds"][rows, slot]))
        status = carry["status"]
        status = STATUS.where(active & failed, result, status)
        if f.kind == "appell":
            status = STATUS.where(active & failed & (result == STATUS.singular), STATUS.singular_split, status)
        status = STATUS.where(over, STATUS.friction_transitions_exceeded, status)
        lost_status = STATUS.where(  # pyright: ignore[reportArgumentType]
            lost_cause == N_LOST, STATUS.contact_normal_force_lost, STATUS.contact_value_invalid
        )
        status = STATUS.where(lost, lost_status, status)
        stopped = over | lost
        new: dict[str, Any] = dict(
            t=jnp.where(active, t1s, carry["t"]),
            q=jnp.where(active, q1, q),
            qd=jnp.where(active, qd1, qd),
            acc=jnp.where(active, acc1, carry["acc"]),
            mode=_where_tree(apply, new_mode, mode),
            done=carry["done"] | ~apply,
            status=status,
            reports=reports,
            times=times,
            kinds=kinds_arr,
            counts=counts + changed.astype(jnp.int32),
            used=carry["used"] + apply.astype(jnp.int32),
            stopped_at=jnp.where(stopped, t1s, carry["stopped_at"]),
            stopped_contact=jnp.where(
                over, j.astype(jnp.int32), jnp.where(lost, lost_contact, carry["stopped_contact"])
            ),
            stop_cause=jnp.where(over, CAP, jnp.where(lost, lost_cause, carry["stop_cause"])),
            steps=carry["steps"] + jnp.where(active, stats, 0),
        )
        seg: dict[str, Any] = dict(
            start=jnp.where(active, ta, nan),
            end=jnp.where(active & ~failed, t1s, nan),
            slipping=mode.slipping & active,
            ends=(q, qd, ta, q1, qd1, t1s, mode, active & ~failed),
        )
        return new, seg

    def idle(carry: dict[str, Any], k) -> tuple[dict[str, Any], dict[str, Any]]:
        """A segment after the last: nothing changes (what `work` gives for a finished solve)."""
        q, qd, mode, te = carry["q"], carry["qd"], carry["mode"], t_end.astype(carry["t"].dtype)
        ends = (q, qd, te, q, qd, te, mode, jnp.zeros((), bool))
        seg: dict[str, Any] = dict(start=nan, end=nan, slipping=jnp.zeros_like(mode.slipping), ends=ends)
        return carry, seg

    def segment(carry: dict[str, Any], k) -> tuple[dict[str, Any], dict[str, Any]]:
        # the solve's segments stop early; the rest of the scan skips them (under vmap both branches
        # run, and `work` leaves a finished member unchanged too). `work` is rematerialised for reverse
        # mode: under vmap this cond becomes a select, which would batch every residual `work` saves,
        # among them the predicate of diffrax's own cond around its event root find ("did any member
        # have an event?"); batched, the backward pass would run that root find's transpose in
        # segments where no member had an event, on zero-filled residuals (an interpolant over
        # [0, 0]: a NaN cotangent that lineax refuses). Recomputed in the backward pass, the
        # predicate is unbatched again, as diffrax intends.
        return jax.lax.cond(carry["done"], idle, jax.checkpoint(work), carry, k)

    scanned: tuple[dict[str, Any], dict[str, Any]] = jax.lax.scan(segment, carry0, jnp.arange(K))
    final, segs = scanned
    q, qd, rep_mode, reached = final["reports"]
    status = final["status"]
    # outputs at the report times
    # the multipliers at the reports, and the utilisation of the sticking contacts at the reports and
    # at both ends of every segment, from one evaluation of the masked KKT system over all those states
    qa, qda, ta_, qb, qdb, tb, seg_mode, seg_ok = segs["ends"]
    qs = jnp.concatenate([jnp.where(reached[:, None], q, 0.0), qa, qb])
    qds = jnp.concatenate([jnp.where(reached[:, None], qd, 0.0), qda, qdb])
    tt = jnp.concatenate([tsr, ta_, tb])
    modes = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b, b]), rep_mode, seg_mode)

    def forces(q_, qd_, t_, md):
        _, lam, _, (N, mus, _), _ = f.kkt(q_, qd_, t_, params, md)
        norms = jnp.stack([jnp.abs(x[0]) if x.shape[0] == 1 else _safe_norm(x) for x in f.contact_forces(lam)])
        return lam, norms, mus * N

    lam_all, norms, cone = jax.vmap(forces)(qs, qds, tt, modes)
    sticking = jnp.concatenate([reached[:, None], seg_ok[:, None], seg_ok[:, None]]) & ~modes.slipping
    peak = jnp.max(jnp.where(sticking, norms / cone, -jnp.inf), axis=0)
    peak = jnp.where(jnp.isfinite(peak), peak, jnp.nan)
    min_margin = jnp.min(jnp.where(sticking, cone - norms, jnp.inf), axis=0)
    min_margin = jnp.where(jnp.isfinite(min_margin), min_margin, jnp.nan)
    out = {}
    if "multipliers" in record:
        out["multipliers"] = lam_all[:n]
    if "energy" in record:
        out["energy"] = jax.vmap(lambda a, b, t: f.mech.energy(a, b, t, params))(q, qd, tsr)
    if "residual" in record:
        out["residual"] = jax.vmap(lambda a, b, t: f.mech.constraint(a, b, t, params))(q, qd, tsr)
    dur = jnp.where(segs["slipping"], jnp.nan_to_num(segs["end"] - segs["start"])[:, None], 0.0)
    slip_time = jnp.sum(dur, axis=0)
    failed = status != STATUS.successful
    link = nan_link(failed, input_sum((params, q0, qd0)))

    def finish(x):
        x = jnp.where(bcast(reached, x), x, jnp.nan) if x.shape[:1] == (n,) else x
        return jnp.where(ok, x, jnp.nan) + link.astype(x.dtype)

    u = None
    if f.mech.has_speeds:  # the solve's velocities are the speeds; qd is dq/dt (at the reports reached)
        safe = jax.vmap(lambda a, b, t: f.rate(a, b, t, params))(
            jnp.where(reached[:, None], q, 0.0), jnp.where(reached[:, None], qd, 0.0), tsr
        )
        u, qd = qd, safe
    q, qd = finish(q), finish(qd)
    u = None if u is None else finish(u)
    out = {key: finish(v) for key, v in out.items()}
    if graph_throw:
        q, qd = raise_in_graph(q, status), raise_in_graph(qd, status)
        u = None if u is None else raise_in_graph(u, status)
        out = {key: raise_in_graph(v, status) for key, v in out.items()}
    diagnostics = ContactDiagnostics(
        names=tuple(c.label(i) for i, c in enumerate(f.contacts)),
        transition_times=final["times"],
        transition_kinds=final["kinds"],
        segment_start=segs["start"],
        segment_end=segs["end"],
        segment_slipping=segs["slipping"],
        slip_time=slip_time + link,
        slip_fraction=slip_time / (t_end - t0) + link,
        slip_distance=final["acc"][:, 0] + link,
        dissipated_energy=final["acc"][:, 1] + link,
        peak_utilisation=peak + link,
        min_margin=min_margin + link,
        stopped_at=final["stopped_at"],
        stopped_contact=final["stopped_contact"],
        stop_cause=final["stop_cause"],
        initial_slipping=mode0.slipping & ok,
        transitions_used=final["used"],
    )
    steps = final["steps"]
    stats = dict(
        num_steps=steps[0],
        num_accepted_steps=steps[1],
        num_rejected_steps=steps[2],
        max_steps=max_steps,
        segments=final["used"] + ok.astype(jnp.int32),
    )
    return Solution(
        ts=ts,
        q=q,
        qd=qd,
        speeds=u,
        multipliers=out.get("multipliers"),
        energy=out.get("energy"),
        residual=out.get("residual"),
        stats=stats,
        status=status,
        names=f.mech.coordinate_names(f.n_coordinates),
        slipping=rep_mode.slipping & reached[:, None],
        contacts=diagnostics,
    )


_run = lean_jit(_run_traced, compiler_options=SOLVE)


def simulate_friction(
    mech: Mechanism,
    form: Formulation,
    params,
    q0,
    qd0,
    ts,
    *,
    solver=None,
    stepsize_controller=None,
    record: tuple = (),
    saveat=None,
    event=None,
    progress_meter=None,
    adjoint=None,
    max_steps: int = 100_000,
    dt0=None,
    throw: bool = True,
    rtol: float = 1e-8,
    max_transitions: int = MAX_TRANSITIONS,
) -> Solution:
    """`simulate` for a mechanism with friction contacts (called by `simulate`, whose
    arguments have been checked and cast; see the module docstring).

    `max_transitions` caps the number of restarts (each a change of mode of one or more
    contacts); reaching it stops the solve with `STATUS.friction_transitions_exceeded`.
    `max_steps` applies to each smooth segment. The default adjoint is
    `diffrax.RecursiveCheckpointAdjoint()` (reverse mode); pass `adjoint=diffrax.ForwardMode()`
    for forward-mode derivatives (`jax.jvp`, `jax.jacfwd`).
    """
    if not isinstance(form, (Lagrange, Appell)):
        raise ValueError(
            f"method={form.name!r}: friction contacts need method='lagrange' or method='appell' (the "
            "substituted form has no contact forces to limit)"
        )
    if isinstance(form, Lagrange) and (form.baumgarte is not None or form.projection):
        raise ValueError(
            "stabilization is not available with friction contacts: each smooth segment is short and starts "
            "on the constraints; use method='appell' where drift matters"
        )
    if saveat is not None or event is not None or progress_meter is not None:
        raise ValueError(
            "with friction contacts, simulate reports at `ts` only: saveat=, event= and progress_meter= are not "
            "available (the solve is a sequence of segments that end at the contact's own events)"
        )
    if isinstance(form, Appell) and any(c.normal_row is not None for c in mech.contacts):
        names = ", ".join(c.label(i) for i, c in enumerate(mech.contacts) if c.normal_row is not None)
        raise ValueError(
            f"method='appell': the normal force of {names} is a constraint's multiplier (Multiplier), and "
            "Appell's equations eliminate the multipliers; use method='lagrange'"
        )
    if isinstance(form, Appell) and mech.nonlinear_constraints:
        raise ValueError("friction contacts with constraints nonlinear in the velocities need method='lagrange'")
    if not isinstance(max_transitions, (int, np.integer)) or max_transitions < 1:
        raise ValueError(f"max_transitions must be a positive integer; got {max_transitions!r}")
    if not hasattr(diffrax.Event(lambda t, y, args, **kw: 1.0), "direction"):
        raise RuntimeError("friction contacts need diffrax ≥ 0.7.2 (events with a direction)")
    if adjoint is None:
        adjoint = diffrax.RecursiveCheckpointAdjoint()
    elif isinstance(adjoint, ForwardSensitivity):
        # jaxnh's forward sensitivities (fit's choice) integrate no events: forward mode through
        # the discrete solve instead, which serves the same jvp/jacfwd
        adjoint = diffrax.ForwardMode()
    elif not isinstance(adjoint, diffrax.AbstractAdjoint):
        raise ValueError(
            "with friction contacts the derivatives go through the restarts of a diffrax solve: pass a diffrax "
            "adjoint (diffrax.RecursiveCheckpointAdjoint() for reverse mode, the default; diffrax.ForwardMode() "
            f"for jvp/jacfwd); got {type(adjoint).__name__}"
        )
    t0 = ts[0]
    m = mech.check_shapes(q0, qd0, t0, params)
    s = qd0.shape[0]  # velocities (speeds, with `kinematics`)
    if isinstance(form, Appell) and m > s:
        # (m = s is a mechanism that moves only while a contact slips: while all stick it has no
        # independent velocity, and the released rows' slip velocities are its quasi-velocities)
        raise ValueError(
            f"method='appell': the mechanism has m={m} constraints for s={s} coordinates, more than its "
            "velocities: the dependent-velocity block cannot be square; use method='lagrange'"
        )
    independent = form.independent if isinstance(form, Appell) else None
    if independent is None and isinstance(form, Appell):
        independent = mech.independent
    f = _Friction(mech, s, m, "lagrange" if isinstance(form, Lagrange) else "appell", independent, q0.shape[0])
    if solver is None:  # (simulate passes its default solver)
        solver = diffrax.Tsit5()
    if coarse_interpolant(solver) and not isinstance(stepsize_controller, diffrax.ConstantStepSize):
        # (as for simulate's events: a transition located on a third-order interpolant between long steps)
        raise ValueError(
            f"solver={type(solver).__name__}(): with friction contacts each change of mode is an event, located "
            "on the solver's interpolant, and this solver's is diffrax's third-order Hermite between long implicit "
            "steps, far less accurate than the requested tolerance. Use diffrax.Kvaerno3() or an explicit solver"
        )

    def run(graph_throw: bool) -> Solution:
        return _run(
            f, params, q0, qd0, ts, solver, stepsize_controller, adjoint, dt0, record=tuple(record),
            max_steps=int(max_steps), cap=int(max_transitions), graph_throw=graph_throw,
        )  # fmt: skip

    sol, traced = run_checked(run, is_traced(params, q0, qd0, ts), bool(throw))
    if throw and not traced and np.ndim(status_code(sol.status)) == 0 and not bool(sol.status == STATUS.successful):
        err = error_for(sol.status)
        raise type(err)(sol.message, sol.status)
    return sol
