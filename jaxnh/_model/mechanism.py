"""The description of a mechanism: energies, forces and constraints.

A `Mechanism` holds plain JAX functions written by the user. Every function
takes its arguments in the same order, `(q, qd, t, params)` (the acceleration
energy `(q, qd, qdd, t, params)`, the potential `(q, t, params)`), where

* `q`  — generalized coordinates, shape (s,), in their own units (m, rad);
* `qd` — generalized velocities dq/dt, shape (s,);
* `t`  — time, s;
* `params` — any pytree of parameters (dict, `eqx.Module`, ...).

Nothing here is differentiated yet: the formulations in `jaxnh._equations`
turn these functions into equations of motion by automatic differentiation.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, Optional, Sequence

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.experimental import checkify

from jaxnh._base.compile import one_shot_jit
from jaxnh._base.linalg import value_and_jacfwd
from jaxnh._model.checks import consistency_tolerance, consistent, nearly_dependent
from jaxnh._model.contacts import as_contacts, check_contact_shapes, check_contacts
from jaxnh._model.holonomic import check_dependent, Elimination, project


def _as_indices(x):
    return None if x is None else tuple(int(i) if isinstance(i, np.integer) else i for i in x)


def _as_groups(x) -> tuple:
    """`quaternions` as a tuple of 4-tuples of distinct coordinate indices (a ValueError otherwise)."""
    if x is None:
        return ()
    try:
        groups = tuple(tuple(g) for g in x)
    except TypeError:
        raise TypeError(
            f"Mechanism: `quaternions` must be groups of four coordinate indices, e.g. ((3, 4, 5, 6),); got {x!r}"
        ) from None
    flat = [i for g in groups for i in g]
    if any(len(g) != 4 for g in groups) or not all(
        isinstance(i, (int, np.integer)) and not isinstance(i, bool) and i >= 0 for i in flat
    ):
        raise ValueError(
            f"Mechanism: `quaternions` must be groups of four coordinate indices (w, x, y, z), e.g. "
            f"((3, 4, 5, 6),); got {x!r}"
        )
    if len(set(flat)) != len(flat):
        raise ValueError(f"Mechanism: `quaternions` groups must not share coordinates; got {x!r}")
    return tuple(tuple(int(i) for i in g) for g in groups)


__all__ = ["Mechanism"]


class Mechanism(eqx.Module):
    """A mechanism with nonholonomic constraints, described by its energies.

    Arguments:
        kinetic: kinetic energy `T(q, qd, t, params) -> scalar`, J. Its
            Hessian in `qd` is the mass matrix and must be positive definite.
            T may depend on t explicitly (rheonomic mechanisms).
        constraints: nonholonomic constraints `c(q, qd, t, params) -> (m,)`,
            each `c_k = 0` along the motion. Linear in the velocities
            (`A(q, t) qd + a(q, t) = 0`, paper eq. 1) or nonlinear, in which
            case the constraint forces follow Chetaev's rule: they are
            `Aᵀ λ` with `A = ∂c/∂qd`. Set `nonlinear_constraints=True` for
            nonlinear ones (the Appell formulation then solves for dependent
            velocities by Newton's method).
        forces: generalized non-potential forces `Q(q, qd, t, params) -> (s,)`
            (N for lengths, N·m for angles): the virtual work is `Q · δq`.
        potential: potential energy `V(q, t, params) -> scalar`, J.
        holonomic: holonomic constraints `g(q, t, params) -> (h,)` (each
            `g_j = 0` along the motion, in its own units, e.g. m for a
            contact height). They are imposed at the velocity level, as
            `ġ = (∂g/∂q) qd + ∂g/∂t = 0` appended to the nonholonomic
            constraints (`constraint` returns `[c, ġ]`), so every formulation,
            `fit`, `sweep` and `linearize` handle them with no extra code; the
            multipliers of the last h constraints are the holonomic constraint
            forces. q0 must satisfy g = 0 (`holonomic_residual` tells;
            `simulate` refuses a q0 off it). g itself is not enforced, only
            its rate: its error is the integral of the solver's errors and
            grows with the length of the run (a bead on a 1 m hoop under
            gravity, g = x² + y² − 1, for 3142 s at the default rtol 1e-8:
            |g| reached 2.0e-2 m² with `method="lagrange"`, 5.6e-6 with
            `"appell"` and 1.2e-6 with `stabilization="projection"`, which
            maps the velocities back onto ġ = 0 after every step).
            Give `dependent` to eliminate the dependent coordinates exactly
            instead.
        acceleration_energy: Gibbs–Appell acceleration energy
            `S(q, qd, qdd, t, params) -> scalar` (J/s²); used by
            `method="appell"` when given. Only its part that depends on
            `qdd` matters; it must be quadratic in `qdd`.
        names: names of the coordinates, e.g. `("phi1", "phi2")`.
        independent: default indices of the independent velocities for the
            Appell and substituted formulations (else chosen automatically
            from the constraint matrix at the initial state).
        nonlinear_constraints: whether `c` is nonlinear in `qd`. The Appell
            formulation then finds the dependent velocities by Newton's method
            started from zero, so write such constraints linear in the
            dependent velocities where possible (`qd2 − sqrt(qd0² + qd1²)`
            rather than `qd0² + qd1² − qd2²`, whose Jacobian vanishes at
            zero); Chetaev's rule gives the same constraint forces for both.
        contacts: friction-held constraint rows, a sequence of
            `jaxnh.FrictionContact` (default none: every constraint holds
            whatever force it takes). Each contact names rows of `constraints`
            written as slip velocities (m/s); they hold while the force they
            need is inside the static friction cone and slip otherwise
            (see the friction page of the documentation). With `kinematics`
            the rows, and the contacts' functions, take the speeds u.
        dependent: indices of h coordinates solved from the h holonomic
            constraints (the block `∂g/∂q_D` must be invertible along the
            motion). `simulate` (and so `fit` and `sweep`) then integrates only
            the other s − h coordinates and recovers these by Newton's method
            at every evaluation, so that g = 0 holds to Newton's accuracy and
            cannot drift; it reports all s coordinates. Newton's method starts
            at q0's dependent coordinates, which keeps the motion on the branch
            of g = 0 that q0 lies on. `reduced` gives the mechanism in the
            independent coordinates, `differentiated` the one without
            elimination. Default None: the holonomic constraints are imposed
            as ġ = 0, as described under `holonomic`.
        guess: `guess(q_I, t, params) -> (h,)`, where Newton's method starts
            for the dependent coordinates instead (and, in `coordinates` and
            `full_state` without a `start`, zeros when there is no guess).
        newton_iterations: Newton iterations for the dependent coordinates
            (quadratic convergence: 8 reach rounding from a reasonable start).
        newton_tol: largest accepted |g| after them (default √eps); a miss
            makes the state NaN, which `simulate` reports as a failure.
        kinematics: `qdot(q, u, t, params) -> (n_q,)`, the rates of the
            coordinates from *speeds* (quasi-velocities) u, affine in u. With
            it, every user function takes the speeds in place of the
            velocities: `T(q, u, t, params)`, `c(q, u, t, params)` (affine in
            u), `Q(q, u, t, params)` (generalized forces conjugate to u: their
            power is `Q · u`), `S(q, u, u̇, t, params)`; u may be shorter than
            q (a unit quaternion has four coordinates and three angular-velocity
            speeds). The equations of motion in the speeds (Boltzmann–Hamel's
            for Lagrange's form, Appell's in the quasi-accelerations) are
            derived from T and this map; see the "Bodies in space" page.
            Default None: u is q̇.
        quaternions: groups of coordinates that are unit quaternions (w, x, y,
            z), e.g. `((3, 4, 5, 6),)`. The solve keeps each at unit norm (it
            rescales them after every step, and the step-size control does not
            count the norm direction) and `simulate` refuses a q0 whose groups
            are not of unit norm to √eps. Needs `kinematics` whose quaternion
            rates are tangent to the unit sphere (`jaxnh.rigid.quaternion_rate`).
    """

    kinetic: Callable = eqx.field(static=True)
    constraints: Optional[Callable] = eqx.field(static=True, default=None)
    forces: Optional[Callable] = eqx.field(static=True, default=None)
    potential: Optional[Callable] = eqx.field(static=True, default=None)
    holonomic: Optional[Callable] = eqx.field(static=True, default=None)
    acceleration_energy: Optional[Callable] = eqx.field(static=True, default=None)
    names: Optional[tuple] = eqx.field(static=True, default=None)
    independent: Optional[tuple] = eqx.field(static=True, default=None)
    nonlinear_constraints: bool = eqx.field(static=True, default=False)
    contacts: tuple = eqx.field(static=True, default=(), converter=as_contacts)
    dependent: Optional[tuple] = eqx.field(static=True, default=None, converter=_as_indices)
    guess: Optional[Callable] = eqx.field(static=True, default=None)
    newton_iterations: int = eqx.field(static=True, default=8)
    newton_tol: Optional[float] = eqx.field(static=True, default=None)
    kinematics: Optional[Callable] = eqx.field(static=True, default=None)
    quaternions: tuple = eqx.field(static=True, default=(), converter=_as_groups)

    def __check_init__(self):
        if not callable(self.kinetic):
            raise TypeError(
                f"Mechanism: `kinetic` must be a function T(q, qd, t, params), got {type(self.kinetic).__name__}"
            )
        for name in ("constraints", "forces", "potential", "acceleration_energy"):
            f = getattr(self, name)
            if f is not None and not callable(f):
                raise TypeError(f"Mechanism: `{name}` must be a function or None, got {type(f).__name__}")
        if self.holonomic is not None and not callable(self.holonomic):
            raise TypeError(
                "Mechanism: `holonomic` must be a function g(q, t, params) or None, "
                f"got {type(self.holonomic).__name__}"
            )
        if self.names is not None and not all(isinstance(n, str) for n in self.names):
            raise TypeError(f"Mechanism: `names` must be a sequence of strings, got {self.names!r}")
        check_contacts(self.contacts)
        if self.contacts and self.constraints is None:
            raise ValueError("Mechanism: `contacts` hold rows of `constraints`, but no `constraints` were given")
        check_dependent(self.dependent, self.holonomic, self.independent)
        if self.dependent is not None and self.contacts:
            raise ValueError(
                "Mechanism: friction `contacts` with eliminated `dependent` coordinates are not supported; "
                "leave out `dependent` (the holonomic constraints are then imposed as ġ = 0)"
            )
        if self.guess is not None and not callable(self.guess):
            raise TypeError(f"Mechanism: `guess` must be a function guess(q_I, t, params), got {self.guess!r}")
        if self.kinematics is not None and not callable(self.kinematics):
            raise TypeError(
                f"Mechanism: `kinematics` must be a function qdot(q, u, t, params) or None, got {self.kinematics!r}"
            )
        if self.quaternions and self.kinematics is None:
            raise ValueError(
                "Mechanism: `quaternions` name coordinates whose rates come from angular-velocity speeds: give "
                "`kinematics=` too (e.g. with jaxnh.rigid.quaternion_rate), and write T in those speeds"
            )
        if self.kinematics is not None and self.dependent is not None:
            raise ValueError(
                "Mechanism: `dependent` coordinates with `kinematics` (speeds) are not supported; leave out "
                "`dependent` (the holonomic constraints are then imposed as ġ = 0)"
            )
        if not isinstance(self.newton_iterations, int) or self.newton_iterations < 1:
            raise ValueError(f"Mechanism: `newton_iterations` must be an integer ≥ 1; got {self.newton_iterations!r}")

    # --- evaluation helpers used by the formulations -------------------------

    def n_constraints(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object) -> int:
        """Number m of velocity constraints (static): nonholonomic plus differentiated holonomic ones."""
        return eqx.filter_eval_shape(lambda *a: self.constraint(*a), q, qd, t, params).shape[0]

    @property
    def has_speeds(self) -> bool:
        """Whether the velocities are speeds u with their own `kinematics` (else u is q̇)."""
        return self.kinematics is not None

    def rate(self, q: jax.Array, u: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        """dq/dt (n_q,) from the speeds u: `kinematics(q, u, t, params)`, or u itself without it."""
        if self.kinematics is None:
            return u
        return jnp.asarray(self.kinematics(q, u, t, params)).astype(jnp.result_type(q, u))

    def speeds_transpose(
        self, q: jax.Array, u: jax.Array, t: jax.typing.ArrayLike, params: object, f: jax.Array
    ) -> jax.Array:
        """`Kᵀ f` (n_u,), with K = ∂q̇/∂u (n_q, n_u): a covector f on the coordinates (such as ∂V/∂q) as
        one on the speeds (its power along u). f itself without `kinematics`."""
        if self.kinematics is None:
            return f
        _, pull = jax.vjp(lambda x: self.rate(q, x, t, params), u)
        return pull(f.astype(jnp.result_type(q, u)))[0]

    def constraint(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        """Velocity constraints `[c(q, qd, t), ġ(q, qd, t)]`, shape (m,); empty without constraints."""
        parts = []
        if self.constraints is not None:
            parts.append(jnp.asarray(self.constraints(q, qd, t, params)))
        holonomic = self.holonomic
        if holonomic is not None:
            _, gd = jax.jvp(
                lambda x, t_: jnp.asarray(holonomic(x, t_, params)),
                (q, jnp.asarray(t, q.dtype)),
                (jnp.asarray(self.rate(q, qd, t, params), q.dtype), jnp.ones((), q.dtype)),
            )
            parts.append(gd.astype(jnp.result_type(qd)))
        if not parts:
            return jnp.zeros((0,), jnp.result_type(qd))
        return parts[0] if len(parts) == 1 else jnp.concatenate(parts)

    def holonomic_residual(self, q: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        """g(q, t), shape (h,) (empty without holonomic constraints): how far q is off them."""
        if self.holonomic is None:
            return jnp.zeros((0,), jnp.result_type(q))
        return jnp.asarray(self.holonomic(q, t, params))

    # --- holonomic constraints solved for dependent coordinates ---------------

    def _elimination(self) -> Elimination:
        if self.dependent is None or self.holonomic is None:
            raise ValueError(
                "Mechanism: this needs `dependent=` (the coordinates solved from `holonomic`); none were given"
            )
        return Elimination(self.holonomic, self.dependent, self.guess, self.newton_iterations, self.newton_tol)

    def newton_start(self, start: Optional[jax.Array]) -> Optional[jax.Array]:
        """Where a solve that eliminates `dependent` starts Newton's method: `start` (q0's own
        dependent coordinates), or None (the `guess`) when the mechanism has a guess."""
        return None if self.guess is not None else start

    def free_coordinates(self, s: int) -> tuple:
        """Indices of the s − h independent coordinates (all s without `dependent`)."""
        dep = self.dependent or ()
        return tuple(i for i in range(s) if i not in dep)

    def coordinates(
        self, q_ind: jax.Array, t: jax.typing.ArrayLike, params: object, start: Optional[jax.Array] = None
    ) -> jax.Array:
        """All coordinates q (s,) from the independent ones q_I (s − h,), in their units.

        The dependent coordinates solve g(q, t) = 0 by Newton's method from
        `start` (default `guess`, else zeros). Differentiable in q_I, t (s) and
        the array leaves of params, to any order, by the implicit function
        theorem; NaN if Newton's method missed `newton_tol`.
        """
        return self._elimination().coordinates(q_ind, t, params, start)

    def full_state(
        self,
        q_ind: jax.Array,
        qd_ind: jax.Array,
        t: jax.typing.ArrayLike,
        params: object,
        start: Optional[jax.Array] = None,
    ) -> tuple[jax.Array, jax.Array]:
        """(q, qd), each (s,), from the independent coordinates q_I and their rates (g = 0, ġ = 0).

        `start`: where Newton's method starts for the dependent coordinates
        (default `guess`, else zeros).
        """
        return self._elimination().state(q_ind, qd_ind, t, params, start)

    def restore(self, q: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        """q (s,) with its dependent coordinates re-solved from the others (Newton from q's own q_D)."""
        return self._elimination().restore(q, t, params)

    def project(self, q: jax.Array, t: jax.typing.ArrayLike, params: object, iterations: int = 4) -> jax.Array:
        """The coordinates nearest to q (Euclidean, mixed units weighted alike) with g(q, t) = 0.

        Gauss–Newton, `iterations` steps; needs `holonomic` only. Use it on
        the drift of g in a simulation without `dependent`.
        """
        if self.holonomic is None:
            raise ValueError("Mechanism.project: the mechanism has no `holonomic` constraints to project onto")
        return project(self.holonomic, q, t, params, iterations)

    def differentiated(self) -> "Mechanism":
        """This mechanism without `dependent`: all s coordinates integrated, g imposed as ġ = 0."""
        return dataclasses.replace(self, dependent=None, guess=None)

    def reduced(self, s: int) -> "Mechanism":
        """The mechanism in the s − h independent coordinates q_I (s: the number of all coordinates).

        T, V, Q, S and c are those of this mechanism at `q = coordinates(q_I)`,
        `q̇ = (∂q/∂q_I) q̇_I + ∂q/∂t` (q̈ likewise); the generalized forces are
        `(∂q/∂q_I)ᵀ Q`. Names and `independent` are carried over. Cached: the
        same mechanism and s give the same object, so compiled programs are reused.
        """
        return _reduced(self, int(s), False)

    def reduced_from_start(self, s: int) -> "Mechanism":
        """`reduced(s)` taking `(params, start)` pairs for params: Newton's method for the
        dependent coordinates starts at `start` (h,) unless a `guess` was given.

        `simulate` integrates this with the start at q0's dependent coordinates, which keeps
        the motion on the branch of g = 0 that q0 lies on.
        """
        return _reduced(self, int(s), True)

    def generalized_forces(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        """Q(q, qd, t) − ∂V/∂q: all applied generalized forces, shape (s,)."""
        Q = jnp.zeros_like(qd)
        if self.forces is not None:
            Q = Q + jnp.asarray(self.forces(q, qd, t, params), dtype=qd.dtype)
        potential = self.potential
        if potential is not None:
            Q = Q - self.speeds_transpose(q, qd, t, params, jax.grad(lambda x: potential(x, t, params))(q))
        return Q

    def energy(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: object) -> jax.Array:
        """Total mechanical energy T + V, J."""
        E = self.kinetic(q, qd, t, params)
        if self.potential is not None:
            E = E + self.potential(q, t, params)
        return E

    def coordinate_names(self, s: int) -> tuple:
        """Names of the s coordinates (`q0`, `q1`, ... when none were given)."""
        return tuple(self.names) if self.names is not None else tuple(f"q{i}" for i in range(s))

    # --- validation ----------------------------------------------------------

    def check_shapes(
        self,
        q: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        qd: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        t: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        params: object,
        *,
        arguments: tuple[str, str] = ("q0", "qd0"),
    ) -> int:
        """Check output shapes of the user functions at trace time; return m.

        Raises ValueError naming the argument or the function at fault, what
        came (its type, or its shape) and what was expected. `arguments`: the
        names the caller's user gave q and qd (`simulate`'s q0 and qd0 by
        default), used in those messages. The answer depends only on the
        mechanism and the shapes and dtypes of the arguments, so it is
        remembered for them (tracing every user function costs ≈ 3 ms of
        Python per call).
        """
        key = _signature_key(self, q, qd, t, params)
        if key is not None and key in _SHAPES_CHECKED:
            return _SHAPES_CHECKED[key]
        m = self._check_shapes(q, qd, t, params, arguments)
        if key is not None:
            if len(_SHAPES_CHECKED) >= _SHAPES_CHECKED_MAX:
                _SHAPES_CHECKED.pop(next(iter(_SHAPES_CHECKED)))
            _SHAPES_CHECKED[key] = m
        return m

    def _check_shapes(self, q, qd, t, params, arguments=("q0", "qd0")) -> int:
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        self._check_state_shapes(q, qd, t, params, arguments)
        return self._check_outputs(q, qd, t, params)

    def _check_state_shapes(self, q, qd, t, params, arguments) -> None:
        """The lengths of q and qd against each other and against the mechanism; a ValueError
        naming the one that disagrees (`arguments`: their names for the user)."""
        qn, qdn = arguments
        batch = " (for a batch of states use jax.vmap or jaxnh.sweep over single states)"
        for x, name, what in ((q, qn, "coordinates"), (qd, qdn, "velocities")):
            if x.ndim != 1:
                raise ValueError(
                    f"{name} must be a vector of the {what}, shape (s,) with s the number of coordinates; "
                    f"got shape {x.shape}" + (batch if x.ndim > 1 else "")
                )
        nq, nqd = q.shape[0], qd.shape[0]
        if self.kinematics is not None:  # speeds: u may be shorter than q; `kinematics` must map it to q̇
            return
        if self.names is not None:
            s = len(self.names)
            source = f"names={tuple(self.names)!r}"
            if nq != s and nqd != s:
                raise ValueError(
                    f"{qn} and {qdn} have shapes ({nq},) and ({nqd},), but the Mechanism has s = {s} coordinates "
                    f"({source}): give {qn} and {qdn} shape ({s},) each, or correct the Mechanism's `names` "
                    "(one per coordinate)"
                )
            if nq != s:
                raise ValueError(
                    f"the coordinates {qn} have shape ({nq},), but the Mechanism has s = {s} coordinates "
                    f"({source}); expected {qn} of shape ({s},) ({qdn} has shape ({nqd},), which agrees)"
                )
            if nqd != s:
                raise ValueError(
                    f"the velocities {qdn} have shape ({nqd},), but qd must have the shape of q, ({s},): one "
                    f"velocity per coordinate ({source}; {qn} has shape ({nq},), which agrees)"
                )
            return
        if nq == nqd:
            return
        # no names: which length do the mechanism's functions accept? (only on this error path)
        works = {n: self._works_with(n, q.dtype, qd.dtype, t, params) for n in (nq, nqd)}
        if works[nq] and not works[nqd]:
            raise ValueError(
                f"the velocities {qdn} have shape ({nqd},), but qd must have the shape of q, ({nq},): one velocity "
                f"per coordinate (the mechanism's functions work with {nq} coordinates, as {qn} has; with {nqd} they "
                f"fail, index past the end or return the wrong shape); expected {qdn} of shape ({nq},)"
            )
        if works[nqd] and not works[nq]:
            raise ValueError(
                f"the coordinates {qn} have shape ({nq},), but the mechanism has s = {nqd} coordinates (its "
                f"functions work with {nqd}, as {qdn} has; with {nq} they fail, index past the end or return the "
                f"wrong shape); expected {qn} of shape ({nqd},)"
            )
        raise ValueError(
            f"{qn} has shape ({nq},) and {qdn} shape ({nqd},): they must have the same length s, one entry per "
            f"coordinate (qd must have the shape of q), and the mechanism's functions do not tell which is "
            f"right. Pass {qn} and {qdn} of the mechanism's length; Mechanism(names=...) lets this message "
            "say which one disagrees"
        )

    def _works_with(self, n: int, q_dtype, qd_dtype, t, params) -> bool:
        """Whether the mechanism's functions accept n coordinates: they return shapes that fit n,
        and index no coordinate or velocity beyond n (JAX clamps such an index silently, so it is
        looked for with `checkify`'s index checks, at q = qd = 0). Used only to word an error."""
        q, qd = jnp.zeros((n,), q_dtype), jnp.zeros((n,), qd_dtype)
        calls = [(self.kinetic, (q, qd, t, params))]
        calls += [(f, (q, qd, t, params)) for f in (self.constraints, self.forces) if f is not None]
        calls += [(f, (q, t, params)) for f in (self.potential, self.holonomic) if f is not None]
        try:
            self._check_outputs(q, qd, t, params)
            for f, args in calls:
                err, _ = checkify.checkify(f, errors=checkify.index_checks)(*args)
                if err.get() is not None:
                    return False
        except Exception:  # any failure of a user function at this length (or traced params): not known to work
            return False
        return True

    def _check_outputs(self, q, qd, t, params) -> int:
        """The shapes the user functions return at q, qd of shape (s,); return m."""
        s = qd.shape[0]  # (the number of velocities: the speeds, with `kinematics`)

        def out(fn, name, *args):
            try:
                return eqx.filter_eval_shape(fn, *args)
            except Exception as e:  # re-raise with the function named
                msg = f"Mechanism `{name}` failed when called with q, qd of shape ({s},): {e}"
                try:
                    err = type(e)(msg)
                except Exception:  # an exception type that takes other arguments
                    err = ValueError(msg)
                raise err from e

        if self.kinematics is not None:
            self._check_kinematics(q, qd, t, params, out)
        T = out(self.kinetic, "kinetic", q, qd, t, params)
        if getattr(T, "shape", None) != ():
            raise ValueError(
                f"Mechanism `kinetic` must return a scalar; got {_returned(T)}. T(q, qd, t, params) must "
                "return a JAX array of shape (): add up the terms, e.g. 0.5 * jnp.sum(J * qd ** 2) or "
                "0.5 * (J1 * qd[0] ** 2 + J2 * qd[1] ** 2)"
            )
        if not jnp.issubdtype(T.dtype, jnp.inexact):
            raise TypeError(
                f"Mechanism `kinetic` returned dtype {T.dtype}: T must be a floating-point scalar (it is "
                "differentiated twice for the mass matrix); compute it from the float velocities qd, "
                "e.g. 0.5 * J * qd[0] ** 2"
            )
        m, g = 0, None
        if self.constraints is not None:
            c = out(self.constraints, "constraints", q, qd, t, params)
            if not _is_vector(c):
                raise ValueError(
                    f"Mechanism `constraints` must return a vector of shape (m,); got {_returned(c)}. "
                    "c(q, qd, t, params) must return a JAX array with one value per constraint: build it "
                    "with jnp.stack([...]), e.g. jnp.stack([U21(t) * qd[0] - qd[1]]) for one constraint"
                )
            m = c.shape[0]
        if self.holonomic is not None:
            g = out(self.holonomic, "holonomic", q, t, params)
            if not _is_vector(g):
                raise ValueError(
                    f"Mechanism `holonomic` must return a vector of shape (h,); got {_returned(g)}. "
                    "g(q, t, params) must return a JAX array with one value per holonomic constraint: build "
                    "it with jnp.stack([...]), e.g. jnp.stack([q[0] ** 2 + q[1] ** 2 - 1.0])"
                )
            m += g.shape[0]
        if self.contacts:
            n_nh = m - (0 if g is None else g.shape[0])
            check_contact_shapes(self.contacts, n_nh, m, q, qd, t, params)
        if m > s:
            raise ValueError(
                f"Mechanism: m={m} constraints but there are only s={s} coordinates (nonholonomic and holonomic "
                "constraints together); expected m ≤ s"
            )
        if self.forces is not None:
            Q = out(self.forces, "forces", q, qd, t, params)
            if getattr(Q, "shape", None) != (s,):
                raise ValueError(
                    f"Mechanism `forces` must return shape ({s},); got "
                    + (str(tuple(Q.shape)) if _is_array(Q) else _returned(Q))
                    + f". Q(q, qd, t, params) must return a JAX array with one generalized force per "
                    f"coordinate (s = {s}): build it with jnp.stack([...]), with 0.0 for a coordinate "
                    "no force acts on"
                )
        if self.potential is not None:
            V = out(self.potential, "potential", q, t, params)
            if getattr(V, "shape", None) != ():
                raise ValueError(
                    f"Mechanism `potential` must return a scalar; got {_returned(V)}. V(q, t, params) must "
                    "return a JAX array of shape (): add up the terms, e.g. m * g * q[1]"
                )
        if self.acceleration_energy is not None:
            S = out(self.acceleration_energy, "acceleration_energy", q, qd, qd, t, params)
            if getattr(S, "shape", None) != ():
                raise ValueError(
                    f"Mechanism `acceleration_energy` must return a scalar; got {_returned(S)}. "
                    "S(q, qd, qdd, t, params) must return a JAX array of shape (): add up the terms"
                )
        if self.independent is not None:
            check_independent(self.independent, s, m)
        return m

    def _check_kinematics(self, q, u, t, params, out) -> None:
        """`kinematics` returns q̇ of q's shape, and the quaternion groups index q (at trace time)."""
        nq, nu = q.shape[0], u.shape[0]
        r = out(self.kinematics, "kinematics", q, u, t, params)
        if getattr(r, "shape", None) != (nq,):
            raise ValueError(
                f"Mechanism `kinematics` must return dq/dt of q's shape ({nq},); got "
                + (str(tuple(r.shape)) if _is_array(r) else _returned(r))
                + f". qdot(q, u, t, params) maps the {nu} speeds u to the rates of the {nq} coordinates"
            )
        for g in self.quaternions:
            if max(g) >= nq:
                raise ValueError(
                    f"Mechanism: quaternions={self.quaternions!r} name coordinate {max(g)}, but q has {nq} coordinates"
                )

    def check_finite(
        self,
        q: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        qd: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        t: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        params: object,
    ) -> None:
        """Raise a ValueError naming the argument (or the params leaf) that holds
        NaN or inf; traced values are skipped."""
        leaves = {"q": q, "qd": qd, "t": t}
        for name, x in leaves.items():
            if _is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
                raise ValueError(f"{name} must be finite; got {np.asarray(x)}")
        for path, leaf in jax.tree_util.tree_leaves_with_path(params):
            if isinstance(leaf, (jax.Array, np.ndarray, float)) and _is_concrete(leaf):
                a = np.asarray(leaf)
                if np.issubdtype(a.dtype, np.inexact) and not np.all(np.isfinite(a)):
                    raise ValueError(f"params{jax.tree_util.keystr(path)} must be finite; got {a}")

    def check_values(
        self,
        q: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        qd: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        t: jax.typing.ArrayLike | Sequence[jax.typing.ArrayLike],
        params: object,
        *,
        constraint_rtol: Optional[float] = None,
    ) -> None:
        """Value checks at a concrete state (skipped for traced values).

        Non-finite inputs, a mass matrix that is not positive definite, and
        initial velocities that violate the constraints each raise a
        ValueError that says what came and what was expected.
        """
        self.check_finite(q, qd, t, params)
        if not all(_is_concrete(x) for x in (q, qd, t)) or not _params_concrete(params):
            return
        self._judge_state_terms(_initial_state_terms(self, q, qd, t, params), constraint_rtol=constraint_rtol)

    def _judge_state_terms(self, terms, *, constraint_rtol: Optional[float] = None):
        """The ValueErrors of `check_values`, from `_state_terms` evaluated at the state (by a
        program of the caller's that computes them along with its own results)."""
        M, c, A, affine, near, allowed, on_manifold = (np.asarray(x) for x in terms)
        if not np.all(np.isfinite(M)):
            raise ValueError(f"Mechanism `kinetic`: the mass matrix ∂²T/∂qd² at the initial state is not finite:\n{M}")
        # Cholesky's accuracy does not depend on the scaling of the coordinates
        # (van der Sluis), so the test is on the Jacobi-scaled matrix D^-½ M D^-½:
        # J1/J2 = 1e6 is fine even in float32, a near-singular coupling is not.
        d = np.diag(M)
        eig = np.linalg.eigvalsh(0.5 * (M + M.T))
        scaled = np.linalg.eigvalsh(0.5 * (M + M.T) / np.sqrt(np.outer(np.abs(d), np.abs(d)) + np.finfo(M.dtype).tiny))
        if np.any(d <= 0) or (
            scaled.min() <= 1e3 * np.finfo(M.dtype).eps * max(abs(scaled).max(), np.finfo(M.dtype).tiny)
        ):
            raise ValueError(
                "Mechanism `kinetic`: the mass matrix ∂²T/∂qd² at the initial state is not positive "
                f"definite, or singular to {M.dtype} precision (eigenvalues {eig}; after scaling to a "
                f"unit diagonal {scaled}); expected all eigenvalues > 0. Check the inertia parameters"
                + (", or use float64." if M.dtype == np.float32 else ".")
            )
        if self.constraints is None:
            return
        if not np.all(np.isfinite(c)):
            raise ValueError(f"Mechanism `constraints` is not finite at the initial state: c = {c}")
        if not np.all(np.isfinite(A)):
            raise ValueError(
                f"Mechanism `constraints`: ∂c/∂qd at the initial state is not finite:\n{A}\n"
                "(a constraint not differentiable there, e.g. sqrt or abs of a velocity at 0)"
            )
        # each constraint on its own velocity scale, as the compiled check judges it (the same
        # functions, evaluated in the program of `_initial_state_terms`)
        if bool(near):
            sv = np.linalg.svd(A / np.linalg.norm(A, axis=1)[:, None], compute_uv=False)
            raise ValueError(
                "Mechanism `constraints`: the rows of ∂c/∂qd at the initial state are nearly dependent "
                f"(singular values of the row-normalised matrix {sv}; "
                "one lies between 1e2 eps and 1e-5 of the largest; 0.09 in float32). Whether the near-repeat "
                "binds is decided by rounding: write a repeated constraint identically or leave it out, or "
                "reformulate the constraints so that their rows are well apart."
            )
        if constraint_rtol is None and not bool(on_manifold):
            raise ValueError(
                f"qd0 violates the nonholonomic constraints: |c(q0, qd0, t0)| = {np.abs(c)}; expected ≤ {allowed} "
                "(√eps × each constraint's velocity scale ‖∂c_k/∂qd‖ · ‖the velocities it involves‖ + "
                "|c_k(q0, 0, t0)|, plus rounding), and a smallest correction onto the constraints of at most "
                "10 times those allowances. "
                "Use jaxnh.consistent_velocities to project qd0 onto the constraints."
            )
        if not self.nonlinear_constraints and not bool(affine):
            raise ValueError(
                "Mechanism `constraints` is nonlinear in qd (∂²c/∂qd² ≠ 0 at the initial state); "
                "pass nonlinear_constraints=True to Mechanism."
            )


def _state_terms(mech: Mechanism, q, qd, t, params):
    """Mass matrix, constraint values and ∂c/∂qd at one state, and the compiled checks' verdicts on
    them (constraints declared linear in qd are; rows nearly dependent; each row's allowance for
    |c|; qd on the constraints):
    what `Mechanism._judge_state_terms` needs, to be traced into one program (the checks alone
    eagerly were some 40 programs)."""
    q, qd = jnp.asarray(q), jnp.asarray(qd)
    M = jax.hessian(lambda v: mech.kinetic(q, v, t, params))(qd)

    def c(v):
        return mech.constraint(q, v, t, params)

    c0, A = value_and_jacfwd(c, qd)
    a = c0 - A @ qd
    return (
        M,
        c0,
        A,
        # affine in qd: ∂²c/∂qd² negligible against ∂c/∂qd (judged here: only the verdict leaves)
        ~(
            jnp.max(jnp.abs(jax.jacfwd(jax.jacfwd(c))(qd)), initial=0.0)
            > 1e-8 * jnp.maximum(1.0, jnp.max(jnp.abs(A), initial=0.0))
        ),
        nearly_dependent(A),
        consistency_tolerance(A, qd, a),
        consistent(A, c0, qd, a),
    )


# run once per check: XLA's cheapest settings
_initial_state_terms = one_shot_jit(_state_terms)


_SHAPES_CHECKED: dict = {}
_SHAPES_CHECKED_MAX = 256


def _signature(x):
    if hasattr(x, "shape") and hasattr(x, "dtype"):
        return ("array", tuple(x.shape), str(x.dtype))
    return ("value", type(x).__name__, x)


def _signature_key(mech, q, qd, t, params):
    """A hashable key of everything `check_shapes` depends on, or None if there is none."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    key = (mech, _signature(q), _signature(qd), _signature(t), treedef, tuple(_signature(x) for x in leaves))
    try:
        hash(key)
    except TypeError:
        return None
    return key


@functools.lru_cache(maxsize=64)
def _reduced(mech: Mechanism, s: int, carried: bool) -> Mechanism:
    el = mech._elimination()
    free = el.free(s)
    if max(el.dependent) >= s:
        raise ValueError(f"Mechanism.reduced: dependent index {max(el.dependent)} ≥ s = {s} coordinates")

    def split(p):
        """(the user's params, Newton's start or None)."""
        if not carried:
            return p, None
        user, start = p
        return user, mech.newton_start(start)

    def full(qi, qdi, t, p):
        user, start = split(p)
        return (*el.state(qi, qdi, t, user, start), user)

    def kinetic(qi, qdi, t, p):
        q, qd, user = full(qi, qdi, t, p)
        return mech.kinetic(q, qd, t, user)

    # the optional functions below are passed on only when this mechanism has them
    def acceleration_energy(qi, qdi, qddi, t, p):
        assert mech.acceleration_energy is not None
        q, qd, user = full(qi, qdi, t, p)
        return mech.acceleration_energy(q, qd, el.accelerations(q, qd, qddi, t, user), t, user)

    def potential(qi, t, p):
        assert mech.potential is not None
        user, start = split(p)
        return mech.potential(el.coordinates(qi, t, user, start), t, user)

    def forces(qi, qdi, t, p):
        assert mech.forces is not None
        q, qd, user = full(qi, qdi, t, p)
        return el.generalized_forces(jnp.asarray(mech.forces(q, qd, t, user), qi.dtype), q, t, user)

    def constraints(qi, qdi, t, p):
        assert mech.constraints is not None
        q, qd, user = full(qi, qdi, t, p)
        return mech.constraints(q, qd, t, user)

    return Mechanism(
        kinetic,
        constraints=constraints if mech.constraints is not None else None,
        forces=forces if mech.forces is not None else None,
        potential=potential if mech.potential is not None else None,
        acceleration_energy=acceleration_energy if mech.acceleration_energy is not None else None,
        names=None if mech.names is None else tuple(mech.names[i] for i in free),
        independent=None if mech.independent is None else tuple(free.index(i) for i in mech.independent),
        nonlinear_constraints=mech.nonlinear_constraints,
    )


def check_independent(independent: Sequence[int], s: int, m: int) -> tuple:
    """Validate a choice of independent velocity indices; return it as a tuple."""
    ind = tuple(int(i) for i in independent)
    if len(ind) != s - m or len(set(ind)) != len(ind) or not all(0 <= i < s for i in ind):
        raise ValueError(
            f"independent={tuple(independent)!r}: expected {s - m} distinct indices in 0..{s - 1} "
            f"(s={s} coordinates minus m={m} constraints)"
        )
    return tuple(sorted(ind))


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _params_concrete(params) -> bool:
    return all(_is_concrete(l) for l in jax.tree_util.tree_leaves(params))


def _is_array(x) -> bool:
    """Whether an output of `eqx.filter_eval_shape` is an array (it gives their shapes and dtypes)."""
    return isinstance(x, (jax.ShapeDtypeStruct, jax.Array, np.ndarray))


def _is_vector(x) -> bool:
    return _is_array(x) and len(x.shape) == 1


def _returned(x) -> str:
    """What a user function returned, in words: an array's shape, or the Python type it is."""
    if _is_array(x):
        return f"shape {tuple(x.shape)}" + (" (a scalar)" if x.shape == () else "")
    if x is None:
        return "None (does the function end without `return`?)"
    if isinstance(x, (list, tuple)):
        return f"a Python {type(x).__name__} of {len(x)} item{'s' if len(x) != 1 else ''}, not a JAX array"
    if isinstance(x, (int, float, complex, bool)):
        return f"a Python {type(x).__name__} ({x!r}), not a JAX array (it does not depend on the arguments)"
    return f"a {type(x).__module__}.{type(x).__qualname__}, not a JAX array"
