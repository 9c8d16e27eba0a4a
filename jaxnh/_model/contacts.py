"""Friction-held constraints: `FrictionContact`.

A nonholonomic constraint row of a `Mechanism` is *held by friction* when the
force that keeps it at zero is a tangential contact force limited by Coulomb's
law: the contact sticks (the row holds, like any other constraint) while the
force it needs stays inside the static cone `‖λ‖ ≤ μs N`, and slips (the row is
released, and a kinetic friction force of size `μk N` acts against the slip
velocity) otherwise. The size of the kinetic force is the contact's *law*
(`ContactLaw`): Coulomb's `μk N` by default, or a force that also depends on the
slip speed (`Viscous`, `Stribeck`, or a user's subclass). The solve that switches
between the two modes (`jaxnh._solve.friction`) is chosen by `simulate` when a
mechanism has contacts; this module only describes a contact and checks the
description.

Convention: a friction-held row is written as the *slip velocity of the
contact point*, in m/s (for the seed paper's variator `r φ1' − ρ(t) φ2'`, eq. 4),
so that its multiplier is the tangential contact force in N and the
generalized friction force is `Aᵀ F` with `A = ∂c/∂qd`. A contact has one row
(a line contact: the variator's roller) or two (the two tangential directions
of a wheel or a ball on the ground).
"""

from __future__ import annotations

import abc
import math
from typing import Callable, ClassVar, Optional, Sequence, Union

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from jaxnh._base.types import PyTree


__all__ = [
    "FrictionContact",
    "ContactValue",
    "ContactLaw",
    "Coulomb",
    "Viscous",
    "Stribeck",
    "Multiplier",
    "check_contacts",
]

ContactValue = Union[float, Callable]
"""A contact quantity: a number (a constant of the model, compiled in) or a function
`f(q, qd, t, params) -> scalar` like every other user function (values taken from
`params` are traced, so they can be differentiated, batched and fitted)."""


class Multiplier(eqx.Module):
    """A normal force taken from the mechanism: the multiplier of one of its constraint rows, N.

    `FrictionContact(rows, normal_force=Multiplier(row), ...)` presses the contact with the
    force that holds constraint row `row` of the mechanism, counted over all its velocity
    constraints: the nonholonomic rows of `constraints` first, then the differentiated
    holonomic ones ġ = 0 (so the first holonomic row is `row = m_nh`). Write that row as the
    rate of the contact's **normal gap**, in m/s (a holonomic g in metres: g = distance of the
    contact point from the surface, positive on the free side), so that its multiplier is the
    normal force in newtons and is positive while the surface presses the body. This is the
    convention of the friction rows (slip velocities, m/s, whose multipliers are forces, N).

    The normal force then follows the motion: a bead on a rough wire is pressed by the force
    that keeps it on the wire, a ball on a curved surface by the force that keeps it on the
    surface. The kinetic force and the normal force depend on each other (the friction changes
    the accelerations, which change the force the gap row needs), and are solved together with
    the other multipliers. The contact must press: a normal force that falls to zero stops the
    solve with `STATUS.contact_normal_force_lost` (friction never pushes a body; lift-off is
    not modelled). Needs `method="lagrange"` (Appell's equations have no multipliers).

    Attributes:
        row: the index of the constraint row whose multiplier is the normal force.
    """

    row: int = eqx.field(static=True)

    def __init__(self, row: int):
        if isinstance(row, bool) or not isinstance(row, (int, np.integer)) or row < 0:
            raise TypeError(f"Multiplier: `row` must be a constraint row index (an int ≥ 0); got {row!r}")
        self.row = int(row)


def _as_value(name: str, x, owner: str = "FrictionContact") -> ContactValue:
    if name == "normal_force" and isinstance(x, Multiplier):
        return x  # pyright: ignore[reportReturnType]
    if callable(x):
        return x
    if isinstance(x, jax.core.Tracer):
        raise TypeError(
            f"{owner}: `{name}` is a traced array; a number given here is a constant of the model. "
            f"To differentiate or batch over it, put it in params and pass a function, e.g. "
            f"{name}=lambda q, qd, t, p: p['{name}']"
        )
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(
            f"{owner}: `{name}` must be a number or a function (q, qd, t, params) -> scalar; got {x!r}"
        ) from None
    if a.ndim != 0 or not math.isfinite(float(a)):
        raise ValueError(f"{owner}: `{name}` must be a finite scalar; got {x!r}")
    return float(a)


def _evaluate(v: ContactValue, q, qd, t, params, dtype) -> jax.Array:
    """A contact value at one state: a scalar of `dtype`."""
    x = v(q, qd, t, params) if callable(v) else v
    return jnp.asarray(x, dtype=dtype).reshape(())


# --- contact laws: the size of the kinetic force while slipping ----------------------------------------


class ContactLaw(eqx.Module):
    """The law of a friction contact while it slips: the size of the kinetic force, N.

    While a contact slips, a force of this size acts against its slip velocity (along
    the slip direction of a two-row contact). Sticking does not depend on the law: a
    contact sticks while the force it needs stays in the static cone `‖λ‖ ≤ μs N`.

    Write a law by subclassing and defining `slip_force`. Its fields must be
    hashable (numbers, strings, functions): a law is a constant of the model,
    compiled into the program. A value to differentiate, batch or fit belongs in
    `params`, read by `slip_force` (it receives them) or by a field that is a
    function `(q, qd, t, params) -> scalar`.

    Requirements of the solve:

    * the force is finite and ≥ 0 for every speed ≥ 0 (a value that is not stops
      the solve where it happens, with `STATUS.contact_value_invalid`);
    * it is a smooth function of the speed with a finite slope at speed 0, where
      every slip starts and stops. The solve calls the law at speeds ≥ 0 only;
      beyond the stop that ends a slip (where the steps that locate the stop
      look) it continues the force linearly with its slope at speed 0.

    With a normal force taken from the mechanism (`Multiplier`), the kinetic force
    and the normal force are solved together: exactly in one step when the force is
    affine in N (set the class attribute `affine_in_normal_force = True`, as the
    built-in laws do), else by Newton's method from N = 0 with a fixed number of
    steps.
    """

    affine_in_normal_force: ClassVar[bool] = False
    """Whether `slip_force` is affine in N (a + b·N, with a and b free of N)."""

    @abc.abstractmethod
    def slip_force(
        self,
        speed: jax.Array,
        N: jax.Array,
        mu_s: jax.Array,
        mu_k: jax.Array,
        q: jax.Array,
        qd: jax.Array,
        t: jax.Array,
        params: PyTree,
    ) -> jax.Array:
        """The size of the kinetic friction force, N (a scalar ≥ 0).

        Arguments:
            speed: the slip speed, m/s (≥ 0): the size of the contact point's slip
                velocity (along the slip direction for a two-row contact).
            N: the normal force, N.
            mu_s: the static friction coefficient μs (dimensionless).
            mu_k: the kinetic friction coefficient μk (dimensionless).
            q: the coordinates, as every user function gets them.
            qd: the velocities.
            t: the time, s.
            params: the parameters (values read from them are differentiable).
        """


class Coulomb(ContactLaw):
    """Coulomb's law: a kinetic force `μk N` (N), whatever the slip speed. The default law."""

    affine_in_normal_force: ClassVar[bool] = True

    def slip_force(
        self,
        speed: jax.Array,
        N: jax.Array,
        mu_s: jax.Array,
        mu_k: jax.Array,
        q: jax.Array,
        qd: jax.Array,
        t: jax.Array,
        params: PyTree,
    ) -> jax.Array:
        """`μk N`, N."""
        return mu_k * N


def _check_number(owner: str, name: str, value: ContactValue, minimum: float, strict: bool, unit: str, why: str):
    if isinstance(value, float) and (value <= minimum if strict else value < minimum):
        bound = ">" if strict else "≥"
        raise ValueError(f"{owner}: `{name}` must be {bound} {minimum:g}{unit}; got {value!r}. {why}")


class Viscous(ContactLaw):
    """Coulomb friction with viscous damping: a kinetic force `μk N + σ v`, N.

    Arguments:
        damping: the viscous coefficient σ ≥ 0, N·s/m (the force grows by σ for
            every m/s of slip speed v): a number, or a function
            `(q, qd, t, params) -> scalar` (values taken from `params` can be
            differentiated, batched and fitted).
    """

    damping: ContactValue = eqx.field(static=True)
    affine_in_normal_force: ClassVar[bool] = True

    def __init__(self, damping: ContactValue):
        self.damping = _as_value("damping", damping, "Viscous")
        _check_number("Viscous", "damping", self.damping, 0.0, False, " N·s/m",
                      "A negative σ would make friction push the slip along.")  # fmt: skip

    def slip_force(
        self,
        speed: jax.Array,
        N: jax.Array,
        mu_s: jax.Array,
        mu_k: jax.Array,
        q: jax.Array,
        qd: jax.Array,
        t: jax.Array,
        params: PyTree,
    ) -> jax.Array:
        """`μk N + σ v`, N."""
        sigma = _evaluate(self.damping, q, qd, t, params, jnp.result_type(speed))
        return mu_k * N + sigma * speed


class Stribeck(ContactLaw):
    """Stribeck friction: a kinetic force that falls from `μs N` at rest to `μk N` with
    the slip speed v, plus viscous damping:
    `N (μk + (μs − μk) exp(−(v/vs)^δ)) + σ v`, N.

    Arguments:
        speed_scale: the Stribeck speed vs > 0, m/s: the speed over which the force
            falls from μs N towards μk N.
        exponent: the shape exponent δ ≥ 1 (dimensionless; 2 is Gaussian, 1
            exponential). Below 1 the force's slope is infinite at speed 0,
            where every slip starts and stops.
        damping: the viscous coefficient σ ≥ 0, N·s/m.

    Each is a number or a function `(q, qd, t, params) -> scalar` (values taken
    from `params` can be differentiated, batched and fitted).
    """

    speed_scale: ContactValue = eqx.field(static=True)
    exponent: ContactValue = eqx.field(static=True)
    damping: ContactValue = eqx.field(static=True)
    affine_in_normal_force: ClassVar[bool] = True

    def __init__(self, speed_scale: ContactValue, exponent: ContactValue = 2.0, damping: ContactValue = 0.0):
        self.speed_scale = _as_value("speed_scale", speed_scale, "Stribeck")
        self.exponent = _as_value("exponent", exponent, "Stribeck")
        self.damping = _as_value("damping", damping, "Stribeck")
        _check_number("Stribeck", "speed_scale", self.speed_scale, 0.0, True, " m/s",
                      "It is the slip speed over which the force falls from μs N to μk N.")  # fmt: skip
        _check_number("Stribeck", "exponent", self.exponent, 1.0, False, "",
                      "Below 1 the force's slope is infinite at speed 0, where every slip starts and stops; "
                      "use exponent=1 (exponential) or 2 (Gaussian).")  # fmt: skip
        _check_number("Stribeck", "damping", self.damping, 0.0, False, " N·s/m",
                      "A negative σ would make friction push the slip along.")  # fmt: skip

    def slip_force(
        self,
        speed: jax.Array,
        N: jax.Array,
        mu_s: jax.Array,
        mu_k: jax.Array,
        q: jax.Array,
        qd: jax.Array,
        t: jax.Array,
        params: PyTree,
    ) -> jax.Array:
        """`N (μk + (μs − μk) exp(−(v/vs)^δ)) + σ v`, N."""
        dtype = jnp.result_type(speed)
        vs = _evaluate(self.speed_scale, q, qd, t, params, dtype)
        sigma = _evaluate(self.damping, q, qd, t, params, dtype)
        delta = self.exponent
        # (v/vs)^δ written as v^δ vs^−δ, and an integer δ as an integer power: the solve differentiates the
        # law's slope at v = 0 with respect to the parameters, which (0/vs)^δ with vs from params would turn
        # into 0 · ∞ (NaN) for δ < 2
        if isinstance(delta, float) and delta.is_integer():
            ratio = speed ** int(delta) / vs ** int(delta)
        else:
            d = _evaluate(delta, q, qd, t, params, dtype)
            ratio = jnp.power(speed, d) * jnp.power(vs, -d)
        return N * (mu_k + (mu_s - mu_k) * jnp.exp(-ratio)) + sigma * speed


class FrictionContact(eqx.Module):
    """A contact whose constraint rows are held by friction.

    Arguments:
        rows: indices of the rows of the mechanism's nonholonomic `constraints`
            that this contact holds: one (a line contact) or two (the two
            tangential directions of a point contact). Each row must be the
            slip velocity of the contact point, m/s, so that its multiplier is
            the tangential contact force, N.
        normal_force: the normal force pressing the contact, N (≥ 0): a value (below),
            or `Multiplier(row)`, the multiplier of one of the mechanism's constraint
            rows (the normal gap's rate), computed with the motion.
        mu_static: static friction coefficient μs (≥ μk): the contact sticks
            while the tangential force it needs satisfies `‖λ‖ ≤ μs N`.
        mu_kinetic: kinetic friction coefficient μk (≥ 0): while slipping, a
            force of size `μk N` acts against the slip velocity (with the default
            law).
        name: a name used in diagnostics and messages (default `contact <i>`).
        law: the size of the kinetic force while slipping, N, as a function of
            the slip speed (a `ContactLaw`): `Coulomb()` (`μk N`, the default),
            `Viscous(damping)`, `Stribeck(speed_scale, exponent, damping)` or a
            subclass of your own. Sticking is the same for every law.

    Each of `normal_force`, `mu_static`, `mu_kinetic` is a number (a constant,
    compiled into the program) or a function `(q, qd, t, params) -> scalar`,
    evaluated along the motion; values taken from `params` are differentiable.
    """

    rows: tuple = eqx.field(static=True)
    normal_force: Union[ContactValue, Multiplier] = eqx.field(static=True)
    mu_static: ContactValue = eqx.field(static=True)
    mu_kinetic: ContactValue = eqx.field(static=True)
    name: Optional[str] = eqx.field(static=True, default=None)
    law: ContactLaw = eqx.field(static=True, default=Coulomb())

    def __init__(
        self,
        rows: Union[int, Sequence[int]],
        normal_force: Union[ContactValue, Multiplier],
        mu_static: ContactValue,
        mu_kinetic: ContactValue,
        name: Optional[str] = None,
        *,
        law: ContactLaw = Coulomb(),
    ):
        r = (rows,) if isinstance(rows, (int, np.integer)) else tuple(rows)
        if not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in r):
            raise TypeError(f"FrictionContact: `rows` must be row indices (ints); got {rows!r}")
        r = tuple(int(i) for i in r)
        if len(r) not in (1, 2) or len(set(r)) != len(r) or min(r) < 0:
            raise ValueError(
                f"FrictionContact: `rows` must be one or two distinct indices ≥ 0 of the nonholonomic constraints "
                f"(a line contact, or the two tangential directions of a point contact); got {rows!r}"
            )
        self.rows = r
        self.normal_force = _as_value("normal_force", normal_force)
        self.mu_static = _as_value("mu_static", mu_static)
        self.mu_kinetic = _as_value("mu_kinetic", mu_kinetic)
        if name is not None and not isinstance(name, str):
            raise TypeError(f"FrictionContact: `name` must be a string or None; got {name!r}")
        self.name = name
        self.law = _check_law(law)
        numbers: dict = {k: getattr(self, k) for k in ("normal_force", "mu_static", "mu_kinetic")}
        for k, v in numbers.items():
            if isinstance(v, float) and v < 0:
                raise ValueError(f"FrictionContact: `{k}` must be ≥ 0; got {v}")
        mus, muk = numbers["mu_static"], numbers["mu_kinetic"]
        if isinstance(mus, float) and isinstance(muk, float) and mus < muk:
            raise ValueError(f"FrictionContact: expected mu_static ≥ mu_kinetic; got μs = {mus} < μk = {muk}")

    @property
    def normal_row(self) -> Optional[int]:
        """The constraint row whose multiplier is the normal force (`Multiplier`), or None."""
        return self.normal_force.row if isinstance(self.normal_force, Multiplier) else None

    def values(
        self,
        q: jax.typing.ArrayLike,
        qd: jax.typing.ArrayLike,
        t: jax.typing.ArrayLike,
        params: object,
        multipliers: Optional[jax.typing.ArrayLike] = None,
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`(N, μs, μk)` at one state: normal force (N) and the two coefficients, scalars.

        `multipliers` (m,), N: the constraint forces at the state, needed when the normal force
        is a `Multiplier`."""
        dtype = jnp.result_type(qd)
        out = []
        for v in (self.normal_force, self.mu_static, self.mu_kinetic):
            if isinstance(v, Multiplier):
                if multipliers is None:
                    raise ValueError(
                        "FrictionContact.values: the normal force is a Multiplier; pass the constraint "
                        "forces at the state as `multipliers`"
                    )
                x = jnp.asarray(multipliers)[v.row]
            else:
                x = v(q, qd, t, params) if callable(v) else v
            out.append(jnp.asarray(x, dtype=dtype).reshape(()))
        return out[0], out[1], out[2]

    def label(self, index: int) -> str:
        """The contact's name, or `contact <index>`."""
        return self.name if self.name is not None else f"contact {index}"


def _check_law(law) -> ContactLaw:
    """`law` if it is a usable `ContactLaw` instance (raises TypeError naming the fix otherwise)."""
    if isinstance(law, type) and issubclass(law, ContactLaw):
        raise TypeError(
            f"FrictionContact: `law` must be an instance; got the class {law.__name__}: write "
            f"law={law.__name__}(...), e.g. law=jaxnh.Viscous(damping=2.0)"
        )
    if not isinstance(law, ContactLaw):
        raise TypeError(
            "FrictionContact: `law` must be a jaxnh.ContactLaw: jaxnh.Coulomb() (the default), "
            f"jaxnh.Viscous(damping), jaxnh.Stribeck(speed_scale), or a subclass of ContactLaw; got {law!r}"
        )
    try:
        hash(law)
    except TypeError:
        raise TypeError(
            f"FrictionContact: the law {type(law).__name__} has a field that is not hashable (an array?): a law "
            "is a constant of the model. Put arrays in params and read them in slip_force, or make the field a "
            "number or a function (q, qd, t, params) -> scalar"
        ) from None
    return law


def as_contacts(contacts) -> tuple:
    """`contacts` as a tuple of `FrictionContact` (a single contact, a sequence, or None)."""
    if contacts is None:
        return ()
    if isinstance(contacts, FrictionContact):
        return (contacts,)
    try:
        out = tuple(contacts)
    except TypeError:
        raise TypeError(
            f"Mechanism: `contacts` must be a sequence of jaxnh.FrictionContact; got {type(contacts).__name__}"
        ) from None
    return out


def check_contacts(contacts: tuple) -> None:
    """Types and row overlaps of a mechanism's contacts (raises TypeError/ValueError)."""
    seen: dict = {}
    for i, c in enumerate(contacts):
        if not isinstance(c, FrictionContact):
            raise TypeError(f"Mechanism: contacts[{i}] must be a jaxnh.FrictionContact; got {type(c).__name__}")
        for r in c.rows:
            if r in seen:
                raise ValueError(
                    f"Mechanism: constraint row {r} is held by contacts[{seen[r]}] and contacts[{i}]; "
                    "each friction-held row belongs to one contact"
                )
            seen[r] = i


def check_contact_shapes(contacts: tuple, n_nonholonomic: int, m: int, q, qd, t, params) -> None:
    """Rows within the nonholonomic constraints, normal-force rows within all m velocity
    constraints and held by no contact, and scalar contact values (at trace time)."""
    friction_rows = {r for c in contacts for r in c.rows}
    for i, c in enumerate(contacts):
        if max(c.rows) >= n_nonholonomic:
            raise ValueError(
                f"Mechanism: contacts[{i}] holds rows {c.rows}, but `constraints` returns {n_nonholonomic} "
                "rows; friction-held rows index the nonholonomic constraints (holonomic ones cannot slip)"
            )
        row = c.normal_row
        if row is not None and (row >= m or row in friction_rows):
            why = (
                f"the mechanism has {m} velocity constraints (nonholonomic first, then the holonomic ones ġ)"
                if row >= m
                else "that row is held by friction (a slip velocity), not a normal gap"
            )
            raise ValueError(
                f"Mechanism: contacts[{i}].normal_force = Multiplier({row}): {why}. The row must be a constraint "
                "row that always holds, written as the rate of the contact's normal gap (m/s), so that its "
                "multiplier is the normal force (N)"
            )
        for name in ("normal_force", "mu_static", "mu_kinetic"):
            f = getattr(c, name)
            if not callable(f) or isinstance(f, Multiplier):
                continue
            try:
                out = eqx.filter_eval_shape(f, q, qd, t, params)
            except Exception as e:  # re-raise with the function named
                raise type(e)(f"Mechanism: contacts[{i}].{name} failed when called with (q, qd, t, params): {e}") from e
            # a Python number (e.g. a value of params held static by filter_eval_shape) is a scalar
            shape = () if isinstance(out, (int, float, np.number)) else getattr(out, "shape", None)
            if shape not in ((), (1,)):
                got = f"shape {shape}" if shape is not None else f"a {type(out).__name__}"
                raise ValueError(
                    f"Mechanism: contacts[{i}].{name} must return a scalar (a JAX array or number); got {got}"
                )
        if type(c.law) is Coulomb:
            continue
        law = f"contacts[{i}].law ({type(c.law).__name__})"

        def force(q_, qd_, t_, p_, c=c):
            dtype = jnp.result_type(qd_)
            N, mus, muk = c.values(q_, qd_, t_, p_, multipliers=jnp.ones((m,), dtype))
            return c.law.slip_force(jnp.zeros((), dtype), N, mus, muk, q_, qd_, t_, p_)

        try:
            out = eqx.filter_eval_shape(force, q, qd, t, params)
        except Exception as e:  # re-raise with the law named
            raise type(e)(
                f"Mechanism: {law}.slip_force failed when called with (speed, N, mu_s, mu_k, q, qd, t, params): {e}"
            ) from e
        if getattr(out, "shape", None) not in ((), (1,)):
            raise ValueError(
                f"Mechanism: {law}.slip_force must return a scalar; got shape {getattr(out, 'shape', None)}"
            )
