"""The interface shared by all formulations of the equations of motion.

A formulation is an object (an `eqx.Module`, so a pytree: its arrays may be
traced, batched and differentiated) that owns everything that differs between
ways of writing the equations of motion:

* the integrated state `y` and how coordinates and velocities are recovered
  from it (`state`, `unpack`);
* the vector field `dy/dt` and the accelerations and multipliers at a state;
* which components of `y` count in the step-size error control (`error_mask`);
* what happens around each step (`step_maps`): drift control for Lagrange's
  equations (projection), the choice of independent velocities for Appell's;
* the checks of an initial state that only it can make (`check`).

A formulation is created unbound (`jaxnh.Appell()`, `jaxnh.Lagrange(baumgarte=2.0)`)
and bound to a mechanism and its sizes by `bind`; `simulate`, `linearize` and
`fit` only use this interface.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, Optional

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from jaxnh._base.linalg import mm, solve_psd_min_norm
from jaxnh._base.status import STATUS
from jaxnh._equations.step_maps import StepMaps, with_quaternions
from jaxnh._equations.terms import constraint_terms, mass_and_velocity_terms
from jaxnh._model.mechanism import Mechanism


class Formulation(eqx.Module):
    """A way to turn a `Mechanism` into equations of motion (see the module docstring).

    Attributes:
        mech: the mechanism, once bound (`None` for a formulation as the user
            creates it).
        s: number of coordinates, once bound.
        m: number of nonholonomic constraints (holonomic ones differentiated
            included), once bound.
    """

    mech: Optional[Mechanism] = None
    s: int = eqx.field(static=True, default=0)
    m: int = eqx.field(static=True, default=0)
    nq: int = eqx.field(static=True, default=0)

    has_multipliers = True
    name = "formulation"

    def bind(self, mech: Mechanism, s: int, m: int, nq: Optional[int] = None) -> Formulation:
        """This formulation for `mech` with s velocities (speeds), m constraints and nq coordinates
        (default s: a mechanism without `kinematics`, whose velocities are q̇)."""
        return dataclasses.replace(self, mech=mech, s=s, m=m, nq=s if nq is None else int(nq))

    def rate(self, q: jax.Array, u: jax.Array, t: jax.typing.ArrayLike, params: Any) -> jax.Array:
        """dq/dt (nq,) from the velocities (speeds) u: the mechanism's `kinematics`, or u itself."""
        return self.bound_mech.rate(q, u, t, params)

    @property
    def bound_mech(self) -> Mechanism:
        """The mechanism of a bound formulation (an error for an unbound one)."""
        if self.mech is None:
            raise ValueError(f"the {self.name!r} formulation is not bound to a mechanism yet (see `bind`)")
        return self.mech

    @abc.abstractmethod
    def state(self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: Any) -> Any:
        """Integrated state y from coordinates q (s,) and velocities qd (s,): one flat
        vector (an integrator's stages and error norm then cost one operation each, where a
        tuple of parts costs one per part)."""

    @abc.abstractmethod
    def unpack(self, y: jax.Array, t: jax.typing.ArrayLike, params: Any) -> tuple[jax.Array, jax.Array]:
        """Coordinates q (s,) and all velocities qd (s,) from the state y."""

    @abc.abstractmethod
    def accelerations(
        self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: Any, multipliers: bool = False
    ) -> tuple[jax.Array, Optional[jax.Array]]:
        """Accelerations qdd (s,) and, if asked, multipliers λ (m,), else None."""

    @abc.abstractmethod
    def vector_field(self, t: jax.typing.ArrayLike, y: jax.Array, params: Any) -> Any:
        """dy/dt for the integrated state y."""

    def error_mask(self) -> Optional[tuple[float, ...]]:
        """Static weights, one per entry of the (flat) state: 1.0 for components in the
        step-size error control, 0.0 for bookkeeping; None for all."""
        return None

    def step_maps(self) -> Optional[StepMaps]:
        """A `jaxnh.StepMaps` applied around every step, or None."""
        return None

    def solve_maps(self) -> Optional[StepMaps]:
        """The maps a solve applies around every step: `step_maps`, with the mechanism's unit
        quaternions rescaled to unit norm after each step (`UnitQuaternions`)."""
        mech = self.mech
        return with_quaternions(self.step_maps(), mech.quaternions if mech is not None else ())

    def check(
        self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: Any
    ) -> tuple[jax.Array, diffrax.RESULTS]:
        """(ok, STATUS) of formulation-specific checks of an initial state (in the graph)."""
        return jnp.asarray(True), STATUS.successful

    def check_given(
        self, q: jax.Array, qd: jax.Array, t: jax.typing.ArrayLike, params: Any, A: jax.Array, inertias: jax.Array
    ) -> tuple[jax.Array, diffrax.RESULTS]:
        """`check`, given what the solve's own initial checks have evaluated at the state already:
        `A` = ∂c/∂qd (m, s) and `inertias`, the mass matrix's diagonal (kg·m² or kg). The default
        ignores them and calls `check`; a formulation whose check needs them overrides this."""
        return self.check(q, qd, t, params)

    def describe_failure(self, status: STATUS) -> Optional[str]:
        """Extra words for a failure status specific to this formulation."""
        return None


def multipliers_from_accelerations(
    mech: Mechanism, q: jax.Array, qd: jax.Array, qdd: jax.Array, t: jax.typing.ArrayLike, params: Any
) -> jax.Array:
    """Multipliers λ with `M qdd + h − Q = Aᵀ λ` (least squares, minimum norm).

    λ_k is the generalized constraint force of constraint k divided by
    `∂c_k/∂qd`: for the variator it is the tangential contact force times
    the lever arm r (N·m).
    """
    M, h = mass_and_velocity_terms(mech, q, qd, t, params)
    R = mm(M, qdd) + h - mech.generalized_forces(q, qd, t, params)
    A, _ = constraint_terms(mech, q, qd, t, params)
    return solve_psd_min_norm(mm(A, A.T), mm(A, R))
