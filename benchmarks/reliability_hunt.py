"""The hunt families of the reliability report (issue 46, item 6): classes an outside hunt found
and the fuzz suite did not cover, each judged with the five outcomes of
benchmarks/reliability_cases.py (right / clear error / failure status / unclear error / silent
wrong) against an exact reference.

* **design helpers** — `jaxnh.design.fd_gradient` on functions with exact derivatives
  (A·exp(b x), cubic polynomials, A·x^k) at |x| from 1e-12 to 1e12 and scales A from 1e-8 to 1e8,
  in float64 and float32.
* **linearize with S** — `jaxnh.linearize(method="appell")` on the variator (dict parameters,
  ratio U(t) = U0 + a sin(2πt/P)) with an acceleration energy S that agrees with T, that disagrees
  by a drawn factor, and that is off by a factor at rounding level; against the exact state
  matrix of the reduced equation, by hand.
* **implicit solvers at report times** — `diffrax.Kvaerno5()` (diffrax's root finder, and
  optimistix.Newton) on `jaxnh.models.variator` at drawn rtol and report grids, against
  `variator.closed_form`, within the bound of tests/test_implicit_reports.py.
* **float32, long horizon** — the variator in float32 over 100–1000 s against its closed form in
  float64, within a bound from the tolerance, the steps and float32's time resolution.
* **failure messages** — inputs that must fail (dtmax not positive, a step bound that exhausts
  max_steps, a force or T that turns NaN mid-run, constraint rows that lose rank mid-run with
  method="appell", a root finder that cannot converge): clear only if the status and its words
  name the real cause.

Every mechanism here is a module-level object whose numbers are traced parameters, so each
family compiles its programs once (`run_all` yields (interface, class, case, outcome)).
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any, Callable

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

import jaxnh as nh
from benchmarks import reliability_cases as R
from jaxnh.design import fd_gradient
from jaxnh.models import variator as V
from jaxnh.profiles import Fourier


FAMILY = "hunt"
FAMILIES = {
    "fd_gradient": "design helpers (fd_gradient)",
    "linearize with S": "linearize with an acceleration energy S (variator)",
    "Kvaerno5": "implicit solvers at report times (variator)",
    "float32": "float32 over a long horizon (variator)",
    "failure": "failure messages",
}
KNOWN_ISSUES: dict = {}
"""Library issues found by these families and not yet fixed, as `reliability_cases.KNOWN_ISSUES` (the
report lists them with R's; a case in their territory carries the key in `known`). None open."""
RATIOS: dict = {}
"""Largest (error / bound) of a right answer per interface, for the report's text."""


def family_of(api: str):
    """The report's family of an interface row of this module, or None."""
    for key, label in FAMILIES.items():
        if api.startswith(key):
            return label
    return None


@dataclasses.dataclass
class HCase:
    """One call of a hunt family: `spec` holds everything the call takes (printed by `repro`)."""

    cls: str
    what: str = ""
    spec: dict = dataclasses.field(default_factory=dict)
    family: str = FAMILY
    known: str = ""
    names: str = r"$^"


def repro(row, case: HCase) -> str:
    spec = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in case.spec.items()}
    return f"# {row[0]}: benchmarks/reliability_hunt.py, class {case.cls!r}\n{spec!r}"


def _ratio(api, err, bound):
    RATIOS[api] = max(RATIOS.get(api, 0.0), float(err / bound))


# =====================================================================================
# 1. design helpers: fd_gradient against exact derivatives
# =====================================================================================
#
# fd_gradient documents an error of order eps^(2/3) of |∂f/∂x| + |f| / L (L the length on which f
# varies at x), with the constants: tests/test_fd_gradient.py holds it to 8 eps^(2/3) of that.
# Here |∂f/∂x| is taken as D, the sum of the magnitudes of its terms, and |f| as F, the size of f's
# rounding in units of eps: each term's magnitude times its condition number (fd_gradient's δ is "the
# relative noise of f"; A exp(b x) computed in floating point has the noise (1 + |b x|) eps, as the
# rounding of b x is amplified by |b x|), and L is the length f varies on (1/|b| for A exp(b x),
# |x|/max(1, |k|) for A x^k, Σ|terms|/D for the polynomial; the step is shortened towards h L where
# L < |x|, so the rounding term is F/L, not F/|x|), so the allowance is
#     FD_C eps^(2/3) (D + F / L),   FD_C = 8,
# A ValueError from fd_gradient that names the entry, f(params), h or scale is a clear error; NaN
# or inf in its result a failure; a finite result outside the allowance silent wrong.

FD_C = 8.0
FD_CLASSES = ("fd: A exp(b x)", "fd: cubic polynomial", "fd: A x^k", "fd: float32", "fd: bad argument")
FD_WORDS = r"fd_gradient: .*(entry x|f\(params\)|\bh\b|scale|resolution)"


def _fd_exp(p):
    return p["A"] * jnp.exp(p["b"] * p["x"])


def _fd_poly(p):
    x = p["x"]
    return p["A"] * (p["c0"] + p["c1"] * x + p["c2"] * x**2 + p["c3"] * x**3)


def _fd_power(k):
    return lambda p: p["A"] * p["x"] ** k


def _fd_terms(kind, p, k=None):
    """(f, f', F, D) at p in float64 from the (dtype-rounded) values (exact to a few ulp): F is the
    size of f's rounding in units of eps, Σ |term| × its condition number (exp(b x): 1 + |b x|, the
    rounding of b x amplified; x^k: 1 + |k| (1 + |log x|) for k not an integer, exp(k log x), and
    1 + |k| for repeated products; the polynomial's x^i: i + 1), D = Σ |terms of f'|, and L the length
    on which f varies at x (1/|b|; |x| / max(1, |k|); the polynomial's Σ |terms| / D)."""
    x, A = p["x"], p["A"]
    if kind == "exp":
        e = A * math.exp(p["b"] * x)
        return e, e * p["b"], abs(e) * (1 + abs(p["b"] * x)), abs(e * p["b"]), 1 / abs(p["b"])
    if kind == "poly":
        c = [p["c0"], p["c1"], p["c2"], p["c3"]]
        terms = [A * c[i] * x**i for i in range(4)]
        dterms = [A * i * c[i] * x ** (i - 1) for i in range(1, 4)]
        F = sum((i + 1) * abs(t) for i, t in enumerate(terms))
        D = sum(map(abs, dterms))
        return sum(terms), sum(dterms), F, D, sum(map(abs, terms)) / D
    assert k is not None
    f = A * x**k
    kappa = 1 + abs(k) * (1 + abs(math.log(abs(x)))) if not float(k).is_integer() else 1 + abs(k)
    return f, A * k * x ** (k - 1), abs(f) * kappa, abs(A * k * x ** (k - 1)), abs(x) / max(1.0, abs(k))


@st.composite
def fd_cases(draw, cls):
    dtype = "float32" if cls == "fd: float32" else "float64"
    if cls == "fd: bad argument":
        label, kw = draw(
            st.sampled_from(
                [
                    ("h = 0", dict(h=0.0)),
                    ("h = 1.5", dict(h=1.5)),
                    ("h = NaN", dict(h=math.nan)),
                    ("scale = -1", dict(scale=-1.0)),
                    ("scale = inf", dict(scale=math.inf)),
                    ("f not finite at params (log(x - 2) at x = 1)", dict(_f="log")),
                ]
            )
        )
        return HCase(cls, "a bad h or scale, or f not finite at params", dict(kind="bad", label=label, **kw))
    kind = {"fd: A exp(b x)": "exp", "fd: cubic polynomial": "poly", "fd: A x^k": "power"}.get(cls)
    if kind is None:
        kind = draw(st.sampled_from(["exp", "poly", "power"]))
    x = draw(R.signed(1.0, 10.0)) * 10.0 ** draw(st.integers(-12, 11))
    spec: dict = dict(kind=kind, dtype=dtype, A=draw(R.signed(1.0, 10.0)) * 10.0 ** draw(st.integers(-8, 7)))
    if kind == "exp":
        spec["b"] = draw(st.floats(-30.0, 30.0).filter(lambda v: abs(v) > 1e-3)) / abs(x)  # b x in ±[1e-3, 30]
    elif kind == "poly":
        scale = abs(x)
        for i in range(4):  # terms of comparable size at |x| ~ s, s drawn: roots, extrema and cancellation
            s = 10.0 ** draw(st.integers(-12, 12))
            spec[f"c{i}"] = draw(st.sampled_from([0.0, 1.0])) * draw(R.signed(0.1, 10.0)) / s**i if i != 1 else 1.0
        spec["c1"] = draw(R.signed(0.1, 10.0)) * (scale ** (-1) if draw(st.booleans()) else 1.0)
    else:
        k = draw(st.sampled_from([-3, -2, -1, 2, 3, 5, 0.5, 1.5, -0.5]))
        spec["k"] = k
        if not float(k).is_integer():
            x = abs(x)
    spec["x"] = x
    what = {
        "exp": "A exp(b x), |b x| in [1e-3, 30]",
        "poly": "A (c0 + c1 x + c2 x² + c3 x³), coefficients drawn at random scales",
        "power": "A x^k, k in {−3, −2, −1, −½, ½, 3/2, 2, 3, 5}",
    }[kind] + f" at |x| in [1e-12, 1e12], |A| in [1e-8, 1e8], {dtype}"
    if cls == "fd: float32":
        what = "any of the three kinds above (each case one), in float32: a result or an overflow refused"
    return HCase(cls, what, spec)


def run_fd(case: HCase) -> R.Outcome:
    s = case.spec
    if s["kind"] == "bad":
        p = {"x": jnp.asarray(1.0)}
        f = (lambda q: jnp.log(q["x"] - 2.0)) if s.get("_f") else (lambda q: q["x"] ** 2)
        kw = {k: v for k, v in s.items() if k in ("h", "scale")}
        try:
            g = fd_gradient(f, p, **kw)
        except ValueError as e:
            return _words(str(e), FD_WORDS)
        except Exception as e:  # noqa: BLE001
            return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
        return R.Outcome(R.SILENT_WRONG, f"accepted {s['label']}: {g}")
    dtype = jnp.float32 if s["dtype"] == "float32" else jnp.float64
    keys = [k for k in ("x", "A", "b", "c0", "c1", "c2", "c3") if k in s]
    p = {k: jnp.asarray(s[k], dtype) for k in keys}
    trainable = {k: k == "x" for k in keys}
    f: Callable = {"exp": _fd_exp, "poly": _fd_poly}.get(s["kind"]) or _fd_power(s["k"])
    try:
        g = fd_gradient(f, p, trainable=trainable)["x"]
    except ValueError as e:
        return _words(str(e), FD_WORDS)
    except Exception as e:  # noqa: BLE001
        return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
    return judge_fd(case, float(g))


def fd_exact(case: HCase) -> tuple[float, float]:
    """(∂f/∂x, the allowance) at the case's x, from the values as rounded to its dtype."""
    s = case.spec
    dtype = np.float32 if s["dtype"] == "float32" else np.float64
    p64 = {k: float(dtype(s[k])) for k in ("x", "A", "b", "c0", "c1", "c2", "c3") if k in s}
    _, exact, F, D, L = _fd_terms(s["kind"], p64, s.get("k"))
    return exact, FD_C * float(np.finfo(dtype).eps) ** (2 / 3) * (D + F / L)


def judge_fd(case: HCase, g: float) -> R.Outcome:
    """The outcome of fd_gradient's result g for the case."""
    if not np.isfinite(g):
        return R.Outcome(R.FAILURE, f"non-finite result {g}")
    exact, tol = fd_exact(case)
    scale = tol / (FD_C * float(np.finfo(np.float32 if case.spec["dtype"] == "float32" else np.float64).eps) ** (2 / 3))
    err = abs(g - exact)
    if err <= tol:
        _ratio("fd_gradient", err, tol)
        return R.Outcome(R.RIGHT, f"error {err / scale:.1e} of |f'| + |f|/L", err / scale)
    return R.Outcome(R.SILENT_WRONG, f"{g!r} for {exact!r}: {err / tol:.3g} × the allowance", err / scale)


def _words(msg: str, words: str) -> R.Outcome:
    if re.search(words, msg, re.S):
        return R.Outcome(R.CLEAR_ERROR, msg.splitlines()[0][:120])
    return R.Outcome(R.UNCLEAR_ERROR, msg.splitlines()[0][:160])


# =====================================================================================
# 2. linearize with a given acceleration energy S (the variator, dict parameters)
# =====================================================================================
#
# The variator: T = ½ (J1 φ1'² + J2 φ2'²), U(t) φ1' − φ2' = 0 with U = U0 + a sin(2πt/P), torques
# (M1, M2). With w = φ1', I = J1 + J2 U², the reduced equation is I ẇ = M1 + U M2 − J2 U U' w, so the
# state matrix of (φ1, φ2, w) is exactly [[0, 0, 1], [0, 0, U], [0, 0, −J2 U U'/I]]. S is given as
# ½ (g J1 φ1''² + f J2 φ2''²): f = g = 1 agrees with T. linearize checks S against T (Hessian of S
# in q̈ against the mass matrix, to √eps of its size); a disagreement must be a ValueError naming
# acceleration_energy (eagerly) or NaN (under jax.jit). A success is right when every entry of A is
# within LIN_RTOL max(1, max|A|) of the exact matrix (R.LIN_RTOL = 1e-7: both sides are exact to
# rounding, and an S off by less than √eps = 1.5e-8 of the mass matrix, which the check lets
# through, moves A by at most about that times the condition number of I).

S_CLASSES = ("S agrees with T", "S disagrees by a factor", "S off by a rounding-level factor")


def _s_ratio(t, p):
    return p["U0"] + p["a"] * jnp.sin(2 * jnp.pi * t / p["P"])


def _s_T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def _s_c(q, qd, t, p):
    return jnp.stack([_s_ratio(t, p) * qd[0] - qd[1]])


def _s_Q(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


def _s_S(q, qd, qdd, t, p):
    return 0.5 * (p["g"] * p["J1"] * qdd[0] ** 2 + p["f"] * p["J2"] * qdd[1] ** 2)


VARIATOR_S = nh.Mechanism(_s_T, constraints=_s_c, forces=_s_Q, acceleration_energy=_s_S, names=("phi1", "phi2"))


@st.composite
def s_cases(draw, cls):
    p = dict(
        J1=draw(R.logu(1e-3, 1.0)),
        J2=draw(R.logu(1e-3, 1.0)),
        U0=draw(st.floats(0.5, 2.0)),
        P=draw(R.logu(0.5, 20.0)),
        M1=draw(st.floats(-1.0, 1.0)),
        M2=draw(st.floats(-1.0, 1.0)),
        f=1.0,
        g=1.0,
    )
    p["a"] = draw(st.floats(0.05, 0.45)) * p["U0"]
    which = draw(st.sampled_from(["f", "g"]))
    if cls == "S disagrees by a factor":
        p[which] = 1.0 + draw(R.signed(1e-4, 1.0)) * 10.0 ** draw(st.integers(0, 2))  # |f − 1| in [1e-4, 100]
        p[which] = abs(p[which]) if p[which] != 0 else 2.0
    elif cls == "S off by a rounding-level factor":
        p[which] = 1.0 + draw(R.signed(1.0, 10.0)) * 10.0 ** draw(st.integers(-15, -6))
    what = {
        "S agrees with T": "S = ½ (J1 φ1''² + J2 φ2''²), drawn inertias, ratio law, torques and state",
        "S disagrees by a factor": "one term of S times f, |f − 1| in [1e-4, 100]",
        "S off by a rounding-level factor": "one term of S times f, |f − 1| in [1e-15, 1e-5]",
    }[cls]
    t = draw(st.floats(-2.0, 2.0))
    w = draw(R.signed(0.1, 10.0))
    U = p["U0"] + p["a"] * math.sin(2 * math.pi * t / p["P"])
    return HCase(cls, what, dict(params=p, q=[draw(st.floats(-3, 3)), draw(st.floats(-3, 3))], qd=[w, U * w], t=t))


def s_exact(spec):
    p, t, w = spec["params"], spec["t"], spec["qd"][0]
    om = 2 * math.pi / p["P"]
    U = p["U0"] + p["a"] * math.sin(om * t)
    dU = p["a"] * om * math.cos(om * t)
    inertia = p["J1"] + p["J2"] * U**2
    del w  # (A does not depend on w: the reduced equation is linear in it)
    return np.array([[0.0, 0.0, 1.0], [0.0, 0.0, U], [0.0, 0.0, -p["J2"] * U * dU / inertia]])


def _judge_lin(case, A) -> R.Outcome:
    A = np.asarray(A, float)
    agrees = case.cls == "S agrees with T"
    if np.all(np.isnan(A)):
        if agrees:
            return R.Outcome(R.SILENT_WRONG, "NaN for an S that agrees with T")
        return R.Outcome(R.FAILURE, "NaN (traced: S disagrees with T)")
    ref = s_exact(case.spec)
    err = float(np.max(np.abs(A - ref)) / max(1.0, np.max(np.abs(ref))))
    if err <= R.LIN_RTOL:
        return R.Outcome(R.RIGHT, f"error {err:.1e}", err)
    return R.Outcome(
        R.SILENT_WRONG,
        f"A off the exact matrix by {err:.3g} of its size (S factors "
        f"f={case.spec['params']['f']!r}, g={case.spec['params']['g']!r})",
        err,
    )


def _s_args(spec):
    return {k: float(v) for k, v in spec["params"].items()}, jnp.asarray(spec["q"]), jnp.asarray(spec["qd"])


def run_s_eager(case: HCase) -> R.Outcome:
    p, q, qd = _s_args(case.spec)
    try:
        lin = nh.linearize(VARIATOR_S, p, q, qd, case.spec["t"], speeds=(0,), method="appell")
    except ValueError as e:
        if case.cls == "S agrees with T":
            return R.Outcome(R.UNCLEAR_ERROR, f"refused an S that agrees: {e}"[:160])
        return _words(str(e), r"acceleration_energy")
    except Exception as e:  # noqa: BLE001
        return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
    return _judge_lin(case, lin.A)


@jax.jit
def _s_jit(p, q, qd, t):
    return nh.linearize(VARIATOR_S, p, q, qd, t, speeds=(0,), method="appell").A


def run_s_jit(case: HCase) -> R.Outcome:
    p, q, qd = _s_args(case.spec)
    try:
        A = _s_jit(p, q, qd, case.spec["t"])
    except Exception as e:  # noqa: BLE001
        return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
    return _judge_lin(case, A)


# =====================================================================================
# 3. implicit solvers at report times: Kvaerno5 on jaxnh.models.variator
# =====================================================================================
#
# The bound of tests/test_implicit_reports.py, for every coordinate and velocity at every report:
# one accepted step may leave √n (atol + rtol Y) in one component (diffrax's RMS norm over the n = 4
# components of Lagrange's state; Appell's has 3, so 4 is conservative), Y the largest |q|, |q̇| of
# the run; the flow carries it with a gain of at most G = 1 + T U_max √(I_max/I_min) (a velocity
# error scales by √(I(s)/I(t)), an angle error gains at most (t − s) U_max times that); over the
# N accepted steps, with no cancellation assumed, |error| ≤ N √n (atol + rtol Y) G. atol = rtol/100.

KV_CLASSES = ("Kvaerno5 at drawn report times",)
KV_N = 11
KV_RTOLS = (1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
KV_VARIANTS = (("VeryChord", "lagrange"), ("Newton", "lagrange"), ("Newton", "appell"))
VARIATOR = V.mechanism()


def _variator_params(s, dtype=None):
    p = V.VariatorParams(
        J1=s["J1"], J2=s["J2"], U21=Fourier(1.0, cos=[0.0], sin=[s["a"]], period=s["P"]), M1=s["M1"], M2=s["M2"]
    )
    if dtype is None:
        return p
    return jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x, p)


@st.composite
def variator_spec(draw, P=(0.5, 5.0)):
    return dict(
        J1=draw(R.logu(0.005, 0.1)),
        J2=draw(R.logu(0.005, 0.1)),
        a=draw(st.floats(0.0, 0.45)),
        P=draw(R.logu(*P)),
        M1=draw(st.floats(0.0, 0.5)),
        M2=draw(st.floats(-0.2, 0.0)),
        w0=draw(st.floats(0.5, 5.0)),
    )


@st.composite
def kv_cases(draw, cls=KV_CLASSES[0]):
    s = draw(variator_spec())
    T = draw(st.floats(0.5, 5.0))
    gaps = np.asarray(
        draw(st.lists(st.one_of(st.floats(0.05, 1.0), R.logu(1e-9, 1e-3)), min_size=KV_N - 1, max_size=KV_N - 1))
    )
    t0 = draw(st.floats(0.0, 1.0))
    ts = t0 + T * np.concatenate([[0.0], np.cumsum(gaps) / np.sum(gaps)])
    s.update(ts=ts, rtol=draw(st.sampled_from(KV_RTOLS)))
    return HCase(
        cls,
        f"the variator (U21 = 1 + a sin(2πt/P), drawn inertias and torques), {KV_N} report times over "
        "0.5–5 s with some gaps of 1e-9–1e-3 s, rtol in {1e-6, …, 1e-10}, atol = rtol/100",
        s,
    )


def _kv_solver(root, rtol):
    if root == "VeryChord":
        return diffrax.Kvaerno5()
    # (the root finder's tolerances as arrays: traced, one program for every rtol drawn)
    newton = optx.Newton(rtol=jnp.asarray(rtol), atol=jnp.asarray(rtol / 100))  # pyright: ignore[reportArgumentType]
    return diffrax.Kvaerno5(root_finder=newton)


def _variator_ref(s, ts, dtype=None):
    """The closed form at ts (float64), with the parameters and w0 as the call sees them."""
    p = _variator_params(s, dtype)
    p64 = jax.tree.map(lambda x: x.astype(jnp.float64) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x, p)
    w0 = float(np.asarray(s["w0"], dtype or np.float64))
    t0 = float(ts[0])
    qd0 = np.array([w0, float(np.asarray(p.U21(jnp.asarray(t0, dtype or jnp.float64))).astype(np.float64)) * w0])
    q, qd = V.closed_form(p64, np.asarray(ts, float), w0=w0)
    return p64, np.asarray(q), np.asarray(qd), qd0


def _failure(q, qd, code, msg):
    if not msg or msg == "success":
        return R.Outcome(R.SILENT_WRONG, f"failure code {code} without a message")
    if np.all(np.isfinite(np.asarray(q)[-1])) or np.all(np.isfinite(np.asarray(qd)[-1])):
        return R.Outcome(R.SILENT_WRONG, f"failure status but finite final values: {msg[:80]}")
    return R.Outcome(R.FAILURE, msg[:100])


def run_kv(case: HCase, root: str, method: str) -> R.Outcome:
    s = case.spec
    ts = np.asarray(s["ts"], float)
    rtol = s["rtol"]
    p = _variator_params(s)
    _, q_ref, qd_ref, _ = _variator_ref(s, ts)
    qd0 = jnp.asarray(qd_ref[0])
    try:
        sol = nh.simulate(
            VARIATOR, p, jnp.zeros(2), qd0, jnp.asarray(ts), method=method, solver=_kv_solver(root, rtol),
            rtol=rtol, atol=rtol / 100, throw=False,
        )  # fmt: skip
    except Exception as e:  # noqa: BLE001
        return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
    code = R._status_code(sol)
    if code != 0:
        return _failure(sol.q, sol.qd, code, sol.message)
    tt = np.linspace(ts[0], ts[-1], 2001)
    U = np.asarray(jax.vmap(p.U21)(jnp.asarray(tt)))
    inertia = s["J1"] + s["J2"] * U**2
    G = 1.0 + (ts[-1] - ts[0]) * U.max() * math.sqrt(inertia.max() / inertia.min())
    Y = max(np.abs(q_ref).max(), np.abs(qd_ref).max())
    n = int(sol.stats["num_accepted_steps"])
    bound = n * 2.0 * (rtol / 100 + rtol * Y) * G
    err = max(np.abs(np.asarray(sol.q) - q_ref).max(), np.abs(np.asarray(sol.qd) - qd_ref).max())
    if err <= bound:
        _ratio(f"Kvaerno5 ({root}, {method})", err, bound)
        return R.Outcome(R.RIGHT, f"error {err / Y:.1e} of Y ({err / bound:.1e} of the bound)", err / Y)
    return R.Outcome(R.SILENT_WRONG, f"success, error {err:.3g} > bound {bound:.3g} ({n} steps)", err / Y)


# =====================================================================================
# 4. float32 over a long horizon: the variator, 100–1000 s
# =====================================================================================
#
# The call: float32 parameters, state and report times (51, evenly spaced over T), Lagrange's form,
# the default solver and atol, rtol drawn in {1e-5, 3e-6}. The reference: variator.closed_form in
# float64 with the float32 values of the parameters, w0 and report times (so only the solve's
# arithmetic differs). Judged: w = φ1' at every report, relative to |w|. With I = J1 + J2 U², the
# reduced equation ẇ = f(t, w) = (M1 + U M2 − J2 U U' w)/I carries an error δw at s to t with a
# factor √(I(s)/I(t)) ≤ g = √(I_max/I_min). Three sources, none assumed to cancel:
#
# * the error control: each of the N accepted steps leaves at most √n (atol + rtol |w|) in w
#   (RMS norm over the n = 4 components of Lagrange's state): N √n (atol + rtol W) g, W = max |w|;
# * float32 rounding of each step's update, y + h Σ b_i k_i: taken as F32_ROUND = 8 eps32 |w| per
#   step (a few roundings of the update and the stages' sum): N 8 eps32 W g;
# * float32's time resolution: U and U' are evaluated at a time rounded to float32, off by up to
#   δt(s) = ulp32(s) (the rounding of t + c h, and of c h), so U is off by |U'| δt and U' by
#   |U''| δt, and ẇ by |∂f/∂U| |U'| δt + |∂f/∂U'| |U''| δt; integrated over the run (on the closed
#   form's w at 20 001 points, a Riemann sum of a smooth envelope) and carried by g.
#
# Right: |w − w_ref| ≤ the sum of the three at every report; a success outside it is silent wrong,
# a failure status (NaN values, a message) a failure. It is a bound, not an estimate; the report
# states the largest ratio of a right answer's error to it. (benchmarks/float32_horizon.py: at
# P = 2 s the time term dominates and tightening rtol barely helps.)

F32_CLASSES = ("float32, 100–1000 s",)
F32_N = 51
F32_RTOLS = (1e-5, 3e-6)
F32_ROUND = 8.0
F32_MAX_STEPS = 10**6


@st.composite
def f32_cases(draw, cls=F32_CLASSES[0]):
    s = draw(variator_spec(P=(2.0, 2000.0)))
    s.update(T=draw(st.floats(100.0, 1000.0)), rtol=draw(st.sampled_from(F32_RTOLS)))
    return HCase(
        cls,
        "the variator in float32 (U21 = 1 + a sin(2πt/P), P in 2–2000 s, drawn inertias and torques) over "
        f"T in 100–1000 s, {F32_N} reports, rtol in {{1e-5, 3e-6}}, against the closed form in float64",
        s,
    )


def f32_bound(s, ts32, n_steps, rtol, atol):
    """The bound above at each report (absolute, on w), from the closed form on a fine grid."""
    eps = float(np.finfo(np.float32).eps)
    p32 = _variator_params(s, jnp.float32)
    c = {k: float(np.float32(s[k])) for k in ("J1", "J2", "a", "P", "M1", "M2")}
    tt = np.linspace(float(ts32[0]), float(ts32[-1]), 20001)
    _, _, qd, _ = _variator_ref(s, tt, jnp.float32)
    del p32
    w = qd[:, 0]
    om = 2 * math.pi / c["P"]
    U = 1.0 + c["a"] * np.sin(om * tt)
    dU = c["a"] * om * np.cos(om * tt)
    ddU = -c["a"] * om**2 * np.sin(om * tt)
    inertia = c["J1"] + c["J2"] * U**2
    f = (c["M1"] + U * c["M2"] - c["J2"] * U * dU * w) / inertia
    df_dU = np.abs(c["M2"] - c["J2"] * dU * w - 2 * c["J2"] * U * f) / inertia
    df_ddU = c["J2"] * np.abs(U * w) / inertia
    dt = np.spacing(np.abs(tt).astype(np.float32)).astype(float)
    rate = df_dU * np.abs(dU) * dt + df_ddU * np.abs(ddU) * dt
    time_term = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(tt))])
    g = math.sqrt(inertia.max() / inertia.min())
    W = np.abs(w).max()
    steps = n_steps * (2.0 * (atol + rtol * W) + F32_ROUND * eps * W)
    return g * (steps + np.interp(np.asarray(ts32, float), tt, time_term))


def run_f32(case: HCase) -> R.Outcome:
    s = case.spec
    ts32 = np.linspace(0.0, s["T"], F32_N).astype(np.float32)
    ts64 = ts32.astype(float)
    p32 = _variator_params(s, jnp.float32)
    _, _, qd_ref, qd0 = _variator_ref(s, ts64, jnp.float32)
    try:
        sol = nh.simulate(
            VARIATOR, p32, jnp.zeros(2, jnp.float32), jnp.asarray(qd0, jnp.float32), jnp.asarray(ts32),
            rtol=s["rtol"], max_steps=F32_MAX_STEPS, throw=False,
        )  # fmt: skip
    except Exception as e:  # noqa: BLE001
        return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
    code = R._status_code(sol)
    if code != 0:
        return _failure(sol.q, sol.qd, code, sol.message)
    n = int(sol.stats["num_accepted_steps"])
    atol = _default_atol(jnp.float32)
    bound = f32_bound(s, ts32, n, s["rtol"], atol)
    w, w_ref = np.asarray(sol.qd[:, 0], float), qd_ref[:, 0]
    err = np.abs(w - w_ref)
    rel = float(np.max(err / np.abs(w_ref)))
    if np.all(err <= bound):
        _ratio("float32", float(np.max(err / bound)), 1.0)
        return R.Outcome(R.RIGHT, f"relative error {rel:.1e} ({np.max(err / bound):.1e} of the bound)", rel)
    i = int(np.argmax(err / bound))
    return R.Outcome(
        R.SILENT_WRONG,
        f"success, |δw| {err[i]:.3g} > bound {bound[i]:.3g} at t = {ts64[i]:g} ({n} steps, relative {rel:.2g})",
        rel,
    )


def _default_atol(dtype) -> float:
    """simulate's default atol (1e-10, for every dtype)."""
    import inspect

    return float(inspect.signature(nh.simulate).parameters["atol"].default)


# =====================================================================================
# 5. failure messages: inputs that must fail, and the words that must name the cause
# =====================================================================================
#
# Each class has a known cause; the outcome is judged on the words:
# * failure status — the status is the cause's STATUS item, its message holds the cause's key
#   words and not the stiffness advice ("stiff"), NaN values, stopped_at at the cause's time (to
#   1e-6 s), and throw=True raises a SimulationError with the same status;
# * clear error — for an argument refused up front: a ValueError naming it, without "stiff";
# * unclear error — any other status or words (a failure that blames something else);
# * silent wrong — a success (or, for the root finder, a success off the exact reduced motion).

FAIL_CLASSES = (
    "dtmax not positive or not finite",
    "dtmax that exhausts max_steps",
    "force turns NaN mid-run",
    "kinetic energy turns NaN mid-run",
    "constraints lose rank mid-run (appell)",
    "root finder that cannot converge (stiff damper)",
)


def _f_T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def _f_U(t, p):
    return 1.0 + p["a"] * jnp.sin(jnp.pi * t)


def _f_c(q, qd, t, p):
    return jnp.stack([_f_U(t, p) * qd[0] - qd[1]])


def _f_Q(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


def _f_Q_nan(q, qd, t, p):
    return jnp.where(t > p["tnan"], jnp.nan, 1.0) * jnp.stack([p["M1"], p["M2"]])


def _f_T_nan(q, qd, t, p):
    return _f_T(q, qd, t, p) * (1.0 + 0.0 * jnp.sqrt(p["tnan"] - t))


def _f_Q_damped(q, qd, t, p):
    return jnp.stack([p["M1"] - p["C"] * qd[0], p["M2"]])


def _f_T3(q, qd, t, p):
    return 0.5 * (qd[0] ** 2 + 2.0 * qd[1] ** 2 + 3.0 * qd[2] ** 2)


def _f_rows(q, qd, t, p):  # independent except at t = t*, where the second row equals the first
    return jnp.stack([qd[0] - qd[2], qd[0] + (t - p["tstar"]) * qd[1] - qd[2]])


def _f_Q3(q, qd, t, p):
    return jnp.stack([1.0, 0.5, 0.0]) + 0.0 * p["tstar"]


F_PLAIN = nh.Mechanism(_f_T, constraints=_f_c, forces=_f_Q)
F_NAN_FORCE = nh.Mechanism(_f_T, constraints=_f_c, forces=_f_Q_nan)
F_NAN_T = nh.Mechanism(_f_T_nan, constraints=_f_c, forces=_f_Q)
F_DAMPED = nh.Mechanism(_f_T, constraints=_f_c, forces=_f_Q_damped)
F_RANK = nh.Mechanism(_f_T3, constraints=_f_rows, forces=_f_Q3)
FAIL_MAX_STEPS = 2000
FAIL_ROOT_MAX_STEPS = 4000


@st.composite
def fail_cases(draw, cls):
    T = draw(st.floats(0.5, 2.0)) if not cls.startswith("root") else 2.0  # (2 s: VeryChord needs > max_steps)
    p = dict(J1=draw(R.logu(0.005, 0.1)), J2=draw(R.logu(0.005, 0.1)), a=draw(st.floats(0.1, 0.45)))
    p.update(M1=draw(st.floats(0.05, 0.5)), M2=draw(st.floats(-0.2, 0.0)))
    s: dict = dict(T=T, w0=draw(st.floats(0.5, 5.0)))
    if cls == "dtmax not positive or not finite":
        s["dtmax"] = draw(
            st.sampled_from([0.0, -0.0, math.nan, math.inf, -math.inf]) | R.signed(1e-9, 1.0).map(lambda v: -abs(v))
        )
        what = "dtmax = 0, −0, NaN, ±inf or negative"
    elif cls == "dtmax that exhausts max_steps":
        s["dtmax"] = T / (FAIL_MAX_STEPS * draw(st.floats(2.5, 20.0)))
        what = f"dtmax = T / (k max_steps), k in 2.5–20, max_steps = {FAIL_MAX_STEPS}"
    elif cls in ("force turns NaN mid-run", "kinetic energy turns NaN mid-run"):
        p["tnan"] = draw(st.floats(0.1, 0.9)) * T
        what = "NaN from t* on, t* in 0.1–0.9 of the run" if "force" in cls else "T × (1 + 0 √(t* − t))"
    elif cls == "constraints lose rank mid-run (appell)":
        p = dict(tstar=draw(st.floats(0.1, 0.9)) * T)
        what = "rows [1, 0, −1] and [1, t − t*, −1] (tests/test_statuses.py), t* in 0.1–0.9 of the run"
    else:
        p["C"] = p["J1"] * draw(R.logu(1e6, 1e7))
        what = (
            f"viscous torque −C φ1', C/J1 in 1e6–1e7 /s, Kvaerno5 with diffrax's root finder (VeryChord), "
            f"rtol 1e-8, max_steps {FAIL_ROOT_MAX_STEPS}: root_finder_failed, or a run that converges and is right"
        )
    s["params"] = p
    return HCase(cls, what, s)


_FAIL_EXPECT = {
    # class: (status name, words that must all appear, whether stopped_at must be the cause's time)
    "dtmax that exhausts max_steps": ("max_steps_step_bound", ("dtmax", "step_ts"), None),
    "force turns NaN mid-run": ("forces_became_non_finite", ("`forces`", "NaN"), "tnan"),
    "kinetic energy turns NaN mid-run": ("kinetic_energy_became_non_finite", ("`kinetic`",), "tnan"),
    "constraints lose rank mid-run (appell)": ("constraints_lost_rank", ("lost rank", "method='lagrange'"), "tstar"),
    "root finder that cannot converge (stiff damper)": (
        "root_finder_failed", ("root finder did not converge", "optimistix.Newton(rtol=rtol, atol=atol)"), None),
}  # fmt: skip


def _fail_call(case: HCase) -> tuple[Any, dict, Any, Any, Any, dict[str, Any]]:
    s, cls = case.spec, case.cls
    p = {k: float(v) for k, v in s["params"].items()}
    ts = jnp.linspace(0.0, s["T"], 11)
    if cls == "constraints lose rank mid-run (appell)":
        return F_RANK, p, jnp.zeros(3), jnp.array([1.0, 0.0, 1.0]), ts, dict(method="appell", max_steps=FAIL_MAX_STEPS)
    qd0 = jnp.array([s["w0"], s["w0"]])  # U(0) = 1
    if cls.startswith("dtmax"):
        # (an array: a traced bound, one program for every case; a Python float would be compiled in)
        dtmax = s["dtmax"] if cls.startswith("dtmax not") else jnp.asarray(s["dtmax"])
        return F_PLAIN, p, jnp.zeros(2), qd0, ts, dict(dtmax=dtmax, max_steps=FAIL_MAX_STEPS)
    if cls == "force turns NaN mid-run":
        return F_NAN_FORCE, p, jnp.zeros(2), qd0, ts, dict(max_steps=FAIL_MAX_STEPS)
    if cls == "kinetic energy turns NaN mid-run":
        return F_NAN_T, p, jnp.zeros(2), qd0, ts, dict(max_steps=FAIL_MAX_STEPS)
    return F_DAMPED, p, jnp.zeros(2), qd0, ts, dict(solver=diffrax.Kvaerno5(), max_steps=FAIL_ROOT_MAX_STEPS)


def damped_reference(case: HCase, ts):
    """The root-finder class's exact motion: the reduced equation (J1 + J2 U²) ẇ + J2 U U' w =
    M1 + U M2 − C w, by SciPy's Radau at rtol 1e-11 (a stiff linear ODE), and φ by quadrature."""
    p = case.spec["params"]

    def rhs(t, y):
        U = 1.0 + p["a"] * math.sin(math.pi * t)
        dU = p["a"] * math.pi * math.cos(math.pi * t)
        w = y[2]
        wd = (p["M1"] + U * p["M2"] - p["C"] * w - p["J2"] * U * dU * w) / (p["J1"] + p["J2"] * U**2)
        return [w, U * w, wd]

    jac = None
    r = solve_ivp(rhs, (ts[0], ts[-1]), [0.0, 0.0, case.spec["w0"]], method="Radau", t_eval=ts, rtol=1e-11,
                  atol=1e-14, jac=jac)  # fmt: skip
    U = 1.0 + p["a"] * np.sin(np.pi * ts)
    return r.y[:2].T, np.stack([r.y[2], U * r.y[2]], axis=1)


def run_fail(case: HCase) -> R.Outcome:
    mech, p, q0, qd0, ts, kw = _fail_call(case)
    if case.cls == "dtmax not positive or not finite":
        try:
            nh.simulate(mech, p, q0, qd0, ts, **kw)
        except ValueError as e:
            msg = str(e)
            if re.search(r"\bdtmax\b", msg) and "stiff" not in msg:
                return R.Outcome(R.CLEAR_ERROR, msg.splitlines()[0][:120])
            return R.Outcome(R.UNCLEAR_ERROR, msg.splitlines()[0][:160])
        except Exception as e:  # noqa: BLE001
            return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
        return R.Outcome(R.SILENT_WRONG, f"dtmax={case.spec['dtmax']!r} accepted")
    try:
        sol = nh.simulate(mech, p, q0, qd0, ts, throw=False, **kw)
    except Exception as e:  # noqa: BLE001
        return R.Outcome(R.UNCLEAR_ERROR, f"{type(e).__name__}: {e}"[:160])
    code = R._status_code(sol)
    name, words, when = _FAIL_EXPECT[case.cls]
    if code == 0:
        if case.cls.startswith("root finder"):  # it did converge: the answer must be right
            q_ref, qd_ref = damped_reference(case, np.asarray(ts))
            c = R.Case("root", ts=np.asarray(ts))
            err = R.motion_error(np.asarray(sol.q), np.asarray(sol.qd), (q_ref, qd_ref), c.ts)
            if err <= 1.0:
                return R.Outcome(R.RIGHT, f"converged; error {err:.2g} × the allowed", err * R.MOTION_RTOL)
            return R.Outcome(R.SILENT_WRONG, f"success, error {err:.3g} × the allowed (1000 × rtol)")
        return R.Outcome(R.SILENT_WRONG, "success on an input that must fail")
    msg = sol.message
    right_status = bool(sol.status == getattr(nh.STATUS, name))
    missing = [w for w in words if w not in msg]
    # the stiffness advice must not be given; the root finder's message says stiffness is not the cause
    blames = "not the cause" not in msg if case.cls.startswith("root finder") else "stiff" in msg
    if not right_status or missing or blames:
        return R.Outcome(R.UNCLEAR_ERROR, f"status {code} (expected {name}), missing {missing}: {msg[:100]}")
    if when is not None:
        stopped = float(sol.stats["stopped_at"])
        if abs(stopped - p[when]) > 1e-6:
            return R.Outcome(R.UNCLEAR_ERROR, f"{name} at t = {stopped:.9g}, the cause is at {p[when]:.9g}")
    out = _failure(sol.q, sol.qd, code, msg)
    if out.kind != R.FAILURE:
        return out
    return R.throw_agrees(lambda: nh.simulate(mech, p, q0, qd0, ts, throw=True, **kw), code) or R.Outcome(
        R.FAILURE, f"{name}: {msg[:80]}"
    )


# =====================================================================================
# All of them
# =====================================================================================


def run_all(n: dict):
    """(interface, class, case, outcome) for every hunt family; n: cases per class (keys fd, s, kv,
    f32, fail; kv is per variant, the variants sharing the cases)."""
    for cls in FD_CLASSES:
        for c in R.draw(fd_cases(cls), n["fd"] if cls != "fd: bad argument" else max(1, n["fd"] // 4)):
            yield "fd_gradient", cls, c, run_fd(c)
    for cls in S_CLASSES:
        for c in R.draw(s_cases(cls), n["s"]):
            yield "linearize with S (appell), eager", cls, c, run_s_eager(c)
            yield "linearize with S (appell), jax.jit", cls, c, run_s_jit(c)
    for cls in FAIL_CLASSES:
        for c in R.draw(fail_cases(cls), n["fail"]):
            yield "failure messages, simulate eager", cls, c, run_fail(c)
    kv = R.draw(kv_cases(), n["kv"]) if n["kv"] else []
    for root, method in KV_VARIANTS:
        for c in kv:
            yield f"Kvaerno5 ({root}, {method})", c.cls, c, run_kv(c, root, method)
    for c in R.draw(f32_cases(), n["f32"]) if n["f32"] else []:
        yield "float32, simulate (default solver)", c.cls, c, run_f32(c)


def text() -> list[str]:
    """The families' paragraph for RELIABILITY.md (with the measured ratios to the bounds)."""
    ratios = ", ".join(f"{k} {v:.1e}" for k, v in sorted(RATIOS.items()))
    return [
        "The hunt families (`benchmarks/reliability_hunt.py`, issue 46), each against an exact reference:",
        "",
        "* **design helpers** — `jaxnh.design.fd_gradient` on A exp(b x), cubic polynomials and A x^k at "
        "|x| in 1e-12–1e12 and |A| in 1e-8–1e8, in float64 and float32: right within "
        f"{FD_C:g} eps^(2/3) (D + F / L), D the sum of the magnitudes of the terms of f', F "
        "that of f's terms times their condition numbers (f's rounding noise, in eps: 1 + |b x| for "
        "exp(b x)) and L the length f varies on (1/|b|, |x|/max(1, |k|)) (the accuracy fd_gradient "
        "documents, with tests/test_fd_gradient.py's "
        "constant); a ValueError naming the entry, f(params), h or scale is a clear error, NaN a failure;",
        "* **linearize with S** — the variator with dict parameters and S = ½ (g J1 φ1''² + f J2 φ2''²): "
        "f = g = 1 (agrees), one factor off by 1e-4–100 (must be refused: eagerly a ValueError naming "
        "acceleration_energy, under jax.jit NaN), or by 1e-15–1e-5 (below the check's √eps it may pass: "
        f"then A must still be right); right within LIN_RTOL = {R.LIN_RTOL:g} of the exact state matrix "
        "[[0, 0, 1], [0, 0, U], [0, 0, −J2 U U'/I]];",
        "* **implicit solvers at report times** — `diffrax.Kvaerno5()` (VeryChord) and with "
        "`optimistix.Newton(rtol, atol)`, Lagrange's and Appell's forms, on `jaxnh.models.variator` at "
        "rtol 1e-6–1e-10 (atol = rtol/100) and 11 drawn report times (some 1e-9–1e-3 s apart): right when "
        "every coordinate and velocity is within N √4 (atol + rtol Y) (1 + T U_max √(I_max/I_min)) of "
        "`closed_form` (tests/test_implicit_reports.py's bound: N accepted steps, each leaving at most "
        "√n × the tolerance in one component, carried by the flow's largest gain, no cancellation);",
        "* **float32, long horizon** — the variator in float32 over 100–1000 s (ratio period 2–2000 s), "
        "rtol 1e-5 or 3e-6, against `closed_form` in float64 with the float32 values of the inputs: right "
        "when φ1' is within g [N (√4 (atol + rtol W) + 8 eps32 W) + ∫ (|∂f/∂U| |U'| + |∂f/∂U'| |U''|) "
        "ulp32(s) ds] at every report (g = √(I_max/I_min) the flow's gain on a velocity error, N accepted "
        "steps, W = max |φ1'|, f = (M1 + U M2 − J2 U U' w)/I; the integral is the error of evaluating "
        "the ratio at a time rounded to float32, the cause benchmarks/float32_horizon.py isolates); a "
        "success outside it is silent wrong;",
        "* **failure messages** — dtmax ≤ 0 or not finite (a ValueError naming dtmax); a dtmax that forces "
        "more steps than max_steps (`max_steps_step_bound`, naming dtmax and step_ts); `forces` or "
        "`kinetic` turning NaN at a drawn t* (`forces_became_non_finite` / "
        "`kinetic_energy_became_non_finite`, stopped at t*); constraint rows that lose rank at t* with "
        "method='appell' (`constraints_lost_rank`, naming method='lagrange', stopped at t*); Kvaerno5 with "
        "diffrax's root finder on a damper with C/J1 in 5e5–5e6 /s (`root_finder_failed`, naming "
        "optimistix.Newton; a run that converges is judged against the reduced equation by SciPy's "
        "Radau): a failure status counts only with the cause's status, its key words, no stiffness "
        "advice, the cause's time and throw=True raising the same status; any other status or words is "
        "an unclear error.",
        "",
        f"Largest error of a right answer over its bound (1 is the bound): {ratios or '–'}.",
    ]
