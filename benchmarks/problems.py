"""The benchmark problems, each with its jaxnh mechanism and hand-written right-hand sides.

* The seed paper's variator (s = 2, m = 1, rheonomic): jaxnh derives the
  equations from T and the constraint; `eq9_jax`/`eq9_numpy` are the paper's
  eq. (9) written out by hand, state (phi1, phi2, phi1'); `closed_form` is the
  exact answer.
* A generic mechanism with s = 10 coordinates and m = 3 constraints: a
  configuration-dependent mass matrix `M(q) = M0 + U diag(cos q) Uᵀ`, constraints
  `A(q) qd + g(t) = 0` with `A(q) = A0 + B diag(sin q)`, a chain potential,
  damping and periodic forcing. Its hand-written right-hand side writes out the
  velocity terms h and the constraint terms b of Lagrange's equations and
  solves the (s + m) × (s + m) system `[[M, −Aᵀ], [A, 0]] [qdd; λ] = [Q − ∂V/∂q − h; −b]`
  with a dense solve, as one would by hand. `rheonomic=False` drops every
  explicit time dependence (g and the forcing).

Every NumPy right-hand side here is written for `scipy.integrate.solve_ivp`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.models import variator as V


# --------------------------------------------------------------------------- variator


class Variator(eqx.Module):
    """The variator over [0, T] with report times ts; the reference is the closed form."""

    mech: nh.Mechanism
    params: V.VariatorParams
    ts: jax.Array
    q0: jax.Array
    qd0: jax.Array
    q_ref: jax.Array
    qd_ref: jax.Array


def variator(T: float = 10.0, n: int = 101, w0: float = 1.0, params=None) -> Variator:
    p = V.default_params() if params is None else params
    ts = jnp.linspace(0.0, T, n)
    q_ref, qd_ref = V.closed_form(p, ts, w0=w0)
    qd0 = jnp.array([w0, float(p.U21(0.0)) * w0])
    return Variator(V.mechanism(), p, ts, jnp.zeros(2), qd0, q_ref, qd_ref)


def eq9_jax(t, y, p: V.VariatorParams):
    """Eq. (9) by hand, in the state layout of jaxnh's Appell form: ((phi1, phi2), (phi1',))."""
    phi, w = y
    U, dU = p.U21(t), p.U21.derivative(t)
    wd = (p.M1(t) + U * p.M2(t) - p.J2 * U * dU * w[0]) / (p.J1 + p.J2 * U**2)
    return (jnp.stack([w[0], U * w[0]]), jnp.stack([wd]))


def eq9_state(v: Variator):
    return (v.q0, v.qd0[:1])


def eq9_unpack(ys, ts, p):
    """(q, qd) at the report times from eq. (9)'s state."""
    phi, w = ys
    U = jax.vmap(p.U21)(ts)
    return phi, jnp.stack([w[:, 0], U * w[:, 0]], axis=1)


def eq9_numpy(p: V.VariatorParams):
    """`f(t, y)` of eq. (9) for SciPy, y = (phi1, phi2, phi1'), with plain NumPy floats."""
    J1, J2 = float(p.J1), float(p.J2)
    mean, per = float(p.U21.mean), float(p.U21.period)
    cs, sn = np.asarray(p.U21.cos), np.asarray(p.U21.sin)
    k = 2 * np.pi * np.arange(1, cs.size + 1) / per
    M1, M2 = float(p.M1.value), float(p.M2.value)

    def f(t, y):
        c, s = np.cos(k * t), np.sin(k * t)
        U = mean + cs @ c + sn @ s
        dU = k @ (sn * c - cs * s)
        w = y[2]
        return np.array([w, U * w, (M1 + U * M2 - J2 * U * dU * w) / (J1 + J2 * U * U)])

    def unpack(Y, ts):
        c, s = np.cos(np.outer(ts, k)), np.sin(np.outer(ts, k))
        U = mean + c @ cs + s @ sn
        return Y[:, :2], np.stack([Y[:, 2], U * Y[:, 2]], axis=1)

    return f, unpack


# --------------------------------------------------------------------------- generic s=10, m=3


def generic_params(s: int = 10, m: int = 3, seed: int = 0, rheonomic: bool = True) -> dict:
    """Constant matrices of the generic mechanism (a dict of float64 arrays)."""
    rng = np.random.RandomState(seed)
    masses = 1.0 + rng.rand(s)
    C = 0.05 * rng.randn(s, s)
    M0 = np.diag(masses) + 0.5 * (C + C.T)
    lam_min = np.linalg.eigvalsh(M0).min()
    U = rng.randn(s, s)
    U *= np.sqrt(0.5 * lam_min / np.sum(U**2))  # Σ|u_k|² = λmin/2: M(q) ≻ 0 for every q
    A0 = np.zeros((m, s))
    for r in range(m):  # each constraint ties a few coordinates, like a rolling contact
        A0[r, 3 * r : 3 * r + 3] = rng.randn(3) + np.array([2.0, 0.0, 0.0])
        A0[r, (3 * r + 4) % s] = -1.0
    B = 0.3 * rng.randn(m, s) * (A0 != 0)
    out = dict(
        M0=M0,
        U=U,
        A0=A0,
        B=B,
        gamma=(0.1 * rng.rand(m)) if rheonomic else np.zeros(m),
        omega=1.0 + rng.rand(m),
        damping=0.05 * np.ones(s),
        stiffness=1.0 + rng.rand(s),
        coupling=0.3,
        force=(0.2 * rng.rand(s)) if rheonomic else np.zeros(s),
        Omega=0.5 + rng.rand(s),
    )
    return {k: jnp.asarray(v, dtype=jnp.float64) for k, v in out.items()}


def _mass(q, p):
    return p["M0"] + (p["U"] * jnp.cos(q)) @ p["U"].T


def generic_mechanism(rheonomic: bool = True) -> nh.Mechanism:
    """The generic mechanism as jaxnh sees it: T, constraints, forces, potential."""

    def kinetic(q, qd, t, p):
        return 0.5 * qd @ _mass(q, p) @ qd

    def potential(q, t, p):
        return 0.5 * jnp.sum(p["stiffness"] * q**2) + p["coupling"] * jnp.sum(jnp.cos(q[:-1] - q[1:]))

    if rheonomic:

        def constraints(q, qd, t, p):
            return (p["A0"] + p["B"] * jnp.sin(q)) @ qd + p["gamma"] * jnp.sin(p["omega"] * t)

        def forces(q, qd, t, p):
            return -p["damping"] * qd + p["force"] * jnp.cos(p["Omega"] * t)
    else:

        def constraints(q, qd, t, p):
            return (p["A0"] + p["B"] * jnp.sin(q)) @ qd

        def forces(q, qd, t, p):
            return -p["damping"] * qd

    return nh.Mechanism(kinetic, constraints=constraints, forces=forces, potential=potential)


def generic_rhs_jax(t, y, p):
    """Lagrange's equations with multipliers written out by hand; state (q, qd)."""
    q, qd = y
    s, m = q.shape[0], p["A0"].shape[0]
    sq, cq = jnp.sin(q), jnp.cos(q)
    U = p["U"]
    M = p["M0"] + (U * cq) @ U.T
    a = U.T @ qd
    h = -U @ (sq * qd * a) + 0.5 * sq * a**2
    d = jnp.sin(q[:-1] - q[1:])
    dV = p["stiffness"] * q - p["coupling"] * (jnp.pad(d, (0, 1)) - jnp.pad(d, (1, 0)))
    Q = -p["damping"] * qd + p["force"] * jnp.cos(p["Omega"] * t) - dV
    A = p["A0"] + p["B"] * sq
    b = (p["B"] * cq) @ (qd**2) + p["gamma"] * p["omega"] * jnp.cos(p["omega"] * t)
    K = jnp.block([[M, -A.T], [A, jnp.zeros((m, m))]])
    x = jnp.linalg.solve(K, jnp.concatenate([Q - h, -b]))
    return (qd, x[:s])


def generic_rhs_numpy(p: dict):
    """`f(t, y)` of the hand-written equations for SciPy, y = (q, qd)."""
    P = {k: np.asarray(v) for k, v in p.items()}
    s, m = P["M0"].shape[0], P["A0"].shape[0]
    U, M0, A0, B = P["U"], P["M0"], P["A0"], P["B"]
    K = np.zeros((s + m, s + m))
    rhs = np.zeros(s + m)

    def f(t, y):
        q, qd = y[:s], y[s:]
        sq, cq = np.sin(q), np.cos(q)
        a = U.T @ qd
        h = -U @ (sq * qd * a) + 0.5 * sq * a**2
        d = np.sin(q[:-1] - q[1:])
        dV = P["stiffness"] * q
        dV[:-1] -= P["coupling"] * d
        dV[1:] += P["coupling"] * d
        Q = -P["damping"] * qd + P["force"] * np.cos(P["Omega"] * t) - dV
        A = A0 + B * sq
        K[:s, :s] = M0 + (U * cq) @ U.T
        K[:s, s:] = -A.T
        K[s:, :s] = A
        rhs[:s] = Q - h
        rhs[s:] = -((B * cq) @ (qd**2) + P["gamma"] * P["omega"] * np.cos(P["omega"] * t))
        x = np.linalg.solve(K, rhs)
        return np.concatenate([qd, x[:s]])

    return f


class Generic(eqx.Module):
    mech: nh.Mechanism
    params: dict
    ts: jax.Array
    q0: jax.Array
    qd0: jax.Array
    independent: tuple = eqx.field(static=True)


def generic(T: float = 10.0, n: int = 101, rheonomic: bool = True, s: int = 10, m: int = 3) -> Generic:
    """The generic mechanism from a consistent initial state (q0, qd0) at t = 0."""
    p = generic_params(s, m, rheonomic=rheonomic)
    mech = generic_mechanism(rheonomic)
    rng = np.random.RandomState(1)
    q0 = jnp.asarray(0.4 * rng.randn(s))
    qd0 = nh.consistent_velocities(mech, q0, jnp.asarray(rng.randn(s)), 0.0, p)
    ind = nh.choose_independent(mech, q0, qd0, 0.0, p)
    return Generic(mech, p, jnp.linspace(0.0, T, n), q0, qd0, ind)
