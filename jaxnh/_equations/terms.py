"""The terms of the equations of motion, each by automatic differentiation.

For kinetic energy T(q, qd, t) the Lagrange expression is

    d/dt ∂T/∂qd − ∂T/∂q = M(q, t) qdd + h(q, qd, t),

with the mass matrix `M = ∂²T/∂qd²` and the velocity terms
`h = (∂p/∂q) qd + ∂p/∂t − ∂T/∂q`, where `p = ∂T/∂qd` is the generalized
momentum (the ∂p/∂t term is the explicit time dependence of a rheonomic T).

A constraint `c(q, qd, t) = 0` differentiated along the motion gives the
acceleration-level constraint `A qdd + b = 0` with `A = ∂c/∂qd` and
`b = (∂c/∂q) qd + ∂c/∂t`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnh._base.linalg import mm, solve_spd


def _along(f, q, qd, t, dqd, rate=None):
    """`f(q, qd, t)` and its derivatives along the k velocity directions `dqd` (s, k) and along the
    motion (q, t) → (q + qd dt, t + dt), in one forward pass over one evaluation of f.

    Returns (f, (k,) + f's shape, f's shape): f's value, its derivatives ∂f/∂qd · dqd_j, and
    (∂f/∂q) q̇ + ∂f/∂t with q̇ = `rate` (default qd itself). The k + 1 tangents are batched (`vmap` of
    `jvp`): f and, for a gradient f, its reverse pass, are traced and evaluated once, not once per
    quantity."""
    k = dqd.shape[1]
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.inexact):  # (an integer time has no tangent)
        t = t.astype(q.dtype)
    motion = qd if rate is None else rate
    tq = jnp.concatenate([jnp.zeros((k, q.shape[0]), q.dtype), motion[None, :].astype(q.dtype)])
    tqd = jnp.concatenate([dqd.T.astype(qd.dtype), jnp.zeros((1, qd.shape[0]), qd.dtype)])
    tt = jnp.concatenate([jnp.zeros((k,), t.dtype), jnp.ones((1,), t.dtype)])

    def push(a, b, c):
        return jax.jvp(f, (q, qd, t), (a, b, c))

    value, d = jax.vmap(push, out_axes=(None, 0))(tq, tqd, tt)
    return value, jax.tree_util.tree_map(lambda x: x[:k], d), jax.tree_util.tree_map(lambda x: x[k], d)


def _gradients(mech, params):
    """(q, qd, t) → (∂T/∂q, ∂T/∂qd): the second is the generalized momentum p."""
    return lambda q_, qd_, t_: jax.grad(mech.kinetic, argnums=(0, 1))(q_, qd_, t_, params)


def mass_and_velocity_terms(mech, q, qd, t, params):
    """Mass matrix M (s, s) and velocity terms h (s,) of the Lagrange expression, from one
    forward pass (s + 1 tangents) over one reverse pass of T.

    With speeds u (`mech.kinematics`, q̇ = K(q, t) u + k(q, t)) these are the terms of the
    Boltzmann–Hamel equations, `M u̇ + h = Q + Aᵀ λ` with `M = ∂²T/∂u²` and
    `h = (∂p/∂q) q̇ + ∂p/∂t − Kᵀ ∂T/∂q + Γᵀ p`, p = ∂T/∂u (`speed_terms`)."""
    if mech.kinematics is not None:
        return speed_terms(mech, q, qd, t, params)
    (dTdq, _), (_, Mt), (_, dp) = _along(_gradients(mech, params), q, qd, t, jnp.eye(qd.shape[0], dtype=qd.dtype))
    return Mt.T, dp - dTdq


def speed_terms(mech, q, u, t, params):
    """M (n_u, n_u) and h (n_u,) of the equations of motion in the speeds u (Boltzmann–Hamel).

    With q̇ = r(q, u, t) = K(q, t) u + k(q, t) and T(q, u, t), the principle of virtual work
    along the admissible displacements δq = K δπ gives, for each speed j,

        d/dt ∂T/∂u_j − K_jᵀ ∂T/∂q + p · γ_j = Q_j,     K γ_j = (∂r/∂q) K_j − dK_j/dt,

    where K_j is the column of K, dK_j/dt = (∂K_j/∂q) q̇ + ∂K_j/∂t its rate along the motion,
    and γ_j carries the transpositional (Hamel) terms: the commutators of the fields K_j, and of
    each K_j with the motion's own drift. γ_j is well defined because the right-hand side is
    tangent to the configuration manifold whenever the fields are (for a unit quaternion, the
    sphere), and K has full column rank: it is taken by least squares. Everything is by automatic
    differentiation of the user's T and `kinematics`; no term is written by hand. For a rigid body
    with body angular velocity ω as speeds, T = ½ ωᵀIω, this gives Euler's I ω̇ + ω × Iω.
    """
    dtype = jnp.result_type(q, u)
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.inexact):
        t = t.astype(q.dtype)

    def rate(q_, u_, t_):
        return mech.rate(q_, u_, t_, params)

    r = rate(q, u, t)
    (dTdq, p), (_, Mt), (_, dp) = _along(_gradients(mech, params), q, u, t, jnp.eye(u.shape[0], dtype=u.dtype), r)

    def kmat(q_, t_):
        return jax.jacfwd(rate, argnums=1)(q_, u, t_)

    K, Kdot = jax.jvp(kmat, (q, t), (r.astype(q.dtype), jnp.ones_like(t)))
    JK = jax.vmap(lambda d: jax.jvp(lambda q_: rate(q_, u, t), (q,), (d,))[1], in_axes=1, out_axes=1)(K)
    V = JK - Kdot
    gamma = solve_spd(mm(K.T, K), mm(K.T, V))
    h = dp - mm(K.T, dTdq.astype(dtype)) + mm(gamma.T, p)
    # V outside the span of K (a nonholonomic constraint written into q̇ = K u, `speeds_span_velocities`)
    # meets a part of ∂T/∂q̇ that T in the speeds does not give: no answer, NaN (never a wrong one)
    eps = jnp.finfo(dtype).eps
    off = jnp.sqrt(jnp.sum((V - mm(K, gamma)) ** 2, axis=0))
    allowed = jnp.sqrt(eps) * jnp.sqrt(jnp.sum(V**2, axis=0)) + 64 * eps * jnp.sqrt(jnp.sum(JK**2 + Kdot**2, axis=0))
    h = jnp.where(jnp.all(off <= allowed), h, jnp.nan)
    return Mt.T, h


def projected_terms(mech, q, qd, t, params, B, beta):
    """`K = Bᵀ M B` (k, k) and `r = Bᵀ (M β + h)` (k,) for the velocity map qd = B v + ...

    The derived Appell field's system matrix and right-hand side from the k + 1
    products `M [B, β]` (the momentum pushed forward along those velocity
    directions only), not from the whole mass matrix: no unused Jacobian column
    is formed (for the variator, k = 1 of s = 2). (Not through `_along`: for the variator's
    flattened Appell field the k + 2 tangents of both gradients made a step 1.5× slower.)
    """
    k = B.shape[1]
    if mech.kinematics is not None:  # the speeds' terms carry Hamel's: from the full M and h
        M, h = speed_terms(mech, q, qd, t, params)
        MB = mm(M, B)
        return mm(B.T, MB), mm(B.T, mm(M, beta) + h)

    def momentum(q_, qd_, t_):
        return jax.grad(mech.kinetic, argnums=1)(q_, qd_, t_, params)

    _, dp = jax.jvp(lambda q_, t_: momentum(q_, qd, t_), (q, t), (qd, jnp.ones_like(t)))
    dTdq = jax.grad(mech.kinetic, argnums=0)(q, qd, t, params)

    def along(d):
        return jax.jvp(lambda v: momentum(q, v, t), (qd,), (d,))[1]

    MD = jax.vmap(along, in_axes=1, out_axes=1)(jnp.concatenate([B, beta[:, None]], axis=1))
    return mm(B.T, MD[:, :k]), mm(B.T, dp - dTdq + MD[:, k])


def constraint_terms(mech, q, qd, t, params):
    """Constraint matrix A = ∂c/∂qd (m, s) and b (m,) with A qdd + b = 0."""

    def c(q_, qd_, t_):
        return mech.constraint(q_, qd_, t_, params)

    rate = mech.rate(q, qd, t, params) if mech.kinematics is not None else None
    _, At, b = _along(c, q, qd, t, jnp.eye(qd.shape[0], dtype=qd.dtype), rate)
    return At.T, b


def speeds_span_velocities(mech, q, u, t, params) -> jax.Array:
    """Whether the speeds' fields K_j (the columns of K = ∂q̇/∂u) close on themselves: each
    commutator (∂K_k/∂q) K_j − (∂K_j/∂q) K_k, and each drift term (∂k/∂q) K_j − (∂K_j/∂q) k − ∂K_j/∂t
    (k = q̇ at u = 0), lies in the span of K, to √eps of its size (a bool at (q, t); u gives only the
    number of speeds).

    It holds for speeds that parameterise every velocity of the configuration (angles with rates of
    their own, a unit quaternion with an angular velocity: its fields are tangent to the sphere), and
    `speed_terms` is then exact. It fails where `kinematics` itself forbids velocities the
    configuration has, a nonholonomic constraint written into q̇ = K u (a rolling condition, a knife
    edge): T in the speeds then does not determine the motion (Hamel's terms need ∂T/∂q̇ off the
    allowed velocities), and such a constraint belongs in `constraints`, written in speeds that span
    every velocity.
    """
    dtype = q.dtype
    t = jnp.asarray(t, dtype)
    zero = jnp.zeros(u.shape, dtype)

    def rate(q_, t_):
        return mech.rate(q_, zero, t_, params).astype(dtype)

    def kmat(q_, t_):
        return jax.jacfwd(lambda v: mech.rate(q_, v, t_, params).astype(dtype))(zero)

    K, k0 = kmat(q, t), rate(q, t)
    dK, dKt = jax.jacfwd(kmat, argnums=(0, 1))(q, t)  # (nq, nu, nq): ∂K_aj/∂q_i; (nq, nu)
    dk0 = jax.jacfwd(rate)(q, t)  # (nq, nq)
    nq = q.shape[0]
    DKK = jnp.einsum("aki,ij->ajk", dK, K)  # [a, j, k] = ((∂K_k/∂q) K_j)_a
    commutators = (DKK - jnp.swapaxes(DKK, 1, 2)).reshape(nq, -1)
    commutator_terms = (jnp.abs(DKK) + jnp.abs(jnp.swapaxes(DKK, 1, 2))).reshape(nq, -1)
    a, b = dk0 @ K, jnp.einsum("aji,i->aj", dK, k0)
    drifts = a - b - dKt
    drift_terms = jnp.abs(a) + jnp.abs(b) + jnp.abs(dKt)
    vecs = jnp.concatenate([commutators, drifts], axis=1)
    terms = jnp.concatenate([commutator_terms, drift_terms], axis=1)
    residual = vecs - mm(K, solve_spd(mm(K.T, K), mm(K.T, vecs)))
    eps = jnp.finfo(dtype).eps
    # rounding: a commutator that is exactly 0 comes out as the difference of two equal products
    floor = 64 * eps * jnp.sqrt(jnp.sum(terms**2, axis=0))
    ok = jnp.sqrt(jnp.sum(residual**2, axis=0)) <= jnp.sqrt(eps) * jnp.sqrt(jnp.sum(vecs**2, axis=0)) + floor
    return jnp.all(ok | ~jnp.isfinite(jnp.sum(residual**2, axis=0)))
