"""Formulations of the equations of motion: `Lagrange`, `Appell`, `Substituted`.

`formulation(mech, method, q, qd, t, params)` resolves a method name (or an
unbound formulation object) and binds it to a mechanism; `accelerations`
evaluates one state.
"""

from __future__ import annotations

from typing import Sequence

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp

from jaxnh._base.host import as_data, as_float, as_time
from jaxnh._base.status import describe, STATUS
from jaxnh._base.types import ArrayInput, PyTree
from jaxnh._equations.appell import Appell
from jaxnh._equations.base import Formulation, multipliers_from_accelerations
from jaxnh._equations.lagrange import Lagrange
from jaxnh._equations.split import choose_independent, VelocitySplit
from jaxnh._equations.substituted import Substituted
from jaxnh._equations.terms import speeds_span_velocities
from jaxnh._model.mechanism import Mechanism


METHODS = ("lagrange", "appell", "substituted")

__all__ = [
    "Appell",
    "Formulation",
    "Lagrange",
    "Substituted",
    "VelocitySplit",
    "METHODS",
    "accelerations",
    "choose_independent",
    "formulation",
    "as_formulation",
    "multipliers_from_accelerations",
]


def as_formulation(method: str | Formulation, independent: Sequence[int] | None = None) -> Formulation:
    """An unbound formulation object from a method name or object.

    `"appell"`, `"lagrange"`, `"substituted"` are aliases of `Appell()`,
    `Lagrange()`, `Substituted()`; `independent` is passed to the Appell and
    substituted forms. Lagrange's equations integrate all velocities: given
    `independent`, they are refused, naming `method='appell'`.
    """
    if independent is not None and (isinstance(method, Lagrange) or (isinstance(method, str) and method == "lagrange")):
        raise ValueError(
            f"independent={tuple(independent)}: fixed independent velocities belong to method='appell' (or "
            "'substituted'); Lagrange's equations, the default, integrate all velocities: pass method='appell' "
            "with them, or leave independent out"
        )
    if isinstance(method, Formulation):
        if independent is not None and isinstance(method, Appell):
            method = eqx.tree_at(lambda f: f.independent, method, tuple(independent), is_leaf=lambda x: x is None)
        return method  # pyright: ignore[reportReturnType]
    if method not in METHODS:
        raise ValueError(
            f"method must be one of {METHODS} or a formulation object such as jaxnh.Appell() or "
            f"jaxnh.Lagrange(baumgarte=...); got {method!r}"
        )
    if method == "lagrange":
        return Lagrange()  # `independent` does not concern Lagrange's equations (all velocities are integrated)
    ind = None if independent is None else tuple(int(i) for i in independent)
    return Appell(independent=ind) if method == "appell" else Substituted(independent=ind)


def formulation(
    mech: Mechanism,
    method: str | Formulation,
    q: jax.typing.ArrayLike,
    qd: jax.typing.ArrayLike,
    t: jax.typing.ArrayLike,
    params: PyTree,
    independent: Sequence[int] | None = None,
) -> Formulation:
    """The formulation `method` (a name or an object) bound to `mech`, shapes checked at trace time.

    `q`, `qd`, `t`, `params` are a sample state (only their shapes and dtypes are used).
    """
    if not isinstance(mech, Mechanism):
        raise TypeError(f"mech must be a jaxnh.Mechanism; got {type(mech).__name__}")
    form = as_formulation(method, independent)
    m = mech.check_shapes(q, qd, t, params)
    return form.bind(mech, jnp.shape(qd)[0], m, jnp.shape(q)[0])


def accelerations(
    mech: Mechanism,
    q: ArrayInput,
    qd: ArrayInput,
    t: ArrayInput,
    params: PyTree,
    method: str | Formulation = "lagrange",
    independent: Sequence[int] | None = None,
) -> tuple[jax.Array, jax.Array | None]:
    """Accelerations and multipliers of a mechanism at one state.

    Runs compiled (once per mechanism, method and shapes) and works under
    `jit`, `vmap` and `grad`.

    Arguments:
        mech: the `Mechanism`.
        q: coordinates, shape (s,).
        qd: velocities, shape (s,); should satisfy the constraints.
        t: time, s.
        params: parameters pytree passed to the user functions.
        method: "lagrange" (multipliers), "appell" (Gibbs–Appell in the
            independent velocities) or "substituted" (the paper's naive and
            wrong method, for comparison only), or a formulation object.
        independent: indices of independent velocities for "appell" and
            "substituted" (default: chosen from the constraint matrix at the state).

    Returns:
        `(qdd, multipliers)`: accelerations (s,) in units of q per s², and
        multipliers λ (m,) such that the constraint forces are `Aᵀ λ` with
        `A = ∂c/∂qd` (`None` for "substituted", which has none).
    """
    q = as_float(q)
    qd = jnp.asarray(qd, dtype=q.dtype)
    t = as_time(t, q)
    params = as_data(params, q)
    form = formulation(mech, method, q, qd, t, params, independent)
    # concrete input: non-finite values or a mass matrix that is not positive
    # definite raise here instead of returning NaN (qd need not be consistent)
    mech.check_values(q, qd, t, params, constraint_rtol=float("inf"))
    concrete = not any(isinstance(x, jax.core.Tracer) for x in [q, qd, t] + jax.tree_util.tree_leaves(params))
    if mech.kinematics is not None and concrete and not bool(speeds_span_velocities(mech, q, qd, t, params)):
        raise ValueError(f"kinematics: {describe(STATUS.speeds_incomplete)[len('solve failed: ') :]}")
    if isinstance(form, Appell) and form.independent is not None and form.m:
        leaves = [q, qd, t] + jax.tree_util.tree_leaves(params)
        if not any(isinstance(x, jax.core.Tracer) for x in leaves) and not bool(_split_ok(form, q, qd, t, params)):
            raise ValueError(
                f"independent={form.independent}: the dependent velocities cannot be solved from the constraints "
                "at this state (the dependent block of ∂c/∂qd is singular); choose other independent velocities "
                "or pass independent=None for an automatic choice"
            )
    return _accelerations(form, q, qd, t, params)


@eqx.filter_jit
def _split_ok(form, q, qd, t, params):
    return form.check(q, qd, t, params)[0]


@eqx.filter_jit
def _accelerations(form, q, qd, t, params):
    return form.accelerations(q, qd, t, params, multipliers=form.has_multipliers)
