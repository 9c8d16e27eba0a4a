"""Roll-rate feedback steer control of the Whipple bicycle: TU Delft's balance-assist bicycle.

A steer motor applies the torque

    T_δ = −k(v) φ̇      (N·m; φ̇ the roll rate, rad/s)

with a gain that falls linearly with the forward speed v (m/s) and is off
from 4.7 m/s on (`roll_rate_gain`):

    k(v) = −κ (4.7 − v)               for 1.5 ≤ v < 4.7 m/s,
    k(v) = −κ (4.7 − 1.5) / 1.5 · v   below 1.5 m/s,
    k(v) = 0                          at or above 4.7 m/s.

κ (N·m·s/rad per m/s) is positive: k < 0, so a roll to the right (φ̇ > 0)
steers to the right, into the fall, and the weave is damped more the larger
κ is. Roll φ and steer δ follow Meijaard et al. (2007), as in
`jaxnh.models.bicycle`: φ positive leaning right, δ positive turning right,
T_δ the torque between the rear frame and the front frame, positive turning
right.

The uncontrolled bicycle is the shipped Whipple model
(`jaxnh.models.bicycle.linearized_speeds`, autodiff linearisation of the
nonlinear equations); the control enters the linearised equations as the
generalised force T_δ on the steer coordinate, so the closed-loop state
matrix for (φ, δ, φ̇, δ̇) is `A − k(v) b e₃ᵀ`, where b is the state's response to a unit
steer torque (`OpenLoop`). With k = 0 it is the open-loop matrix exactly.

`fit_kappa` estimates κ from measured weave eigenvalues (real and imaginary
parts) by Gauss–Newton with the Jacobian from `jax.jacfwd` through the
eigenvalues of the closed-loop matrix; `fit_measurements` does so for both
gain settings of the embedded data set `jaxnh/data/balance_assist_weave.json`
(measured on TU Delft's riderless balance-assist bicycle; source: the public
GitHub repository mechmotum/fall-probability-paper, public domain as declared
by its README).
"""

from __future__ import annotations

import dataclasses
import json
import math
from importlib import resources
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxnh.identify.problem import statistics_host
from jaxnh.models import bicycle


__all__ = [
    "V_LOW",
    "V_OFF",
    "GAINS",
    "FIT_SPEEDS",
    "DATA_FILE",
    "WeaveData",
    "load_data",
    "roll_rate_gain",
    "OpenLoop",
    "open_loop",
    "closed_loop",
    "weave_eigenvalues",
    "residuals",
    "KappaFit",
    "fit_kappa",
    "fit_measurements",
    "t_quantile",
]

V_LOW = 1.5  # m/s: below it the gain falls linearly to zero at standstill
V_OFF = 4.7  # m/s: the controller is off at and above this speed
GAINS = (8, 10)  # the two gain settings measured (the controller's own numbering, no unit)
FIT_SPEEDS = (1.6, 4.5)  # m/s: the measured speeds fitted (1.66–4.44; the controller is on)
DATA_FILE = "balance_assist_weave.json"
STEER_TORQUE = 2  # steer among the independent speeds (roll, rear wheel, steer) of `bicycle.linearized`
ROLL_RATE = 2  # roll rate among the lean–steer states (roll, steer, roll rate, steer rate)


@dataclasses.dataclass(frozen=True)
class WeaveData:
    """The embedded measurements (`jaxnh/data/balance_assist_weave.json`).

    Attributes:
        speeds: forward speeds (7,), m/s.
        weave: {gain setting: measured weave eigenvalue (7,), complex: real part 1/s, imaginary part rad/s}.
        params: the bicycle's Whipple-model parameters (`jaxnh.models.bicycle` names, SI units) as float arrays.
        source: where the numbers come from; licence: their licence.
    """

    speeds: np.ndarray
    weave: dict[int, np.ndarray]
    params: dict[str, jax.Array]
    source: str
    licence: str


def load_data() -> WeaveData:
    """The embedded measured weave eigenvalues of the balance-assist bicycle at two gain settings."""
    raw = json.loads(resources.files("jaxnh").joinpath("data", DATA_FILE).read_text())
    tables = {g: np.asarray(raw[f"gain_{g}"], dtype=float) for g in GAINS}
    speeds = tables[GAINS[0]][:, 0]
    if not all(np.array_equal(t[:, 0], speeds) for t in tables.values()):
        raise ValueError(f"{DATA_FILE}: the gain settings were measured at different speeds")
    weave = {g: t[:, 1] + 1j * t[:, 2] for g, t in tables.items()}
    params = {k: jnp.asarray(v, dtype=jnp.result_type(float)) for k, v in raw["bike_without_rider"].items()}
    return WeaveData(speeds, weave, params, raw["source"], raw["licence"])


def roll_rate_gain(v: jax.typing.ArrayLike, kappa: jax.typing.ArrayLike) -> jax.Array:
    """The roll-rate gain k(v) of the control law T_δ = −k(v) φ̇, N·m·s/rad.

    Arguments:
        v: forward speed, m/s (any shape).
        kappa: the gain's slope κ, N·m·s/rad per m/s (positive: steer into the fall).

    Returns:
        −κ (4.7 − v) for 1.5 ≤ v < 4.7 m/s, −κ (4.7 − 1.5)/1.5 · v below 1.5 m/s, exactly 0 at
        or above 4.7 m/s. Differentiable in κ (and in v away from 1.5 and 4.7 m/s).
    """
    v = jnp.asarray(v, dtype=jnp.result_type(float))
    kappa = jnp.asarray(kappa, dtype=v.dtype)
    low = -kappa * (V_OFF - V_LOW) / V_LOW * v
    mid = -kappa * (V_OFF - v)
    return jnp.where(v >= V_OFF, jnp.zeros_like(mid), jnp.where(v < V_LOW, low, mid))


class OpenLoop(eqx.Module):
    """The uncontrolled bicycle's linearised lean and steer at several speeds.

    Attributes:
        speeds: forward speeds (n,), m/s.
        A: state matrices (n, 4, 4) for (roll φ, steer δ, roll rate φ̇, steer rate δ̇), from
            `bicycle.linearized_speeds` (the same as `bicycle.linear_lean_steer`), 1/s and 1/s².
        b: response of the state's rates to a unit steer torque (n, 4): (0, 0, mass⁻¹ e_δ) for the
            roll and steer rates, 1/(kg·m²).
    """

    speeds: jax.Array
    A: jax.Array
    b: jax.Array


def open_loop(speeds: jax.typing.ArrayLike, params: dict, method: str = "lagrange") -> OpenLoop:
    """Linearise the uncontrolled Whipple bicycle about upright straight running at each speed.

    Arguments:
        speeds: forward speeds (n,), m/s.
        params: Whipple-model parameters (`jaxnh.models.bicycle` names; e.g. `load_data().params`).
        method: "lagrange" or "appell", as in `bicycle.linearized`.

    Returns:
        An `OpenLoop`: the state matrices and the steer-torque input at each speed. For concrete
        speeds and parameters (the matrices are gathered on the host, not traced); the control
        gain, the differentiable part, is applied afterwards by `closed_loop`.
    """
    speeds = jnp.asarray(speeds, dtype=jnp.result_type(float))
    lin = bicycle.linearized_speeds(speeds, params, method)
    ls = np.asarray(bicycle.LEAN_STEER)
    A = jnp.asarray(np.asarray(lin.A)[:, ls][:, :, ls])
    unit = np.zeros(np.asarray(lin.mass).shape[-1])
    unit[STEER_TORQUE] = 1.0
    response = np.linalg.solve(np.asarray(lin.mass), np.broadcast_to(unit, lin.mass.shape[:-1])[..., None])[..., 0]
    b = np.zeros(A.shape[:2])
    b[:, 2] = response[:, 0]  # roll rate
    b[:, 3] = response[:, STEER_TORQUE]  # steer rate
    return OpenLoop(speeds=speeds, A=A, b=jnp.asarray(b))


def closed_loop(plant: OpenLoop, kappa: jax.typing.ArrayLike) -> jax.Array:
    """Closed-loop state matrices (n, 4, 4) under T_δ = −k(v) φ̇ with the gain slope κ (N·m·s/rad per m/s).

    `A − k(v) b e₃ᵀ`: the torque's effect on the rates, proportional to the roll rate. Exactly the
    open-loop `plant.A` where k(v) = 0 (v ≥ 4.7 m/s). Differentiable in κ.
    """
    k = roll_rate_gain(plant.speeds, kappa)
    return plant.A.at[:, :, ROLL_RATE].add(-k[:, None] * plant.b)


def weave_eigenvalues(plant: OpenLoop, kappa: jax.typing.ArrayLike) -> jax.Array:
    """The weave eigenvalue at each speed (n,), complex: real part 1/s, imaginary part rad/s.

    The eigenvalue of the closed-loop matrix with the largest imaginary part (the weave is the
    one oscillatory mode at these speeds; a real result means it has none). Differentiable in κ
    (`jax.jacfwd`) where that eigenvalue is simple.
    """
    lam = jax.vmap(jnp.linalg.eigvals)(closed_loop(plant, kappa))
    pick = jnp.argmax(lam.imag, axis=-1)
    return jnp.take_along_axis(lam, pick[:, None], axis=-1)[:, 0]


def residuals(kappa: jax.typing.ArrayLike, plant: OpenLoop, measured: jax.typing.ArrayLike) -> jax.Array:
    """Model minus measurement: real parts (1/s) then imaginary parts (rad/s), (2n,)."""
    lam = weave_eigenvalues(plant, kappa)
    measured = jnp.asarray(measured)
    return jnp.concatenate([lam.real - measured.real, lam.imag - measured.imag])


def _residuals_and_jacobian(kappa, plant, measured):
    return residuals(kappa, plant, measured), jax.jacfwd(residuals)(kappa, plant, measured)


_value_and_jacobian: Callable[..., tuple[jax.Array, jax.Array]] = jax.jit(_residuals_and_jacobian)


def t_quantile(dof: int, level: float = 0.95) -> float:
    """Two-sided quantile of Student's t distribution: P(|T| ≤ t) = level with `dof` degrees of freedom.

    Exact for whole `dof` (Abramowitz & Stegun 26.7.3–4, the series in cos θ), solved by
    bisection; no SciPy import.
    """
    if dof < 1 or int(dof) != dof or not 0.0 < level < 1.0:
        raise ValueError(f"t_quantile: dof must be a whole number ≥ 1 and 0 < level < 1; got {dof}, {level}")
    nu = int(dof)

    def inside(t):  # P(|T| ≤ t)
        th = math.atan(t / math.sqrt(nu))
        c2, s, c = math.cos(th) ** 2, math.sin(th), math.cos(th)
        if nu == 1:
            return 2.0 * th / math.pi
        term, total = 1.0, 1.0
        if nu % 2 == 0:
            for j in range(1, (nu - 2) // 2 + 1):
                term *= c2 * (2 * j - 1) / (2 * j)
                total += term
            return s * total
        for j in range(1, (nu - 3) // 2 + 1):
            term *= c2 * (2 * j) / (2 * j + 1)
            total += term
        return 2.0 / math.pi * (th + s * c * total)

    lo, hi = 0.0, 1.0
    while inside(hi) < level:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if inside(mid) < level else (lo, mid)
    return 0.5 * (lo + hi)


@dataclasses.dataclass(frozen=True)
class KappaFit:
    """The least-squares estimate of κ from measured weave eigenvalues.

    Attributes:
        kappa: the estimate, N·m·s/rad per m/s.
        std: its standard error, from the Gauss–Newton covariance s² (JᵀJ)⁻¹ with the residual
            variance s² = Σr² / dof (no measurement uncertainty is published: the spread of the
            residuals, model error included, stands for it).
        interval: the 95 % interval κ ± t₀.₉₇₅(dof) · std (Student's t, `t_quantile`).
        dof: degrees of freedom, 2n − 1.
        rms: root mean square of the residuals (real and imaginary parts together), 1/s.
        rms_real, rms_imag: of the real parts (1/s) and of the imaginary parts (rad/s) alone.
        speeds: the fitted speeds (n,), m/s; measured, fitted: the weave eigenvalues there (n,).
        residuals: (2n,), real parts then imaginary parts; jacobian: ∂residuals/∂κ (2n,).
        iterations: Gauss–Newton steps taken; converged: the last step was below 1e-10 of κ.
    """

    kappa: float
    std: float
    interval: tuple[float, float]
    dof: int
    rms: float
    rms_real: float
    rms_imag: float
    speeds: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    iterations: int
    converged: bool


def fit_kappa(
    plant: OpenLoop, measured: jax.typing.ArrayLike, kappa0: float = 4.0, max_iterations: int = 50
) -> KappaFit:
    """Fit the gain slope κ to measured weave eigenvalues by Gauss–Newton.

    Arguments:
        plant: the uncontrolled bicycle at the measured speeds (`open_loop`).
        measured: measured weave eigenvalues (n,), complex (real part 1/s, imaginary part rad/s).
        kappa0: starting value, N·m·s/rad per m/s.
        max_iterations: Gauss–Newton steps at most (each step is halved while it does not lower Σr²).

    Returns:
        A `KappaFit`: κ, its standard error and 95 % interval, the residuals and their RMS. The
        Jacobian is `jax.jacfwd` through the closed-loop eigenvalues; the real and imaginary parts
        are weighted alike.
    """
    measured = np.asarray(measured, dtype=complex)
    kappa = float(kappa0)
    r, J = (np.asarray(x) for x in _value_and_jacobian(kappa, plant, measured))
    converged, it = False, 0
    for it in range(1, max_iterations + 1):
        step = -float(J @ r) / float(J @ J)
        cost = float(r @ r)
        while True:
            r_new, J_new = (np.asarray(x) for x in _value_and_jacobian(kappa + step, plant, measured))
            if float(r_new @ r_new) <= cost or abs(step) < 1e-14 * max(1.0, abs(kappa)):
                break
            step *= 0.5
        kappa, r, J = kappa + step, r_new, J_new
        if abs(step) <= 1e-10 * max(1.0, abs(kappa)):
            converged = True
            break
    stats = statistics_host(J[:, None], r)
    std = float(stats["std"][0])
    dof = int(stats["dof"])
    half = t_quantile(dof) * std
    n = measured.shape[0]
    lam = measured + r[:n] + 1j * r[n:]
    return KappaFit(
        kappa=kappa,
        std=std,
        interval=(kappa - half, kappa + half),
        dof=dof,
        rms=float(np.sqrt(np.mean(r**2))),
        rms_real=float(np.sqrt(np.mean(r[:n] ** 2))),
        rms_imag=float(np.sqrt(np.mean(r[n:] ** 2))),
        speeds=np.asarray(plant.speeds),
        measured=measured,
        fitted=lam,
        residuals=r,
        jacobian=J,
        iterations=it,
        converged=converged,
    )


def fit_measurements(data: WeaveData | None = None, method: str = "lagrange") -> tuple[dict[int, KappaFit], OpenLoop]:
    """Fit κ for each gain setting of the embedded data over the speeds in `FIT_SPEEDS` (1.66–4.44 m/s).

    Returns ({gain setting: `KappaFit`}, the `OpenLoop` at all measured speeds, 5.0 m/s included:
    `weave_eigenvalues(plant, fit.kappa)` is the model there, uncontrolled at 5.0 m/s).
    """
    data = load_data() if data is None else data
    plant = open_loop(data.speeds, data.params, method)
    sel = np.flatnonzero((data.speeds >= FIT_SPEEDS[0]) & (data.speeds <= FIT_SPEEDS[1]))
    part = OpenLoop(speeds=plant.speeds[sel], A=plant.A[sel], b=plant.b[sel])
    return {g: fit_kappa(part, data.weave[g][sel]) for g in GAINS}, plant
