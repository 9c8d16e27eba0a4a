"""The seed paper's friction variator, as the README writes it, and its peers.

* `mechanism()`, `PARAMS`, `Q0`, `QD0`, `TS`: the README's example (U21(t) =
  1 + 0.4 sin πt, J1 = 0.02, J2 = 0.05 kg·m², M1 = 0.3, M2 = −0.1 N·m,
  phi1' = phi2' = 2 rad/s at t = 0, 10 s, 101 report times), with jaxnh's
  default settings.
* `reference()`: the closed form (`jaxnh.models.variator.closed_form`, by
  quadrature).
* `eq9(t, y, args)`: the paper's corrected eq. (9) written by hand for
  diffrax, state y = (phi1, phi2, phi1').
* `SYMPY_PIPELINE`: T and the rolling constraint given to SymPy's
  `LagrangesMethod`, its right-hand side lambdified with NumPy for
  `scipy.integrate.solve_ivp` (state (phi1, phi2, phi1', phi2')).
* `numba_tsit5()`: the bare-loop limit, eq. (9) in an adaptive Tsit5 loop
  (diffrax's tableau and error control) compiled by numba.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

import jaxnh as nh


def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def U21(t):
    return 1.0 + 0.4 * jnp.sin(jnp.pi * t)


def rolling(q, qd, t, p):
    return jnp.stack([U21(t) * qd[0] - qd[1]])


def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


def mechanism() -> nh.Mechanism:
    return nh.Mechanism(T, constraints=rolling, forces=torques, names=("phi1", "phi2"))


PARAMS = {k: jnp.asarray(v) for k, v in {"J1": 0.02, "J2": 0.05, "M1": 0.3, "M2": -0.1}.items()}
W0 = 2.0
Q0 = jnp.zeros(2)
QD0 = jnp.array([W0, W0])
TS = jnp.linspace(0.0, 10.0, 101)


def reference():
    """(q, qd) at TS from the closed form, as NumPy arrays."""
    from jaxnh.models import variator as V

    p = V.VariatorParams(
        J1=0.02, J2=0.05, U21=nh.profiles.Fourier(1.0, cos=[0.0], sin=[0.4], period=2.0), M1=0.3, M2=-0.1
    )
    q, qd = V.closed_form(p, TS, w0=W0)
    return np.asarray(q), np.asarray(qd)


def eq9(t, y, args):
    """Eq. (9) by hand: phi1'' = (M1 + U M2 − J2 U U' phi1') / (J1 + J2 U²); y = (phi1, phi2, phi1')."""
    J1, J2, M1, M2 = args
    U = 1.0 + 0.4 * jnp.sin(jnp.pi * t)
    dU = 0.4 * jnp.pi * jnp.cos(jnp.pi * t)
    w = y[2]
    return jnp.stack([w, U * w, (M1 + U * M2 - J2 * U * dU * w) / (J1 + J2 * U**2)])


EQ9_ARGS = (0.02, 0.05, 0.3, -0.1)
EQ9_Y0 = np.array([0.0, 0.0, W0])


def eq9_unpack(ys, ts):
    """(q, qd) from eq. (9)'s states (rows are times)."""
    ys, ts = np.asarray(ys), np.asarray(ts)
    U = 1.0 + 0.4 * np.sin(np.pi * ts)
    return ys[:, :2], np.column_stack([ys[:, 2], U * ys[:, 2]])


SYMPY_PIPELINE = r'''
import numpy as np
import sympy as sm
import sympy.physics.mechanics as me
from scipy.integrate import solve_ivp

def numpy_rhs():
    """Lagrange's equations with the rolling constraint's multiplier, from T, by SymPy."""
    t = me.dynamicsymbols._t
    phi1, phi2 = me.dynamicsymbols("phi1 phi2")
    J1, J2, M1, M2 = sm.symbols("J1 J2 M1 M2")
    U = 1 + sm.Rational(2, 5) * sm.sin(sm.pi * t)
    N = me.ReferenceFrame("N")
    A, B = N.orientnew("A", "Axis", (phi1, N.z)), N.orientnew("B", "Axis", (phi2, N.z))
    L = J1 * phi1.diff(t) ** 2 / 2 + J2 * phi2.diff(t) ** 2 / 2
    lm = me.LagrangesMethod(L, [phi1, phi2], forcelist=[(A, M1 * N.z), (B, M2 * N.z)], frame=N,
                            nonhol_coneqs=[U * phi1.diff(t) - phi2.diff(t)])
    lm.form_lagranges_equations()
    states = [phi1, phi2, phi1.diff(t), phi2.diff(t)]
    f = sm.lambdify((t, states, (J1, J2, M1, M2)), lm.rhs()[:4, 0], cse=True)
    return lambda t_, y, p: np.asarray(f(t_, y, p), dtype=float).ravel()

def solve(rhs, y0, p, ts, rtol, atol, method="RK45"):
    return solve_ivp(rhs, (ts[0], ts[-1]), y0, method=method, t_eval=ts, rtol=rtol, atol=atol, args=(p,))
'''


def sympy_namespace() -> dict:
    ns: dict = {}
    exec(compile(SYMPY_PIPELINE, "<sympy variator>", "exec"), ns)
    return ns


def numba_tsit5():
    """`solve(y0, ts, rtol, atol) -> (ys, steps)`: eq. (9) in an adaptive Tsit5 loop compiled by numba
    (diffrax's Tsit5 tableau, RMS error norm, I-controller with diffrax's default factors, steps clipped
    at the report times), or None without numba. The first call compiles."""
    try:
        import numba
    except ImportError:
        return None
    import diffrax

    tab = diffrax.Tsit5.tableau
    s = len(tab.c) + 1
    A = np.zeros((s, s))
    for i, row in enumerate(tab.a_lower):
        A[i + 1, : len(row)] = row
    c = np.r_[0.0, tab.c]
    e = np.asarray(tab.b_error, float)
    J1, J2, M1, M2 = EQ9_ARGS

    @numba.njit(cache=False)
    def f(t, y, out):
        U = 1.0 + 0.4 * math.sin(math.pi * t)
        dU = 0.4 * math.pi * math.cos(math.pi * t)
        w = y[2]
        out[0] = w
        out[1] = U * w
        out[2] = (M1 + U * M2 - J2 * U * dU * w) / (J1 + J2 * U * U)

    @numba.njit(cache=False)
    def solve(y0, ts, rtol, atol):
        n = y0.size
        K = np.empty((s, n))
        ys = np.empty((ts.size, n))
        ys[0] = y0
        y, y1, tmp = y0.copy(), np.empty(n), np.empty(n)
        t, dt, k, steps = ts[0], 1e-3, 1, 0
        f(t, y, K[0])
        while k < ts.size and steps < 100000:
            t1 = min(t + dt, ts[k])
            h = t1 - t
            for i in range(1, s):
                for j in range(n):
                    acc = 0.0
                    for m in range(i):
                        acc += A[i, m] * K[m, j]
                    tmp[j] = y[j] + h * acc
                f(t + c[i] * h, tmp, K[i])
            err = 0.0
            for j in range(n):
                y1[j] = tmp[j]  # the last stage is the solution (FSAL)
                d = 0.0
                for m in range(s):
                    d += e[m] * K[m, j]
                sc = atol + rtol * max(abs(y[j]), abs(y1[j]))
                err += (h * d / sc) ** 2
            err = math.sqrt(err / n)
            fac = min(10.0, max(0.2, 0.9 * err ** (-1.0 / 5.0))) if err > 0 else 10.0
            steps += 1
            if err <= 1.0:
                hit = t1 == ts[k]
                t = t1
                y[:] = y1
                K[0] = K[s - 1]
                if hit:  # a step shortened to land on a report time does not shrink the next one
                    ys[k] = y
                    k += 1
                    dt = max(dt, h * fac)
                    continue
            dt = h * fac
        return ys, steps

    return solve
