"""A car pulling N trailers: the size study's mechanism, three ways.

Bodies 0 (the car) … N (the trailers) move on a plane, each resting on one
axle with a knife edge (no sideways velocity at the axle). Body i's axle is
the point P_i, its heading θ_i; its mass centre lies a_i ahead of its axle,
its hitch b_i behind it; trailer i hangs from the hitch of body i − 1 by a
drawbar of length L_i:

    P_i = P_{i−1} − b_{i−1} e(θ_{i−1}) − L_i e(θ_i),   e(θ) = (cos θ, sin θ).

Coordinates (s = N + 3): the car's axle (x, y) (m) and the headings θ_0 … θ_N
(rad). Constraints (m = N + 1): the sideways velocity of every axle (m/s).
Two degrees of freedom remain: the car's forward speed and its yaw rate. A
thrust F along the car, a drag −c v at its axle and a steering torque
τ sin(ω t) on it (rheonomic) drive the train.

1. `mechanism(N)`, `params(N)`, `initial_state(N)`: jaxnh, written as a user
   writes from docs/own-mechanism.md (positions by cumulative sums, velocities
   by `jax.jvp` inside T and the constraints).
2. `SYMPY_PIPELINE`: the same mechanism with `sympy.physics.mechanics`
   (frames, points by the two-point theorem, `KanesMethod` with the knife
   edges as velocity constraints, generalized speeds (forward speed, sideways
   speed, yaw rates) of which the sideways speed and the trailers' yaw rates
   are dependent), lambdified with NumPy and integrated by `scipy.integrate.
   solve_ivp`: the source of a script a user would write, run by `exec` (the
   size study runs it in fresh processes).
3. `jax_source(N)`: the same SymPy equations printed as the Python source of
   a JAX right-hand side (common subexpressions, `jnp` calls, a dense solve
   for the speeds' rates), "the equations written by hand in JAX". Generated
   at run time, never stored.

Units: m, kg, kg·m², N, N·m, rad, s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh


T_END = 10.0
N_REPORT = 101


# --------------------------------------------------------------------------- 1. jaxnh


def heading(th):
    return jnp.stack([jnp.cos(th), jnp.sin(th)], axis=-1)


def axles(q, p):
    """Axle points P_0 … P_N (N + 1, 2), m: the car's, then each trailer's behind the one before."""
    e = heading(q[2:])
    steps = -(p["b"][:, None] * e[:-1] + p["L"][:, None] * e[1:])
    return q[:2] + jnp.concatenate([jnp.zeros((1, 2), q.dtype), jnp.cumsum(steps, axis=0)])


def centres(q, p):
    """Mass centres (N + 1, 2), m."""
    return axles(q, p) + p["a"][:, None] * heading(q[2:])


def kinetic(q, qd, t, p):
    _, v = jax.jvp(lambda q: centres(q, p), (q,), (qd,))
    return 0.5 * jnp.sum(p["m"] * jnp.sum(v**2, axis=-1)) + 0.5 * jnp.sum(p["I"] * qd[2:] ** 2)


def knife_edges(q, qd, t, p):
    """Sideways velocity of every axle (N + 1,), m/s."""
    _, v = jax.jvp(lambda q: axles(q, p), (q,), (qd,))
    th = q[2:]
    return -jnp.sin(th) * v[:, 0] + jnp.cos(th) * v[:, 1]


def drive(q, qd, t, p):
    """Thrust along the car and drag at its axle (N), steering torque on the car (N·m)."""
    push = p["F"] * heading(q[2]) - p["c"] * qd[:2]
    steer = p["tau"] * jnp.sin(p["omega"] * t)
    return jnp.concatenate([push, jnp.stack([steer]), jnp.zeros(q.shape[0] - 3, q.dtype)])


def mechanism(N: int) -> nh.Mechanism:
    names = ("x", "y") + tuple(f"theta{i}" for i in range(N + 1))
    return nh.Mechanism(kinetic, constraints=knife_edges, forces=drive, names=names)


def params(N: int) -> dict:
    """Car: 2 kg, 0.5 kg·m², centre 0.8 m ahead of the axle, hitch 0.4 m behind; trailers: 1 kg,
    0.2 kg·m², centre 0.3 m ahead of the axle, drawbar 1 m, hitch 0.3 m behind."""
    f = jnp.float64
    m = np.r_[2.0, np.ones(N)]
    return {
        "m": jnp.asarray(m, f),
        "I": jnp.asarray(np.r_[0.5, 0.2 * np.ones(N)], f),
        "a": jnp.asarray(np.r_[0.8, 0.3 * np.ones(N)], f),
        "b": jnp.asarray(np.r_[0.4, 0.3 * np.ones(N - 1)], f),
        "L": jnp.asarray(np.ones(N), f),
        "F": jnp.asarray(1.0, f),
        "c": jnp.asarray(0.5, f),
        "tau": jnp.asarray(0.3, f),
        "omega": jnp.asarray(1.0, f),
    }


def initial_state(N: int, p=None):
    """(q0, qd0): trailers zig-zag by 0.2 rad, the car moves at 1 m/s turning at 0.3 rad/s; the trailers'
    yaw rates follow from their knife edges."""
    p = params(N) if p is None else p
    th = 0.2 * np.sin(np.arange(N + 1))
    q0 = np.r_[0.0, 0.0, th]
    qd0 = np.r_[np.cos(th[0]), np.sin(th[0]), 0.3, np.zeros(N)]
    A = np.asarray(jax.jacobian(knife_edges, argnums=1)(jnp.asarray(q0), jnp.asarray(qd0), 0.0, p))
    qd0[3:] = np.linalg.solve(A[1:, 3:], -A[1:, :3] @ qd0[:3])
    return jnp.asarray(q0), jnp.asarray(qd0)


def report_times():
    return jnp.linspace(0.0, T_END, N_REPORT)


KEYS = ("m", "I", "a", "b", "L", "F", "c", "tau", "omega")


def param_vector(p):
    """The parameters in the order of the SymPy symbols (`SYMPY_PIPELINE`'s `params`), (5N + 6,)."""
    return jnp.concatenate([jnp.ravel(jnp.asarray(p[k])) for k in KEYS])


def param_dict(N: int, v) -> dict:
    """Inverse of `param_vector`."""
    sizes = (N + 1, N + 1, N + 1, N, N, 1, 1, 1, 1)
    parts = jnp.split(jnp.asarray(v), np.cumsum(sizes)[:-1])
    return {k: (x if k in KEYS[:5] else x[0]) for k, x in zip(KEYS, parts)}


def to_speeds(q, qd):
    """Kane's generalized speeds (forward, sideways, yaw rates) from (q, qd) (rows are times)."""
    q, qd = np.atleast_2d(q), np.atleast_2d(qd)
    c, s = np.cos(q[:, 2]), np.sin(q[:, 2])
    return np.column_stack([c * qd[:, 0] + s * qd[:, 1], -s * qd[:, 0] + c * qd[:, 1], qd[:, 2:]])


def from_state(y):
    """(q, qd) from Kane's state [q, u] (rows are times)."""
    y = np.atleast_2d(np.asarray(y))
    n = y.shape[1] // 2
    q, u = y[:, :n], y[:, n:]
    c, s = np.cos(q[:, 2]), np.sin(q[:, 2])
    qd = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], u[:, 2:]])
    return q, qd


# --------------------------------------------------------------------------- the reference


def lagrange_numpy(N: int, p):
    """`f(t, y)` for `solve_ivp`, y = (q, qd): Lagrange's equations with multipliers written out by hand
    in NumPy, `[[M, −Aᵀ], [A, 0]] [q̈; λ] = [Q − h; −b]`, the reference of the size study.

    Every point is X = (x, y) − Σ_k w_k e_k (w a row of lever arms), so ∂X/∂θ_k = −w_k n_k and
    J̇q̇ = Σ_k w_k θ̇_k² e_k, with n_k = (−sin θ_k, cos θ_k). T = Σ ½ m_i |Ġ_i|² + ½ I_i θ̇_i² gives
    M = Σ m_i J_Giᵀ J_Gi + diag(0, 0, I) and h = Σ m_i J_Giᵀ J̇_Gi q̇; the knife edge of axle i is
    n_i · Ṗ_i = A_i q̇ and b_i = n_i · J̇_Pi q̇ − θ̇_i e_i · Ṗ_i.
    """
    P = {k: np.asarray(v, float) for k, v in p.items()}
    s = N + 3
    W_P = np.zeros((N + 1, N + 1))  # lever arms of the axles: P_i = P_{i−1} − b_{i−1} e_{i−1} − L_i e_i
    for i in range(1, N + 1):
        W_P[i] = W_P[i - 1]
        W_P[i, i - 1] += P["b"][i - 1]
        W_P[i, i] += P["L"][i - 1]
    W_G = W_P - np.diag(P["a"])
    M_theta = np.diag(np.r_[0.0, 0.0, P["I"]])

    def jac(W, e, n):
        J = np.zeros((N + 1, 2, s))
        J[:, 0, 0] = J[:, 1, 1] = 1.0
        J[:, :, 2:] = -(W[:, None, :] * n.T[None, :, :])
        return J

    def f(t, y):
        q, qd = y[:s], y[s:]
        th, w = q[2:], qd[2:]
        e, n = np.c_[np.cos(th), np.sin(th)], np.c_[-np.sin(th), np.cos(th)]
        JG, JP = jac(W_G, e, n), jac(W_P, e, n)
        aG, aP = (W_G * w**2) @ e, (W_P * w**2) @ e  # J̇ q̇ of every centre and axle (N + 1, 2)
        M = np.einsum("i,iak,ial->kl", P["m"], JG, JG) + M_theta
        h = np.einsum("i,iak,ia->k", P["m"], JG, aG)
        A = np.einsum("ia,iak->ik", n, JP)
        vP = JP @ qd
        b = np.sum(n * aP, axis=1) - w * np.sum(e * vP, axis=1)
        Q = np.zeros(s)
        Q[:2] = P["F"] * e[0] - P["c"] * qd[:2]
        Q[2] = P["tau"] * np.sin(P["omega"] * t)
        K = np.block([[M, -A.T], [A, np.zeros((N + 1, N + 1))]])
        return np.r_[qd, np.linalg.solve(K, np.r_[Q - h, -b])[:s]]

    return f


def reference(N: int, p, q0, qd0, ts):
    """(q, qd) at ts from `lagrange_numpy` by SciPy's DOP853 at rtol 1e-12, atol 1e-14."""
    from scipy.integrate import solve_ivp

    ts = np.asarray(ts)
    y0 = np.r_[np.asarray(q0, float), np.asarray(qd0, float)]
    sol = solve_ivp(lagrange_numpy(N, p), (ts[0], ts[-1]), y0, "DOP853", t_eval=ts, rtol=1e-12, atol=1e-14)
    if sol.status != 0:
        raise RuntimeError(f"reference solve failed: {sol.message}")
    return sol.y[: N + 3].T, sol.y[N + 3 :].T


# --------------------------------------------------------------------------- 2. SymPy, as a user writes it

SYMPY_PIPELINE = r'''
import numpy as np
import sympy as sm
import sympy.physics.mechanics as me
from scipy.integrate import solve_ivp

def derive(N):
    """Kane's equations of the car with N trailers."""
    t = me.dynamicsymbols._t
    x, y = me.dynamicsymbols("x y")
    th = me.dynamicsymbols(f"theta0:{N + 1}")
    v, vs = me.dynamicsymbols("v v_s")                   # forward and sideways speed of the car's axle
    w = me.dynamicsymbols(f"w0:{N + 1}")                 # yaw rates
    m, I, a = sm.symbols(f"m0:{N + 1}"), sm.symbols(f"I0:{N + 1}"), sm.symbols(f"a0:{N + 1}")
    b, L = sm.symbols(f"b0:{N}"), sm.symbols(f"L1:{N + 1}")
    F, c, tau, omega = sm.symbols("F c tau omega")

    Nf = me.ReferenceFrame("N")
    O = me.Point("O")
    O.set_vel(Nf, 0)
    B = []
    for i in range(N + 1):
        Bi = Nf.orientnew(f"B{i}", "Axis", (th[i], Nf.z))
        Bi.set_ang_vel(Nf, w[i] * Nf.z)
        B.append(Bi)
    P = [O.locatenew("P0", x * Nf.x + y * Nf.y)]
    P[0].set_vel(Nf, v * B[0].x + vs * B[0].y)
    for i in range(1, N + 1):
        H = P[i - 1].locatenew(f"H{i - 1}", -b[i - 1] * B[i - 1].x)
        H.v2pt_theory(P[i - 1], Nf, B[i - 1])
        Pi = H.locatenew(f"P{i}", -L[i - 1] * B[i].x)
        Pi.v2pt_theory(H, Nf, B[i])
        P.append(Pi)
    bodies = []
    for i in range(N + 1):
        G = P[i].locatenew(f"G{i}", a[i] * B[i].x)
        G.v2pt_theory(P[i], Nf, B[i])
        bodies.append(me.RigidBody(f"body{i}", G, B[i], m[i], (me.inertia(B[i], 0, 0, I[i]), G)))
    loads = [(P[0], F * B[0].x - c * P[0].vel(Nf)), (B[0], tau * sm.sin(omega * t) * Nf.z)]

    kd = [v - (sm.cos(th[0]) * x.diff(t) + sm.sin(th[0]) * y.diff(t)),
          vs - (-sm.sin(th[0]) * x.diff(t) + sm.cos(th[0]) * y.diff(t))]
    kd += [w[i] - th[i].diff(t) for i in range(N + 1)]
    knife = [P[i].vel(Nf).dot(B[i].y) for i in range(N + 1)]
    kane = me.KanesMethod(Nf, q_ind=[x, y, *th], u_ind=[v, w[0]], u_dependent=[vs, *w[1:]],
                          kd_eqs=kd, velocity_constraints=knife)
    kane.kanes_equations(bodies, loads)
    q = [x, y, *th]
    u = [v, w[0], vs, *w[1:]]
    params = [*m, *I, *a, *b, *L, F, c, tau, omega]
    return kane, q, u, params, t

def numpy_rhs(N):
    """(rhs(t, y, p) for solve_ivp with y = [q, u in kane order], the derivation)."""
    kane, q, u, params, t = derive(N)
    qdot = sm.Matrix([kane.kindiffdict()[qi.diff(t)] for qi in q])
    M = sm.lambdify((t, q, u, params), kane.mass_matrix, cse=True)
    f = sm.lambdify((t, q, u, params), kane.forcing, cse=True)
    g = sm.lambdify((t, q, u, params), qdot, cse=True)
    n = len(q)

    def rhs(t_, y, p):
        qq, uu = y[:n], y[n:]
        ud = np.linalg.solve(M(t_, qq, uu, p), np.asarray(f(t_, qq, uu, p)).ravel())
        return np.concatenate([np.asarray(g(t_, qq, uu, p)).ravel(), ud])

    return rhs, (kane, q, u, params, t, qdot)

def solve(rhs, y0, p, ts, rtol, atol, method="RK45"):
    return solve_ivp(rhs, (ts[0], ts[-1]), y0, method=method, t_eval=ts, rtol=rtol, atol=atol, args=(p,))
'''
"""A SymPy/SciPy script. Kane's speeds are ordered [v, w0, v_s, w1 … wN] (independent first):
`kane_state` maps (q, qd) to that layout."""


def sympy_namespace() -> dict:
    ns: dict = {}
    exec(compile(SYMPY_PIPELINE, "<sympy pipeline>", "exec"), ns)
    return ns


def kane_state(q, qd) -> np.ndarray:
    """[q, u] with u in Kane's order [v, w0, v_s, w1 … wN]."""
    u = to_speeds(q, qd)[0]
    return np.r_[np.asarray(q, float), u[0], u[2], u[1], u[3:]]


def kane_unpack(Y) -> tuple:
    """(q, qd) rows from Kane-ordered states (rows are times)."""
    Y = np.atleast_2d(np.asarray(Y))
    n = Y.shape[1] // 2
    q, u = Y[:, :n], Y[:, n:]
    u = np.column_stack([u[:, 0], u[:, 2], u[:, 1], u[:, 3:]])
    return from_state(np.column_stack([q, u]))


# --------------------------------------------------------------------------- 3. generated JAX source


def jax_source(N: int, ns: dict | None = None) -> str:
    """Python source of `rhs(t, y, p)` (diffrax's signature; y = [q, u] in Kane's order, p the flat
    parameter vector) computing Kane's equations of `SYMPY_PIPELINE` with `jnp`."""
    import sympy as sm
    from sympy.printing.numpy import JaxPrinter

    ns = sympy_namespace() if ns is None else ns
    kane, q, u, prm, t = ns["derive"](N)
    qdot = sm.Matrix([kane.kindiffdict()[qi.diff(t)] for qi in q])
    n, o = len(q), len(u)
    names = {qi: sm.Symbol(f"q_{i}") for i, qi in enumerate(q)}
    names.update({ui: sm.Symbol(f"u_{i}") for i, ui in enumerate(u)})
    names.update({pi: sm.Symbol(f"p_{i}") for i, pi in enumerate(prm)})
    names[t] = sm.Symbol("t")
    exprs = [e.xreplace(names) for e in (*kane.mass_matrix, *kane.forcing, *qdot)]
    subs, red = sm.cse(exprs)
    pr = JaxPrinter()
    lines = [
        "import jax",
        "import jax.numpy as jnp",
        "",
        "",
        "def rhs(t, y, p):",
        f"    {', '.join(f'q_{i}' for i in range(n))}, = y[:{n}]",
        f"    {', '.join(f'u_{i}' for i in range(o))}, = y[{n}:]",
        f"    {', '.join(f'p_{i}' for i in range(len(prm)))}, = p",
    ]
    lines += [f"    {s} = {pr.doprint(e)}" for s, e in subs]
    M, f, g = red[: o * o], red[o * o : o * o + o], red[o * o + o :]
    rows = ", ".join("[" + ", ".join(pr.doprint(M[r * o + k]) for k in range(o)) + "]" for r in range(o))
    lines.append(f"    M = jnp.array([{rows}])")
    lines.append(f"    f = jnp.array([{', '.join(pr.doprint(e) for e in f)}])")
    lines.append(f"    qd = jnp.array([{', '.join(pr.doprint(e) for e in g)}])")
    lines.append("    return jnp.concatenate([qd, jnp.linalg.solve(M, f)])")
    return "\n".join(lines) + "\n"


def load_source(src: str):
    """The `rhs` of a generated source text."""
    ns: dict = {}
    exec(compile(src, "<generated chain rhs>", "exec"), ns)
    return ns["rhs"]
