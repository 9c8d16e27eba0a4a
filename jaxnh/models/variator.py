"""The stepless friction variator of the seed paper (figure 1).

Shaft 1 (angle phi1, inertia J1, reduced torque M1) drives shaft 2 (phi2, J2,
M2) through a friction roller that rolls without slip, `r phi1' = rho phi2'`.
When the contact radius rho(t) is moved, the transmission ratio
`U21(t) = r / rho(t)` varies and the constraint

    U21(t) phi1' − phi2' = 0                                   (paper eq. 4)

cannot be integrated: s = 2 coordinates, m = 1 nonholonomic constraint,
one degree of freedom. The correct equation of motion (eq. 9) is

    (J1 + J2 U21²) phi1'' + J2 U21 U21' phi1' = M1 + U21 M2,

and the contact multiplier is `lambda = M2 − J2 (U21' phi1' + U21 phi1'')`
(N·m: the tangential contact force times the lever arm). The naive method of
substituting the constraint into T gives eq. (16), with twice the velocity
term. The paper's equations are written out here by hand only as
references for tests and the demo; the library derives its own by autodiff.

Units: angles rad, inertias kg·m², torques N·m, time s.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float

from jaxnh._model.contacts import FrictionContact
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.profiles import Constant, Fourier, Profile


__all__ = [
    "VariatorParams",
    "mechanism",
    "default_params",
    "closed_form",
    "paper_eq9",
    "paper_eq16",
    "paper_multiplier",
    "DriveParams",
    "friction_mechanism",
    "ContactRadius",
]


class VariatorParams(eqx.Module):
    """Parameters of the friction variator.

    Attributes:
        J1: inertia of shaft 1 with everything rigidly attached, kg·m².
        J2: inertia of shaft 2, kg·m².
        U21: transmission ratio U21(t) = r / rho(t) (dimensionless profile).
        M1: torque reduced to shaft 1 (motor), N·m, a profile of time.
        M2: torque reduced to shaft 2 (load; negative when braking), N·m.
    """

    J1: Float[Array, ""]
    J2: Float[Array, ""]
    U21: Profile
    M1: Profile
    M2: Profile

    def __init__(
        self,
        J1: ArrayLike,
        J2: ArrayLike,
        U21: ArrayLike | Profile,
        M1: ArrayLike | Profile = 0.0,
        M2: ArrayLike | Profile = 0.0,
    ):
        f = jnp.result_type(float)
        self.J1 = jnp.asarray(J1, dtype=f)
        self.J2 = jnp.asarray(J2, dtype=f)
        self.U21 = U21 if isinstance(U21, Profile) else Constant(U21)
        self.M1 = M1 if isinstance(M1, Profile) else Constant(M1)
        self.M2 = M2 if isinstance(M2, Profile) else Constant(M2)


def kinetic(q, qd, t, p: VariatorParams):
    """T = ½ (J1 phi1'² + J2 phi2'²), J (paper eq. 7)."""
    return 0.5 * (p.J1 * qd[0] ** 2 + p.J2 * qd[1] ** 2)


def constraint(q, qd, t, p: VariatorParams):
    """Rolling without slip: U21(t) phi1' − phi2' = 0, rad/s (paper eq. 4)."""
    return jnp.stack([p.U21(t) * qd[0] - qd[1]])


def torques(q, qd, t, p: VariatorParams):
    """Generalized forces (M1(t), M2(t)), N·m."""
    return jnp.stack([p.M1(t), p.M2(t)])


def acceleration_energy(q, qd, qdd, t, p: VariatorParams):
    """S = ½ (J1 phi1''² + J2 phi2''²), J/s² (paper eq. 22)."""
    return 0.5 * (p.J1 * qdd[0] ** 2 + p.J2 * qdd[1] ** 2)


def mechanism(acceleration_energy_given: bool = False) -> Mechanism:
    """The variator as a `Mechanism`, coordinates (phi1, phi2), phi1' independent.

    With `acceleration_energy_given=True` the Appell formulation uses the
    paper's S (eq. 22); otherwise it builds S from T.
    """
    return Mechanism(
        kinetic,
        constraints=constraint,
        forces=torques,
        acceleration_energy=acceleration_energy if acceleration_energy_given else None,
        names=("phi1", "phi2"),
        independent=(0,),
    )


class DriveParams(eqx.Module):
    """The variator with its roller held by friction (`friction_mechanism`).

    Attributes:
        variator: the variator's inertias, ratio law and torques (`VariatorParams`).
        radius: the roller's radius r, m (the contact radius on shaft 2 is
            rho(t) = r / U21(t)).
        normal_force: the force N pressing the roller onto shaft 2, N.
        mu_static: static friction coefficient μs of the roller's contact.
        mu_kinetic: kinetic friction coefficient μk ≤ μs.
    """

    variator: VariatorParams
    radius: Float[Array, ""]
    normal_force: Float[Array, ""]
    mu_static: Float[Array, ""]
    mu_kinetic: Float[Array, ""]

    def __init__(
        self,
        variator: VariatorParams,
        radius: ArrayLike,
        normal_force: ArrayLike,
        mu_static: ArrayLike,
        mu_kinetic: ArrayLike,
    ):
        f = jnp.result_type(float)
        self.variator = variator
        self.radius, self.normal_force = jnp.asarray(radius, dtype=f), jnp.asarray(normal_force, dtype=f)
        self.mu_static, self.mu_kinetic = jnp.asarray(mu_static, dtype=f), jnp.asarray(mu_kinetic, dtype=f)


def slip_velocity(q, qd, t, p: DriveParams):
    """Slip velocity of the roller's contact, r phi1' − rho(t) phi2' with rho = r / U21, m/s
    (paper eq. 4 times rho): the row a `FrictionContact` holds, its multiplier the tangential
    force, N (the paper's lambda, N·m, is rho times it)."""
    r, U = p.radius, p.variator.U21(t)
    return jnp.stack([r * qd[0] - (r / U) * qd[1]])


def _drive_kinetic(q, qd, t, p: DriveParams):
    return kinetic(q, qd, t, p.variator)


def _drive_torques(q, qd, t, p: DriveParams):
    return torques(q, qd, t, p.variator)


def _normal_force(q, qd, t, p: DriveParams):
    return p.normal_force


def _mu_static(q, qd, t, p: DriveParams):
    return p.mu_static


def _mu_kinetic(q, qd, t, p: DriveParams):
    return p.mu_kinetic


def friction_mechanism() -> Mechanism:
    """The variator whose roller transmits torque only by friction: its rolling constraint
    (`slip_velocity`) is held while the tangential force it needs is inside μs N and slips
    otherwise, with the kinetic force μk N against the slip. Parameters: `DriveParams`.
    (Built from module-level functions: every call returns an equal mechanism, which reuses
    the programs compiled for another.)"""
    roller = FrictionContact(0, _normal_force, _mu_static, _mu_kinetic, name="roller")
    return Mechanism(
        _drive_kinetic,
        constraints=slip_velocity,
        forces=_drive_torques,
        names=("phi1", "phi2"),
        independent=(0,),
        contacts=(roller,),
    )


@dataclasses.dataclass(frozen=True)
class ContactRadius:
    """The roller's contact radius on shaft 2, ρ(t) = r / U21(t), m: the lever that turns the
    tangential contact force (N) into the multiplier of eq. (4) (N·m). A hashable function
    `(t, params: VariatorParams) -> ρ`, for `jaxnh.identify.StickLimit(lever=...)`.

    Attributes:
        radius: the roller's radius r, m.
    """

    radius: float

    def __call__(self, t, p: VariatorParams):
        return self.radius / p.U21(t)


def default_params() -> VariatorParams:
    """A small laboratory variator: J1 = 0.02, J2 = 0.05 kg·m², U21 between
    0.6 and 1.4 with a 2 s period, motor torque 0.3 N·m, load −0.1 N·m."""
    return VariatorParams(J1=0.02, J2=0.05, U21=Fourier(1.0, cos=[0.0], sin=[0.4], period=2.0), M1=0.3, M2=-0.1)


# --- the paper's equations, by hand, as references ----------------------------


def paper_eq9(phi1d: ArrayLike, t: ArrayLike, p: VariatorParams) -> jax.Array:
    """phi1'' from the correct eq. (9)."""
    U, dU = p.U21(t), p.U21.derivative(t)
    return (p.M1(t) + U * p.M2(t) - p.J2 * U * dU * phi1d) / (p.J1 + p.J2 * U**2)


def paper_eq16(phi1d: ArrayLike, t: ArrayLike, p: VariatorParams) -> jax.Array:
    """phi1'' from the naive eq. (16) (velocity term twice too large)."""
    U, dU = p.U21(t), p.U21.derivative(t)
    return (p.M1(t) + U * p.M2(t) - 2 * p.J2 * U * dU * phi1d) / (p.J1 + p.J2 * U**2)


def paper_multiplier(phi1d: ArrayLike, phi1dd: ArrayLike, t: ArrayLike, p: VariatorParams) -> jax.Array:
    """lambda = M2 − J2 (U21' phi1' + U21 phi1''), N·m (from eq. 8)."""
    return p.M2(t) - p.J2 * (p.U21.derivative(t) * phi1d + p.U21(t) * phi1dd)


# --- closed form by quadrature ---------------------------------------------------


def closed_form(
    p: VariatorParams,
    ts: ArrayLike | list[ArrayLike] | tuple[ArrayLike, ...],
    phi0: tuple[float, float] | jax.Array | np.ndarray = (0.0, 0.0),
    w0: ArrayLike = 1.0,
    *,
    max_panel: float = 0.02,
    nodes: int = 10,
) -> tuple[jax.Array, jax.Array]:
    """The exact motion by quadrature, for torques that depend on time only.

    With I(t) = J1 + J2 U21(t)² and w = phi1', eq. (9) is
    `d/dt (sqrt(I) w) = (M1 + U21 M2) / sqrt(I)`, so

        sqrt(I(t)) w(t) = sqrt(I(0)) w(0) + ∫_0^t (M1 + U21 M2) / sqrt(I) ds,

    and phi1, phi2 follow by quadrature of w and U21 w. The integrals use
    composite Gauss–Legendre rules (`nodes` points, panels no wider than
    `max_panel` s, nested for the inner integral), accurate to rounding for
    smooth profiles. `ts` must be concrete (it sets the panel grid).

    Returns:
        `(q, qd)` of shapes (n, 2): (phi1, phi2) in rad and their rates, rad/s.
    """
    ts_np = np.asarray(ts, dtype=float)
    if ts_np.ndim != 1 or ts_np.size < 1 or np.any(np.diff(ts_np) <= 0):
        raise ValueError("closed_form: ts must be a concrete, strictly increasing 1-D array")
    P = max(1, int(np.ceil(np.max(np.diff(ts_np), initial=0.0) / max_panel)))
    x, wq = np.polynomial.legendre.leggauss(nodes)
    x, wq = jnp.asarray((x + 1) / 2), jnp.asarray(wq / 2)
    f = jnp.result_type(float)
    ts = jnp.asarray(ts_np, dtype=f)
    frac = jnp.arange(P, dtype=f) / P
    a = (ts[:-1, None] + (ts[1:] - ts[:-1])[:, None] * frac).reshape(-1)  # panel starts
    h = jnp.repeat(jnp.diff(ts) / P, P)

    def inertia(t):  # I(t) above
        return p.J1 + p.J2 * p.U21(t) ** 2

    def F(t):
        return (p.M1(t) + p.U21(t) * p.M2(t)) / jnp.sqrt(inertia(t))

    Fv = jax.vmap(F)
    node_t = a[:, None] + h[:, None] * x  # (N, n)
    dG = h * jnp.sum(wq * Fv(node_t.reshape(-1)).reshape(node_t.shape), axis=1)
    G_start = jnp.concatenate([jnp.zeros(1, f), jnp.cumsum(dG)])[:-1]  # G at each panel start
    inner_t = a[:, None, None] + h[:, None, None] * x[None, :, None] * x[None, None, :]
    inner = jnp.sum(wq * Fv(inner_t.reshape(-1)).reshape(inner_t.shape), axis=2)
    G_node = G_start[:, None] + h[:, None] * x * inner
    c0 = jnp.sqrt(inertia(ts[0])) * w0
    Iv = jax.vmap(inertia)
    Uv = jax.vmap(p.U21)
    w_node = (c0 + G_node) / jnp.sqrt(Iv(node_t.reshape(-1)).reshape(node_t.shape))
    U_node = Uv(node_t.reshape(-1)).reshape(node_t.shape)
    d1 = h * jnp.sum(wq * w_node, axis=1)
    d2 = h * jnp.sum(wq * U_node * w_node, axis=1)
    zero = jnp.zeros(1, f)
    phi1 = phi0[0] + jnp.concatenate([zero, jnp.cumsum(d1)])[::P]
    phi2 = phi0[1] + jnp.concatenate([zero, jnp.cumsum(d2)])[::P]
    G_ts = jnp.concatenate([zero, jnp.cumsum(dG)])[::P]
    w = (c0 + G_ts) / jnp.sqrt(Iv(ts))
    return jnp.stack([phi1, phi2], axis=1), jnp.stack([w, Uv(ts) * w], axis=1)
