"""The Whipple bicycle, from rigid bodies and rolling contacts.

Four rigid bodies — rear wheel R, rear frame with rider B, front frame
(fork and handlebar) H, front wheel F — with knife-edge wheels rolling
without slip on level ground, as in the benchmark of Meijaard, Papadopoulos,
Ruina & Schwab (2007), *Linearized dynamics equations for the balance and
steer of a bicycle: a benchmark and review*, Proc. R. Soc. A 463:1955–1982.
Axes and parameters are the paper's: x forward, y to the right, z down,
origin at the rear contact in the upright reference configuration; its
Table 1 is `BENCHMARK`.

Coordinates, s = 8 (names `COORDINATES`):

    x, y    rear contact point, m            yaw     heading ψ, rad
    roll    lean φ (to the right), rad       pitch   rear frame pitch θ, rad
    rear_wheel   θ_R, rear wheel angle relative to the rear frame, rad
    steer   δ (front turned right), rad      front_wheel  θ_F, relative to the fork, rad

The rear frame's orientation is `Rz(ψ) Rx(φ) Ry(θ)`; the front frame turns
by δ about the steer axis, tilted back by λ and meeting the ground a trail
c ahead of the front contact. Constraints: the front wheel touches the
ground (one holonomic constraint, solved for the pitch θ), and both wheels
roll without slipping (four nonholonomic constraints). That leaves three
degrees of freedom: roll, steer and the rear wheel's rotation, whose rates
are the independent velocities.

The equations of motion are never written here: T and S come from the body
poses through `jaxnh.rigid.RigidBodies`, the contact constraints through
`jaxnh.rigid.Wheel`, and `jaxnh.linearize` turns them into the benchmark's
linear equations `M q̈ + v C1 q̇ + (g K0 + v² K2) q = f` for q = (φ, δ).
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._analysis.linearize import Linearization, linearize
from jaxnh._base.compile import ONE_SHOT as _ONE_SHOT, one_shot_jit
from jaxnh._base.host import array_module
from jaxnh._base.linalg import mm
from jaxnh._base.status import is_traced
from jaxnh._model.mechanism import Mechanism
from jaxnh._model.rigid import RigidBodies, rot_axis, rot_x, rot_y, rot_z, Wheel


__all__ = [
    "BENCHMARK",
    "PUBLISHED",
    "COORDINATES",
    "ROLL",
    "STEER",
    "INDEPENDENT",
    "LEAN_STEER",
    "default_params",
    "bodies",
    "front_contact",
    "rolling",
    "system",
    "mechanism",
    "upright",
    "linearized",
    "linear_lean_steer",
    "linearized_speeds",
    "canonical_matrices",
    "canonical_from",
    "weave_speed",
    "capsize_speed",
    "characteristic_polynomial",
]

COORDINATES = ("x", "y", "yaw", "roll", "pitch", "rear_wheel", "steer", "front_wheel")
ROLL, PITCH, REAR, STEER, FRONT = 3, 4, 5, 6, 7
INDEPENDENT = (ROLL, REAR, STEER)

#: Table 1 of Meijaard et al. (2007): SI units, inertias about the body's mass
#: centre in the reference configuration's axes (x forward, z down).
BENCHMARK = {
    "w": 1.02,
    "c": 0.08,
    "lam": np.pi / 10,
    "g": 9.81,
    "rR": 0.3,
    "mR": 2.0,
    "IRxx": 0.0603,
    "IRyy": 0.12,
    "xB": 0.3,
    "zB": -0.9,
    "mB": 85.0,
    "IBxx": 9.2,
    "IByy": 11.0,
    "IBzz": 2.8,
    "IBxz": 2.4,
    "xH": 0.9,
    "zH": -0.7,
    "mH": 4.0,
    "IHxx": 0.05892,
    "IHyy": 0.06,
    "IHzz": 0.00708,
    "IHxz": -0.00756,
    "rF": 0.35,
    "mF": 3.0,
    "IFxx": 0.1405,
    "IFyy": 0.28,
}

#: Published results for the benchmark parameters (eq. 5.4 and §5 of the paper).
PUBLISHED = {
    "M": [[80.81722, 2.31941332208709], [2.31941332208709, 0.29784188199686]],
    "C1": [[0.0, 33.86641391492494], [-0.85035641456978, 1.68540397397560]],
    "K0": [[-80.95, -2.59951685249872], [-2.59951685249872, -0.80329488458618]],
    "K2": [[0.0, 76.59734589573222], [0.0, 2.65431523794604]],
    "weave_speed": 4.29238253634111,
    "capsize_speed": 6.02426201538837,
    "eigenvalues_v0": [3.13164324790656, -3.13164324790656, 5.53094371765393, -5.53094371765393],
    "eigenvalues_v5": [
        -14.0783896927982,
        complex(-0.77534188219585, 4.46486771378823),
        complex(-0.77534188219585, -4.46486771378823),
        -0.32286642900409,
    ],
}


def default_params() -> dict:
    """The benchmark parameters (`BENCHMARK`) as float arrays: differentiable, batchable."""
    return {k: jnp.asarray(v, dtype=jnp.result_type(float)) for k, v in BENCHMARK.items()}


# --- geometry ---------------------------------------------------------------------


def _frames(q, p):
    """Rear wheel centre, rear frame orientation, steer-axis point and front frame orientation."""
    x, y, psi, phi, theta, _, delta, _ = (q[i] for i in range(8))
    lean = mm(rot_z(psi), rot_x(phi))
    RB = mm(lean, rot_y(theta))
    rear = jnp.stack([x, y, jnp.zeros_like(x)]) - p["rR"] * lean[:, 2]  # the rear contact is (x, y, 0)
    axis = jnp.stack([jnp.sin(p["lam"]), jnp.zeros_like(p["lam"]), jnp.cos(p["lam"])])  # steer axis, pointing down
    RH = mm(RB, rot_axis(axis, delta))
    # the steer axis meets the ground at (w + c, 0, 0) in the reference configuration
    S = rear + mm(RB, jnp.stack([p["w"] + p["c"], jnp.zeros_like(p["w"]), p["rR"]]))
    return rear, RB, S, RH


def _front_point(S, RH, ref, p):
    """Inertial position of a front-frame point given by its reference coordinates."""
    return S + mm(RH, ref - jnp.stack([p["w"] + p["c"], jnp.zeros_like(p["w"]), jnp.zeros_like(p["w"])]))


def _rear_wheel_pose(q, t, p):
    """Rear wheel centre and orientation (the contact is (x, y, 0) by construction)."""
    lean = mm(rot_z(q[2]), rot_x(q[ROLL]))
    centre = jnp.stack([q[0], q[1], jnp.zeros_like(q[0])]) - p["rR"] * lean[:, 2]
    return centre, mm(lean, rot_y(q[PITCH] + q[REAR]))


def _front_wheel_pose(q, t, p):
    """Front wheel centre and orientation."""
    _, _, S, RH = _frames(q, p)
    zero = jnp.zeros_like(p["w"])
    return _front_point(S, RH, jnp.stack([p["w"], zero, -p["rF"]]), p), mm(RH, rot_y(q[FRONT]))


def _poses(q, t, p):
    rear, RB, S, RH = _frames(q, p)
    zero = jnp.zeros_like(p["w"])
    rear_frame = rear + mm(RB, jnp.stack([p["xB"], zero, p["zB"] + p["rR"]]))
    fork = _front_point(S, RH, jnp.stack([p["xH"], zero, p["zH"]]), p)
    front = _front_point(S, RH, jnp.stack([p["w"], zero, -p["rF"]]), p)
    return [
        (rear, mm(RB, rot_y(q[REAR]))),
        (rear_frame, RB),
        (fork, RH),
        (front, mm(RH, rot_y(q[FRONT]))),
    ]


def _inertia(xx, yy, zz, xz):
    z = jnp.zeros_like(xx)
    return jnp.stack([jnp.stack([xx, z, xz]), jnp.stack([z, yy, z]), jnp.stack([xz, z, zz])])


def _inertias(p):
    z = jnp.zeros_like(p["w"])
    return [
        (p["mR"], _inertia(p["IRxx"], p["IRyy"], p["IRxx"], z)),
        (p["mB"], _inertia(p["IBxx"], p["IByy"], p["IBzz"], p["IBxz"])),
        (p["mH"], _inertia(p["IHxx"], p["IHyy"], p["IHzz"], p["IHxz"])),
        (p["mF"], _inertia(p["IFxx"], p["IFyy"], p["IFxx"], z)),
    ]


def _gravity(p):
    z = jnp.zeros_like(p["g"])
    return jnp.stack([z, z, p["g"]])


def _rear_radius(p):
    return p["rR"]


def _front_radius(p):
    return p["rF"]


REAR_WHEEL = Wheel(_rear_wheel_pose, _rear_radius, axle=1, normal=(0.0, 0.0, -1.0))
FRONT_WHEEL = Wheel(_front_wheel_pose, _front_radius, axle=1, normal=(0.0, 0.0, -1.0))


def bodies() -> RigidBodies:
    """The four bodies (rear wheel, rear frame, front frame, front wheel) under gravity."""
    return RigidBodies(
        _poses, _inertias, gravity=_gravity, names=("rear wheel", "rear frame", "front frame", "front wheel")
    )


def front_contact(q: jax.typing.ArrayLike, t: jax.typing.ArrayLike, p: dict) -> jax.Array:
    """Height of the front wheel's lowest point above the ground, m (holonomic: 0)."""
    return jnp.stack([FRONT_WHEEL.height(q, t, p)])


def rolling(q: jax.typing.ArrayLike, qd: jax.typing.ArrayLike, t: jax.typing.ArrayLike, p: dict) -> jax.Array:
    """Slip velocities of the rear and front contacts along x and y, m/s (4,)."""
    return jnp.concatenate([REAR_WHEEL.slip(q, qd, t, p), FRONT_WHEEL.slip(q, qd, t, p)])


@functools.lru_cache(maxsize=None)
def system() -> Mechanism:
    """The Whipple bicycle in all 8 coordinates: the pitch is the dependent coordinate
    of the front-contact constraint (Newton starts from pitch 0, the reference
    configuration), the roll, rear wheel and steer rates are the independent velocities."""
    b = bodies()
    return Mechanism(
        b.kinetic,
        constraints=rolling,
        potential=b.potential,
        holonomic=front_contact,
        acceleration_energy=b.acceleration_energy,
        names=COORDINATES,
        independent=INDEPENDENT,
        dependent=(PITCH,),
    )


def mechanism(method: str = "appell") -> Mechanism:
    """The bicycle as a `jaxnh.Mechanism` for a method.

    "lagrange": all 8 coordinates, the front contact imposed as ġ = 0 among
    the constraints (`Mechanism.differentiated`). "appell": the 7
    coordinates other than the pitch, which is solved by Newton's method
    (`Mechanism.reduced`), with the acceleration energy S.
    """
    if method == "lagrange":
        return system().differentiated()
    if method == "appell":
        return system().reduced(len(COORDINATES))
    raise ValueError(f"bicycle.mechanism: method must be 'lagrange' or 'appell'; got {method!r}")


# --- steady running and its linearisation ------------------------------------------------


def upright(v: jax.typing.ArrayLike, params: dict) -> tuple[jax.Array, jax.Array]:
    """Upright straight running at forward speed v (m/s): (q, q̇) in all 8 coordinates.

    The reference configuration, moving along x: ẋ = v and the wheels turn at
    −v/r (their axles point to the right, +y, so forward rolling is a negative rotation).
    """
    xp = array_module(v, params)  # concrete: NumPy (eager jnp would compile each op)
    v = xp.asarray(v, dtype=jnp.result_type(float))
    z = xp.zeros_like(v)
    q = xp.zeros(8, v.dtype)
    qd = xp.stack([v, z, z, z, z, -v / xp.asarray(params["rR"]), z, -v / xp.asarray(params["rF"])])
    return jnp.asarray(q), jnp.asarray(qd)


FREE = tuple(i for i in range(8) if i != PITCH)  # coordinates of the "appell" (reduced) mechanism


def _reduce(idx):
    """Positions of full-coordinate indices among the 7 non-pitch coordinates."""
    return tuple(FREE.index(i) for i in idx)


def linearized(v: jax.typing.ArrayLike, params: dict | None = None, method: str = "lagrange") -> Linearization:
    """`jaxnh.Linearization` of upright straight running at speed v (m/s).

    State `(roll, steer, d roll, d rear_wheel, d steer)`; the position,
    heading and wheel angles are ignorable and left out. `method` as in
    `mechanism`: "lagrange" linearises Lagrange's expression from T in all 8
    coordinates (perturbed configurations re-solved for the pitch),
    "appell" linearises Appell's equations from S in the 7 coordinates left
    after the Newton elimination of the pitch. Upright running is steady, so
    the operating accelerations are zero (`rates` confirms it).
    """
    params = default_params() if params is None else params
    q, qd = upright(v, params)
    steady = jnp.zeros(len(INDEPENDENT), q.dtype)
    if method == "lagrange":
        return linearize(
            mechanism("lagrange"),
            params,
            q,
            qd,
            coordinates=(ROLL, STEER),
            speeds=INDEPENDENT,
            method="lagrange",
            complete=system().restore,
            accelerations=steady,
        )
    sel = jnp.asarray(FREE)
    return linearize(
        mechanism(method),
        params,
        q[sel],
        qd[sel],
        coordinates=_reduce((ROLL, STEER)),
        speeds=_reduce(INDEPENDENT),
        method="appell",
        accelerations=steady,
    )


LEAN_STEER = (0, 1, 2, 4)  # roll, steer, d roll, d steer within the linearised state


def linear_lean_steer(v: jax.typing.ArrayLike, params: dict | None = None, method: str = "lagrange") -> jax.Array:
    """The 4×4 state matrix for (roll, steer, roll rate, steer rate) at forward speed v (m/s).

    From the nonlinear model by automatic differentiation (`linearized`);
    the rear wheel rate, which decouples at upright running, is dropped.
    Works under `jit`, `vmap` (over v and params) and `grad`; see `linearized_speeds`
    for many speeds at once.
    """
    A = linearized(v, params, method).A
    if not is_traced(A):  # concrete: select on the host (eagerly, each indexing op is a program to compile)
        return jnp.asarray(np.asarray(A)[np.ix_(LEAN_STEER, LEAN_STEER)])
    idx = jnp.asarray(LEAN_STEER)
    return A[idx][:, idx]


# One-shot linearisations are evaluated a handful of times: XLA's cheapest
# optimisation settings halve their compile time and cost nothing noticeable.
ONE_SHOT = _ONE_SHOT


def _linearized_speeds_uncompiled(speeds, params, method):
    return jax.vmap(lambda v: linearized(v, params, method))(speeds)


_linearized_speeds: Callable[..., Linearization] = one_shot_jit(_linearized_speeds_uncompiled)


def linearized_speeds(
    speeds: jax.typing.ArrayLike | list[jax.typing.ArrayLike] | tuple[jax.typing.ArrayLike, ...],
    params: dict | None = None,
    method: str = "lagrange",
) -> Linearization:
    """`linearized` at each of `speeds` (m/s): a batched `Linearization`.

    For concrete speeds and parameters, `linearized` at each speed, stacked: its programs are
    compiled once, whatever the number of speeds (some 6 ms per speed after the first), and every
    speed is checked as `linearized` checks one. Under `jit`/`vmap`/`grad` it is `jax.vmap` of
    `linearized`, one program for the batch (`jax.jit(linearized_speeds)` gives that for concrete
    speeds too: worth its compilation for thousands of speeds)."""
    params = default_params() if params is None else params
    speeds = jnp.asarray(speeds, dtype=jnp.result_type(float))
    if is_traced(speeds, params) or speeds.ndim != 1:
        return _linearized_speeds(speeds, params, method)
    each = [linearized(v, params, method) for v in np.asarray(speeds)]
    return jax.tree_util.tree_map(lambda *xs: jnp.asarray(np.stack([np.asarray(x) for x in xs])), *each)


def canonical_from(lin: Linearization, g: jax.typing.ArrayLike) -> dict:
    """M, C1, K0, K2 from a batched `Linearization` whose first two speeds are 0 and 1 m/s."""
    # concrete: selected on the host (eagerly, each indexing operation is a program to compile)
    xp = jnp if is_traced(lin, g) else np
    mass, damping, stiffness = (xp.asarray(x) for x in (lin.mass, lin.damping, lin.stiffness))
    ls = xp.asarray((0, 2))  # roll and steer among the independent speeds (roll, rear wheel, steer)
    out = {
        "M": mass[0][ls][:, ls],
        "C1": damping[1][ls][:, ls],
        "K0": stiffness[0][ls] / xp.asarray(g),
        "K2": stiffness[1][ls] - stiffness[0][ls],
    }
    return out if xp is jnp else {k: jnp.asarray(v) for k, v in out.items()}


def canonical_matrices(params: dict | None = None, method: str = "lagrange") -> dict:
    """The benchmark's M, C1, K0, K2 (2×2 each) of the linearised model.

    The lean and steer equations linearised about upright running are
    `M q̈ + v C1 q̇ + (g K0 + v² K2) q = f` (Meijaard et al. 2007, eq. 5.3):
    M is the mass matrix for (φ̇, δ̇), the damping at v = 1 m/s is C1, the
    stiffness at v = 0 is g K0, and its growth from v = 0 to 1 m/s is K2.
    """
    params = default_params() if params is None else params
    return canonical_from(linearized_speeds(jnp.array([0.0, 1.0]), params, method), params["g"])


def characteristic_polynomial(
    mats: dict, v: jax.typing.ArrayLike, g: jax.typing.ArrayLike
) -> tuple[jax.typing.ArrayLike, ...]:
    """Coefficients a4..a0 of det(λ² M + λ v C1 + g K0 + v² K2)."""
    M, C, K = mats["M"], v * mats["C1"], g * mats["K0"] + v**2 * mats["K2"]
    a4 = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    a3 = M[0, 0] * C[1, 1] + C[0, 0] * M[1, 1] - M[0, 1] * C[1, 0] - C[0, 1] * M[1, 0]
    a2 = (
        M[0, 0] * K[1, 1]
        + K[0, 0] * M[1, 1]
        - M[0, 1] * K[1, 0]
        - K[0, 1] * M[1, 0]
        + C[0, 0] * C[1, 1]
        - C[0, 1] * C[1, 0]
    )
    a1 = C[0, 0] * K[1, 1] + K[0, 0] * C[1, 1] - C[0, 1] * K[1, 0] - K[0, 1] * C[1, 0]
    a0 = K[0, 0] * K[1, 1] - K[0, 1] * K[1, 0]
    return a4, a3, a2, a1, a0


def _matrices(params, method, matrices):
    params = default_params() if params is None else params
    mats = canonical_matrices(params, method) if matrices is None else matrices
    return {k: np.asarray(x, dtype=float) for k, x in mats.items()}, float(params["g"])


def weave_speed(
    params: dict | None = None,
    bracket: tuple[float, float] = (1.0, 5.5),
    method: str = "lagrange",
    matrices: dict | None = None,
) -> float:
    """Speed (m/s) where the weave mode becomes stable.

    Its complex pair crosses the imaginary axis where the Hurwitz
    determinant `a1 a2 a3 − a0 a3² − a4 a1²` of the characteristic
    polynomial `det(λ² M + λ v C1 + g K0 + v² K2)` vanishes; the root in
    `bracket` is found by bisection to rounding. `matrices`: M, C1,
    K0, K2 if already computed (else `canonical_matrices(params, method)`).
    """
    mats, g = _matrices(params, method, matrices)

    def hurwitz(v):
        a4, a3, a2, a1, a0 = characteristic_polynomial(mats, v, g)
        return a1 * a2 * a3 - a0 * a3**2 - a4 * a1**2

    return _root(hurwitz, *bracket)


def capsize_speed(
    params: dict | None = None,
    bracket: tuple[float, float] = (5.0, 10.0),
    method: str = "lagrange",
    matrices: dict | None = None,
) -> float:
    """Speed (m/s) where the capsize mode becomes unstable: its real eigenvalue
    crosses zero, where `a0 = det(g K0 + v² K2)` vanishes (root in `bracket`)."""
    mats, g = _matrices(params, method, matrices)
    return _root(lambda v: characteristic_polynomial(mats, v, g)[4], *bracket)


def _root(f, lo: float, hi: float) -> float:
    """The root of f in [lo, hi] (a sign change) by bisection, to rounding of the speed (m/s)."""
    f_lo, f_hi = f(lo), f(hi)
    if not f_lo * f_hi <= 0:
        raise ValueError(f"no sign change of the criterion between {lo} and {hi} m/s: choose another bracket")
    while hi - lo > 4 * np.finfo(float).eps * max(abs(lo), abs(hi)):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        f_mid = f(mid)
        if f_mid == 0:
            return float(mid)
        if (f_mid < 0) == (f_lo < 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return float(0.5 * (lo + hi))
