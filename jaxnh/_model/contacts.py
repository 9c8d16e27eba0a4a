"""Friction-held constraints: `FrictionContact`.

A nonholonomic constraint row of a `Mechanism` is *held by friction* when the
force that keeps it at zero is a tangential contact force limited by Coulomb's
law: the contact sticks (the row holds, like any other constraint) while the
force it needs stays inside the static cone `‖λ‖ ≤ μs N`, and slips (the row is
released, and a kinetic friction force of size `μk N` acts against the slip
velocity) otherwise. The solve that switches between the two
(`jaxnh._solve.friction`) is chosen by `simulate` when a mechanism has contacts;
this module only describes a contact and checks the description.

Convention: a friction-held row is written as the *slip velocity of the
contact point*, in m/s (for the seed paper's variator `r φ1' − ρ(t) φ2'`, eq. 4),
so that its multiplier is the tangential contact force in N and the
generalized friction force is `Aᵀ F` with `A = ∂c/∂qd`. A contact has one row
(a line contact: the variator's roller) or two (the two tangential directions
of a wheel or a ball on the ground).
"""

from __future__ import annotations

import math
from typing import Callable, Optional, Sequence, Union

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np


__all__ = ["FrictionContact", "ContactValue", "check_contacts"]

ContactValue = Union[float, Callable]
"""A contact quantity: a number (a constant of the model, compiled in) or a function
`f(q, qd, t, params) -> scalar` like every other user function (values taken from
`params` are traced, so they can be differentiated, batched and fitted)."""


def _as_value(name: str, x) -> ContactValue:
    if callable(x):
        return x
    if isinstance(x, jax.core.Tracer):
        raise TypeError(
            f"FrictionContact: `{name}` is a traced array; a number given here is a constant of the model. "
            f"To differentiate or batch over it, put it in params and pass a function, e.g. "
            f"{name}=lambda q, qd, t, p: p['{name}']"
        )
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(
            f"FrictionContact: `{name}` must be a number or a function (q, qd, t, params) -> scalar; got {x!r}"
        ) from None
    if a.ndim != 0 or not math.isfinite(float(a)):
        raise ValueError(f"FrictionContact: `{name}` must be a finite scalar; got {x!r}")
    return float(a)


class FrictionContact(eqx.Module):
    """A contact whose constraint rows are held by Coulomb friction.

    Arguments:
        rows: indices of the rows of the mechanism's nonholonomic `constraints`
            that this contact holds: one (a line contact) or two (the two
            tangential directions of a point contact). Each row must be the
            slip velocity of the contact point, m/s, so that its multiplier is
            the tangential contact force, N.
        normal_force: the normal force pressing the contact, N (≥ 0).
        mu_static: static friction coefficient μs (≥ μk): the contact sticks
            while the tangential force it needs satisfies `‖λ‖ ≤ μs N`.
        mu_kinetic: kinetic friction coefficient μk (≥ 0): while slipping, a
            force of size `μk N` acts against the slip velocity.
        name: a name used in diagnostics and messages (default `contact <i>`).

    Each of `normal_force`, `mu_static`, `mu_kinetic` is a number (a constant,
    compiled into the program) or a function `(q, qd, t, params) -> scalar`,
    evaluated along the motion; values taken from `params` are differentiable.
    """

    rows: tuple = eqx.field(static=True)
    normal_force: ContactValue = eqx.field(static=True)
    mu_static: ContactValue = eqx.field(static=True)
    mu_kinetic: ContactValue = eqx.field(static=True)
    name: Optional[str] = eqx.field(static=True, default=None)

    def __init__(
        self,
        rows: Union[int, Sequence[int]],
        normal_force: ContactValue,
        mu_static: ContactValue,
        mu_kinetic: ContactValue,
        name: Optional[str] = None,
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
        numbers = {k: getattr(self, k) for k in ("normal_force", "mu_static", "mu_kinetic")}
        for k, v in numbers.items():
            if isinstance(v, float) and v < 0:
                raise ValueError(f"FrictionContact: `{k}` must be ≥ 0; got {v}")
        mus, muk = numbers["mu_static"], numbers["mu_kinetic"]
        if isinstance(mus, float) and isinstance(muk, float) and mus < muk:
            raise ValueError(f"FrictionContact: expected mu_static ≥ mu_kinetic; got μs = {mus} < μk = {muk}")

    def values(
        self, q: jax.typing.ArrayLike, qd: jax.typing.ArrayLike, t: jax.typing.ArrayLike, params: object
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`(N, μs, μk)` at one state: normal force (N) and the two coefficients, scalars."""
        dtype = jnp.result_type(qd)
        out = []
        for v in (self.normal_force, self.mu_static, self.mu_kinetic):
            x = v(q, qd, t, params) if callable(v) else v
            out.append(jnp.asarray(x, dtype=dtype).reshape(()))
        return out[0], out[1], out[2]

    def label(self, index: int) -> str:
        """The contact's name, or `contact <index>`."""
        return self.name if self.name is not None else f"contact {index}"


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


def check_contact_shapes(contacts: tuple, n_nonholonomic: int, q, qd, t, params) -> None:
    """Rows within the nonholonomic constraints, and scalar contact values (at trace time)."""
    for i, c in enumerate(contacts):
        if max(c.rows) >= n_nonholonomic:
            raise ValueError(
                f"Mechanism: contacts[{i}] holds rows {c.rows}, but `constraints` returns {n_nonholonomic} "
                "rows; friction-held rows index the nonholonomic constraints (holonomic ones cannot slip)"
            )
        for name in ("normal_force", "mu_static", "mu_kinetic"):
            f = getattr(c, name)
            if not callable(f):
                continue
            try:
                out = eqx.filter_eval_shape(f, q, qd, t, params)
            except Exception as e:  # re-raise with the function named
                raise type(e)(f"Mechanism: contacts[{i}].{name} failed when called with (q, qd, t, params): {e}") from e
            if getattr(out, "shape", None) not in ((), (1,)):
                raise ValueError(
                    f"Mechanism: contacts[{i}].{name} must return a scalar; got shape {getattr(out, 'shape', None)}"
                )
