"""The "declared nonlinear constraint" family of the reliability checks (issue 15).

The shafts family of `benchmarks/reliability_cases.py` with its constraint

    c = R(t) phi1' + a1 phi2' + a2 phi3' + b sin(w t) + nl phi1'²,   R(t) = U + dU tanh(k (t − tsw)),

declared nonlinear in the velocities (`Mechanism(..., nonlinear_constraints=True)`), every
number a traced parameter. Its Jacobian is `A = ∂c/∂q̇ = [R + 2 nl phi1', a1, a2]`. c is a
quadratic in phi1' with two roots; the one jaxnh's Newton iterations reach from zero is the
root "near" the linear constraint's, the branch where `R + 2 nl phi1'` has the sign of R
(`y = R + 2 nl phi1'` is called the branch variable below; its fold y = 0 is where the two
roots meet and, when a1 = a2 = 0, where ∂c/∂q̇ is singular).

The reference shares no code with jaxnh: the KKT system `M q̈ = Q + Aᵀλ, A q̈ = −∂c/∂t`
(c does not depend on q, so the differentiated constraint has no `(∂c/∂q) q̇` term) written
out by hand in NumPy (`reliability_cases.ShaftsModel`, whose `jac` carries the 2 nl phi1'
term) and integrated by SciPy's DOP853 at rtol 1e-12; consistent initial velocities by the
quadratic formula in NumPy (its cancellation-free form, then one Newton step), never by
jaxnh; `consistent_velocities` against the exact kinetic-energy projection (Newton's method
on its KKT conditions in NumPy, with the second-order condition checked); linearisations
against complex-step derivatives of the reference's reduced field about the given velocities
(`reliability_cases.ref_linearization(..., at_qd=True)`).

The reference is checked against exact solutions in tests/test_fuzz.py: with a1 ≠ 0, a
constant ratio, only M1 acting and no damping, the reduced equation is separable,
`(J1 + J2 y²/a1²) ẋ = M1` (x = phi1'), whose implicit solution and the polynomial
quadratures of the positions are exact; with a1 = a2 = 0, phi1'(t) is the root of the
quadratic at every t. Energy is NOT such a check here: Chetaev's constraint force Aᵀλ does
the work `λ A q̇ = λ (c + nl phi1'²) = λ nl phi1'²` on the motion (A q̇ = c only for a
constraint homogeneous of degree one in q̇), so the energy of this mechanism changes even
with no torque, damping or rheonomic term.

The outcomes and tolerances are those of the shafts family (reliability_cases: MOTION_RTOL
× each component's scale + MOTION_ATOL, scaled with the tolerances asked for; GRAD_RTOL;
LIN_RTOL).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

import jaxnh as nh
from benchmarks import reliability_cases as R
from jaxnh._base.status import describe


SHAFTS_NL = nh.Mechanism(
    R.shafts_kinetic,
    constraints=R.shafts_constraint,
    forces=R.shafts_forces,
    names=("phi1", "phi2", "phi3"),
    nonlinear_constraints=True,
)
METHODS = ("lagrange", "appell")
NL_THETA = ("J2", "nl")
"""The parameters differentiated in the gradient checks: an inertia and the constraint's
nonlinear coefficient (which moves the consistent start with it: phi2'(t0), or phi1'(t0) when
it is solved from the quadratic)."""
FAMILY = "shafts-nl"
MODEL = R.ShaftsModel

SQRT_EPS = math.sqrt(np.finfo(np.float64).eps)
CV_RTOL = SQRT_EPS
"""consistent_velocities is right when it meets c = 0 to its documented acceptance, |c| ≤ √eps
× (|A| |q̇| + |c(q, 0, t)|) (recomputed here in NumPy), and every velocity is within CV_RTOL ×
(|q̇ given| + |q̇ reference|) of the exact projection: a residual of √eps of the constraint's
scale moves the velocities by about √eps of theirs along the constraint's normal (the rows here
are well conditioned), and nothing smaller is promised. The exact projection converges to
1e-14 of the scale (`ref_projection`); a point of c = 0 that is not the nearest is off by
O(nl |δ|²) for a move δ off the constraint."""


# =====================================================================================
# The reference
# =====================================================================================


def nl_qd0(p, w0, v3, t0, solve, xp=jnp):
    """Velocities meeting c = 0 at t0. solve = 0: phi1' = w0, phi3' = v3 and phi2' from the
    constraint (linear in it, a1 ≠ 0). solve = 1 (the classes with a1 = 0): phi2' = w0,
    phi3' = v3 and phi1' the near root of nl x² + R x + r = 0, r = a2 v3 + b sin(w t0), in the
    form without cancellation, x = −2 r / (R + sign(R) √D), D = R² − 4 nl r (D < 0, no root,
    is clipped to 0). solve = 2: phi1' = −R / (2 nl), the double root, exactly (for D = 0 the
    formula would carry the rounding of D, ±eps R², as √(eps) R ≈ 1e-8 R into y = R + 2 nl phi1':
    a start just off the fold, which has a motion). Written for NumPy (the reference) and
    jax.numpy (the differentiated loss of the batched program, which needs qd0 as a function of
    nl); jaxnh computes none of it."""
    Rt = R.ratio(t0, p, xp)
    a1, a2, nl = p["a1"], p["a2"], p["nl"]
    rheo = p["b"] * xp.sin(p["w"] * t0)
    phi2_lin = -(Rt * w0 + a2 * v3 + rheo + nl * w0**2) / xp.where(a1 != 0, a1, 1.0)
    r = a2 * v3 + rheo
    D = xp.where(solve > 0, xp.maximum(Rt * Rt - 4 * nl * r, 0.0), 1.0)
    den = Rt + xp.where(Rt >= 0, 1.0, -1.0) * xp.sqrt(D)
    x = xp.where(solve > 1.5, -Rt / (2 * nl), -2 * r / xp.where(solve > 0, den, 1.0))
    return xp.stack([xp.where(solve > 0, x, w0), xp.where(solve > 0, w0, phi2_lin), v3 + 0.0 * a1])


def ref_qd0(p, w0, v3, t0, solve):
    """nl_qd0 in NumPy, polished by one Newton step on the solved velocity (not at the double root)."""
    p = {k: np.float64(v) for k, v in p.items()}
    qd = np.asarray(nl_qd0(p, np.float64(w0), np.float64(v3), np.float64(t0), solve, np), float)
    if np.all(np.isfinite(qd)) and solve < 1.5:
        j = 0 if solve else 1
        A, c = MODEL.jac(None, qd, t0, p)[0], MODEL.value(None, qd, t0, p)[0]
        if A[j] != 0:
            qd[j] -= c / A[j]
    return qd


def nl_motion(p, q0, qd0, ts, rtol: float = 1e-12):
    """(q, q̇ at ts, branch margin) by SciPy's DOP853 at rtol from the KKT equations; None when
    the integration fails. The margin is min over the steps of y / R (y = R + 2 nl phi1'): > 0
    while the motion stays on the near root, < 0 on the far one."""
    s = MODEL.s
    ts = np.asarray(ts, float)
    y0 = np.concatenate([np.asarray(q0, float), np.asarray(qd0, float)])

    def f(t, y):
        return np.concatenate([y[s:], R.ref_accelerations(MODEL, y[:s], y[s:], t, p, solve=np.linalg.solve)])

    try:
        with np.errstate(all="ignore"):
            scale = np.max(np.abs(y0)) + np.max(np.abs(f(ts[0], y0))) * (ts[-1] - ts[0]) + 1e-300
            sol = solve_ivp(
                f, (ts[0], ts[-1]), y0, method="DOP853", rtol=rtol, atol=rtol * 1e-3 * scale, dense_output=True
            )
    except (np.linalg.LinAlgError, ValueError):
        return None
    if sol.status != 0 or not np.all(np.isfinite(sol.y)):
        return None
    y = sol.sol(ts)
    y[:, 0], y[:, -1] = sol.y[:, 0], sol.y[:, -1]
    Rs = R.ratio(sol.t, p, np)
    margin = float(np.min((Rs + 2 * p["nl"] * sol.y[s]) / Rs))
    return y[:s].T, y[s:].T, margin


def ref_projection(p, q, qd, t, iterations: int = 40):
    """The exact kinetic-energy projection of qd on c = 0, argmin ½ (x − qd)ᵀ M (x − qd) subject to
    c(x) = 0: Newton's method on its KKT conditions `M (x − qd) − A(x)ᵀ μ = 0, c(x) = 0` from
    (qd, 0), with their exact Jacobian `[[M − μ ∂²c/∂x², −Aᵀ], [A, 0]]` (∂²c/∂x² = 2 nl e1 e1ᵀ),
    then the second-order condition (M − μ ∂²c/∂x² positive definite on the null space of A: a
    minimum, not a saddle). None when it does not converge to 1e-14 of the scale or is no minimum."""
    M = MODEL.mass(q, t, p)
    H = np.zeros((3, 3))
    H[0, 0] = 2 * p["nl"]
    x, mu = np.array(qd, float), 0.0
    scale = np.max(np.abs(M)) * (np.max(np.abs(qd)) + 1e-300)
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            A = MODEL.jac(q, x, t, p)
            F = np.concatenate([M @ (x - qd) - A[0] * mu, MODEL.value(q, x, t, p)])
            J = np.block([[M - mu * H, -A.T], [A, np.zeros((1, 1))]])
            try:
                z = np.linalg.solve(J, -F)
            except np.linalg.LinAlgError:
                return None
            x, mu = x + z[:3], mu + z[3]
        A = MODEL.jac(q, x, t, p)
        F = np.concatenate([M @ (x - qd) - A[0] * mu, MODEL.value(q, x, t, p)])
        if not np.all(np.isfinite(F)) or np.max(np.abs(F)) > 1e-14 * scale * (1 + np.max(np.abs(A))):
            return None
        N = np.linalg.svd(A)[2][1:].T  # the null space of A (3 × 2)
        if np.min(np.linalg.eigvalsh(N.T @ (M - mu * H) @ N)) <= 0:
            return None
    return x


# =====================================================================================
# Cases
# =====================================================================================


@dataclasses.dataclass
class NLCase:
    """One call of the family: parameters, the start (w0, v3, and `solve`: whether phi1' is
    solved from the quadratic), an offset `delta` added to the consistent qd0, report times."""

    cls: str
    params: dict
    w0: float
    v3: float
    q0: Any
    ts: Any
    solve: float = 0.0
    delta: Any = dataclasses.field(default_factory=lambda: np.zeros(3))
    valid: bool = True
    what: str = ""
    names: str = r"$^"
    known: str = ""
    kw: dict = dataclasses.field(default_factory=dict)
    fd_h: float = 1e-4  # relative step of the reference's central differences
    qd: Any = None  # consistent_velocities cases: the velocity to project
    family: str = FAMILY

    @property
    def qd0(self):
        return ref_qd0(self.params, self.w0, self.v3, self.ts[0], self.solve) + self.delta

    @functools.cached_property
    def _ref(self):
        if not self.valid:
            return None
        return nl_motion(self.params, self.q0, self.qd0, self.ts)

    def reference(self):
        """(q, q̇) at the report times, or None."""
        return None if self._ref is None else self._ref[:2]


def _grid_sin(p, ts, n=4001):
    t = np.linspace(ts[0], ts[-1], n)
    return t, np.sin(p["w"] * t)


def _fold_time(draw, p, ts):
    """(σ, index into the grid) of a time in the middle of the run where σ sin(w t) reaches a new
    running maximum above 0.05 (so that D = R² (1 − u sin(w t)) with u = σ / sin(w t_f) first
    reaches 0 there, crossing it), or None; w is doubled until one exists."""
    for _ in range(5):
        t, S = _grid_sin(p, ts)
        cands = []
        for sigma in (1.0, -1.0):
            g = sigma * S
            runmax = np.maximum.accumulate(g)
            new = np.nonzero((g[1:] > runmax[:-1]) & (g[1:] > 0.05))[0] + 1
            new = new[(new > 0.2 * len(t)) & (new < 0.8 * len(t))]
            cands += [(sigma, int(j)) for j in new]
        if cands:
            return cands[int(draw(st.floats(0.0, 0.999)) * len(cands))], t, S
        p["w"] *= 2.0
    return None, None, None


NL_CLASSES = (
    "nonlinear: valid",
    "nonlinear: inconsistent qd0",
    "nonlinear: near-singular ∂c/∂qd",
    "nonlinear: fold inside the run",
    "nonlinear: singular ∂c/∂qd at the start",
    "nonlinear: start on the far root",
)
"""Value classes (every interface runs them). 'valid': a1 ≠ 0, so ∂c/∂q̇ is regular everywhere,
and the motion stays on the near root with margin y/R ≥ 0.25 (nl shrunk until it does).
The last four: a1 = a2 = 0 (phi1' is fixed by c alone: A = [y, 0, 0], singular at the fold
y = 0), a constant ratio, and b sin(w t) placed so that the discriminant D(t) = R² − 4 nl b
sin(w t) comes within δ R² of 0 (valid: right, or a failure status), crosses 0 inside the run
(no motion exists past it: a failure status), or is 0 at t0 (phi1' at the double root, A = 0);
'start on the far root': a1 small, phi1'(t0) on the other root (y of the opposite sign to R),
a valid start of a motion that Lagrange's equations integrate (Appell's see the issue
'nonlinear-far-root')."""

FAR_ROOT = "nonlinear-far-root"
NOT_NEAREST = "nonlinear-projection-not-nearest"


def _valid_nl(draw, p, w0, v3, q0, ts):
    """nl of either sign, up to 0.35 |R| / |w0| (nl w0² up to 0.35 of R w0), halved until the
    reference motion keeps y / R ≥ 0.25 (the near root, well away from the fold)."""
    nl = draw(R.signed(0.05, 0.35)) * abs(p["U"]) / (abs(w0) + 0.3)
    for _ in range(12):
        p["nl"] = nl
        ref = nl_motion(p, q0, ref_qd0(p, w0, v3, ts[0], 0.0), ts)
        if ref is not None and ref[2] >= 0.25:
            return
        nl *= 0.5
    p["nl"] = nl


@st.composite
def nl_cases(draw, cls=None):
    """One case of a class of the declared-nonlinear family (drawn when cls is None)."""
    cls = draw(st.sampled_from(NL_CLASSES)) if cls is None else cls
    p, w0, v3, q0, ts = draw(R.physical())
    delta, solve, valid, what, known, fd_h = np.zeros(3), 0.0, True, "", "", 1e-4
    if cls in ("nonlinear: valid", "nonlinear: inconsistent qd0"):
        _valid_nl(draw, p, w0, v3, q0, ts)
        what = (
            "the valid shafts class with c + nl phi1'², nl up to 0.35 |R|/|w0|, the motion on the near "
            "root with y/R ≥ 0.25 (∂c/∂qd regular: a1 = −0.5..−2)"
        )
        if cls == "nonlinear: inconsistent qd0":
            qd = ref_qd0(p, w0, v3, ts[0], 0.0)
            eps = draw(R.logu(1e-6, 0.5))
            delta = np.array([0.0, eps * (abs(qd[1]) + abs(w0 * p["U"])), 0.0])
            valid = False
            what = "the valid class with phi2'(t0) off c = 0 by a fraction 1e-6..0.5 of its scale"
    elif cls == "nonlinear: start on the far root":
        U = p["U"]
        p.update(dU=0.0, nl=draw(R.signed(0.2, 2.0)) * abs(U))
        f = draw(st.floats(0.5, 2.0))
        w0 = -U * (1 + f) / (2 * p["nl"])  # y0 = R + 2 nl w0 = −f R: the far root
        ratio = draw(st.floats(0.1, 0.5))  # |a1|/√J2 below |y0|/√J1: Appell's choice makes phi1' dependent
        p["a1"] = -ratio * f * abs(U) * math.sqrt(p["J2"] / p["J1"])
        what = "a1 small (|a1|/√J2 = 0.1..0.5 × |y0|/√J1), phi1'(t0) on the far root (y0 = −(0.5..2) R): a valid start"
    else:
        p.update(a1=0.0, a2=0.0, dU=0.0, nl=draw(R.signed(0.1, 3.0)) * abs(p["U"]))
        solve = 1.0
        Rc = p["U"]
        if cls == "nonlinear: singular ∂c/∂qd at the start":
            if abs(math.sin(p["w"] * ts[0])) < 0.1:  # sin(w t0) away from 0 (b finite)
                ts, p["w"] = ts - ts[0] + 1.0, 1.2
            p["b"] = Rc * Rc / (4 * p["nl"] * math.sin(p["w"] * ts[0]))
            solve = 2.0  # phi1'(t0) = −R / (2 nl), y0 = 0 to rounding
            valid = False
            what = "a1 = a2 = 0, D(t0) = R² − 4 nl b sin(w t0) = 0: phi1'(t0) at the double root, ∂c/∂qd = 0"
        elif cls == "nonlinear: near-singular ∂c/∂qd":
            dlt = draw(R.logu(1e-3, 0.1))
            t, S = _grid_sin(p, ts)
            sigma = 1.0 if np.max(S) >= -np.min(S) else -1.0
            smax = float(np.max(sigma * S))
            if smax < 0.05:
                p["w"] = 1.2
                t, S = _grid_sin(p, ts)
                sigma = 1.0 if np.max(S) >= -np.min(S) else -1.0
                smax = float(np.max(sigma * S))
            p["b"] = sigma * (1 - dlt) / smax * Rc * Rc / (4 * p["nl"])
            fd_h = min(1e-4, 1e-3 * dlt)
            what = (
                "a1 = a2 = 0, b sin(w t) brings D = R² − 4 nl b sin(w t) to δ R², δ = 1e-3..0.1, inside the run "
                "(|∂c/∂qd| down to √δ |R|)"
            )
        else:  # fold inside the run
            pick, t, S = _fold_time(draw, p, ts)
            if pick is None:
                raise AssertionError("no fold time found")  # (does not happen: w is doubled up to 16×)
            sigma, j = pick
            p["b"] = Rc * Rc / (4 * p["nl"] * S[j])  # D = R² (1 − sin(w t) / sin(w t_f))
            valid = False
            what = "a1 = a2 = 0, D = R² − 4 nl b sin(w t) crosses 0 at 20..80 % of the run: no motion exists past it"
    return NLCase(
        cls, p, float(w0), float(v3), np.asarray(q0, float), np.asarray(ts, float), solve, delta, valid=valid,
        what=what, known=known, fd_h=fd_h,
    )  # fmt: skip


CV_CLASSES = ("cv: on the constraint", "cv: off the constraint", "cv: no real solution")


@st.composite
def cv_cases(draw, cls):
    """Velocities to project: consistent ones (the answer is qd itself), ones moved off c = 0 by
    1e-8..0.3 of their scale in a random direction (the exact projection: known issue
    'nonlinear-projection-not-nearest'), or ones for which c = 0 has no solution (a1 = a2 = 0 and
    D < 0: expected a clear error eagerly, NaN under jit)."""
    c = draw(nl_cases("nonlinear: valid"))
    p = dict(c.params)
    qd = c.qd0
    valid, known, names = True, "", r"constraint|nonlinear|iterations"
    if cls == "cv: on the constraint":
        what = "a consistent qd of the valid class (the projection is qd itself)"
    elif cls == "cv: off the constraint":
        d = np.asarray([draw(st.floats(-1.0, 1.0)) for _ in range(3)]) + np.array([0.3, 0.0, 0.0])
        qd = qd + d / np.max(np.abs(d)) * draw(R.logu(1e-8, 0.3)) * np.max(np.abs(qd))
        what = "a consistent qd moved by 1e-8..0.3 of its size in a random direction"
    else:
        p.update(a1=0.0, a2=0.0, dU=0.0)
        if abs(math.sin(p["w"] * c.ts[0])) < 0.1:  # sin(w t0) away from 0
            c, p["w"] = dataclasses.replace(c, ts=c.ts - c.ts[0] + 1.0), 1.2
        s = math.sin(p["w"] * float(c.ts[0]))
        p["b"] = (1 + draw(R.logu(1e-4, 1.0))) * p["U"] ** 2 / (4 * p["nl"] * s)  # D(t0) < 0
        valid = False
        what = "a1 = a2 = 0 and D(t0) = R² − 4 nl b sin(w t0) < 0 (by 1e-4..1 R²): c = 0 has no solution"
    return dataclasses.replace(c, cls=cls, params=p, qd=qd, valid=valid, what=what, known=known, names=names)


# =====================================================================================
# Judging and running
# =====================================================================================


def _p_call(p):
    return {k: float(v) for k, v in p.items()}


def judge_motion(case: NLCase, q, qd, code, message) -> R.Outcome:
    """R.judge_solution with this family's reference."""
    ref = case.reference() if case.valid and code == 0 else None
    if code == 0 and case.valid and ref is None:
        return R.Outcome(R.SILENT_WRONG, "success, but the reference integration failed")
    return R.judge_solution(case, q, qd, code, message, ref)  # pyright: ignore[reportArgumentType]


def run_eager(case: NLCase, method: str) -> R.Outcome:
    """`simulate` eagerly (throw=False; a failure must also raise the same status with throw=True)."""
    p = _p_call(case.params)
    call = dict(method=method, **case.kw)
    try:
        sol = nh.simulate(SHAFTS_NL, p, case.q0, case.qd0, case.ts, throw=False, **call)
    except Exception as e:  # noqa: BLE001
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    code = R._status_code(sol)
    out = judge_motion(case, sol.q, sol.qd, code, sol.message)
    again = lambda: nh.simulate(SHAFTS_NL, p, case.q0, case.qd0, case.ts, throw=True, **call)  # noqa: E731
    return R.throw_agrees(again, code) or out


@functools.lru_cache(maxsize=None)
def _jitted(method):
    def f(p, q0, qd0, ts):
        sol = nh.simulate(SHAFTS_NL, p, q0, qd0, ts, method=method, throw=True)
        return sol.q, sol.qd

    return jax.jit(f)


def run_jit(case: NLCase, method: str) -> R.Outcome:
    """`simulate` under the user's jax.jit with throw=True: a failure is an in-graph error."""
    try:
        q, qd = _jitted(method)(_p_call(case.params), case.q0, case.qd0, case.ts)
        q, qd = np.asarray(q), np.asarray(qd)
    except Exception as e:  # noqa: BLE001
        hit = [m for m in R.STATUS_MESSAGES if m[:60] in str(e)]
        if hit:
            return R.Outcome(R.FAILURE, "in-graph error: " + hit[0][:80])
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    return judge_motion(case, q, qd, 0, "success")


def _loss(theta, rest, w0, v3, solve, delta, q0, ts, method):
    p = {**rest, **theta}
    qd0 = nl_qd0(p, w0, v3, ts[0], solve) + delta
    sol = nh.simulate(SHAFTS_NL, p, q0, qd0, ts, method=method, throw=False)
    L = jnp.dot(jnp.asarray(R.W_Q), sol.q[-1]) + jnp.dot(jnp.asarray(R.W_QD), sol.qd[-1])
    return L, (sol.q, sol.qd, sol.status._value)


@functools.lru_cache(maxsize=None)
def _program(method):
    return jax.jit(jax.vmap(jax.value_and_grad(functools.partial(_loss, method=method), has_aux=True)))


def _stack(cases):
    f = lambda xs: jnp.asarray(np.stack([np.asarray(x, float) for x in xs]))  # noqa: E731
    theta = {k: f([c.params[k] for c in cases]) for k in NL_THETA}
    rest = {k: f([c.params[k] for c in cases]) for k in R.SHAFTS_KEYS if k not in NL_THETA}
    return (
        theta,
        rest,
        f([c.w0 for c in cases]),
        f([c.v3 for c in cases]),
        f([c.solve for c in cases]),
        f([c.delta for c in cases]),
        f([c.q0 for c in cases]),
        f([c.ts for c in cases]),
    )


def batched(cases, method):
    """(q, q̇, status, gradient dict) per case, R.BATCH cases per call of one compiled program."""
    out = []
    for i in range(0, len(cases), R.BATCH):
        chunk = list(cases[i : i + R.BATCH])
        n = len(chunk)
        chunk += [chunk[0]] * (R.BATCH - n)
        (_, (q, qd, status)), grad = _program(method)(*_stack(chunk))
        q, qd, status = np.asarray(q), np.asarray(qd), np.asarray(status)
        grad = {k: np.asarray(v) for k, v in grad.items()}
        out += [(q[j], qd[j], int(status[j]), {k: float(grad[k][j]) for k in NL_THETA}) for j in range(n)]
    return out


def ref_loss(case: NLCase, theta: dict):
    """The differentiated scalar by the reference at parameters theta (the consistent start
    recomputed there, as in `_loss`)."""
    p = {**case.params, **theta}
    qd0 = ref_qd0(p, case.w0, case.v3, case.ts[0], case.solve) + case.delta
    ref = nl_motion(p, case.q0, qd0, case.ts)
    if ref is None:
        return None
    return float(np.dot(R.W_Q, ref[0][-1]) + np.dot(R.W_QD, ref[1][-1]))


def direction(case: NLCase) -> dict:
    rng = np.random.default_rng(abs(hash(tuple(np.round(case.ts, 12)))) % 2**32)
    return {k: float(rng.normal()) * abs(float(case.params[k])) for k in NL_THETA}


def judge_gradient(case: NLCase, grad: dict) -> R.Outcome:
    """As R.judge_gradient: the derivative along a direction v (relative to each parameter's size)
    against the reference's central difference at the relative step case.fd_h (smaller near the
    fold, where the motion's dependence on nl has the scale δ), to GRAD_RTOL of the terms' size
    plus MOTION_ATOL per unit of the weights."""
    h = case.fd_h
    v = direction(case)
    terms = np.array([float(grad[k]) * v[k] for k in NL_THETA])
    plus = ref_loss(case, {k: float(case.params[k]) + h * v[k] for k in NL_THETA})
    minus = ref_loss(case, {k: float(case.params[k]) - h * v[k] for k in NL_THETA})
    if plus is None or minus is None:
        return R.Outcome(R.SILENT_WRONG, "success, but the reference failed near the parameters")
    fd = (plus - minus) / (2 * h)
    gv = float(np.sum(terms))
    floor = R.MOTION_ATOL * (np.sum(np.abs(R.W_Q)) + np.sum(np.abs(R.W_QD))) * sum(abs(x) for x in v.values())
    err = abs(gv - fd) / (R.GRAD_RTOL * (abs(fd) + np.sum(np.abs(terms))) + floor)
    if np.isfinite(gv) and err <= 1.0:
        return R.Outcome(R.RIGHT, f"gradient error {err * R.GRAD_RTOL:.1e}", err * R.GRAD_RTOL)
    return R.Outcome(
        R.SILENT_WRONG,
        f"success but gradient along v {gv:.6g} vs reference {fd:.6g} ({err:.3g} × the allowed error)",
        err * R.GRAD_RTOL,
    )


def run_vmap_grad(cases, method):
    """(value outcome, gradient outcome) per case through jit(vmap(value_and_grad))."""
    out = []
    for c, (q, qd, code, g) in zip(cases, batched(cases, method)):
        value = judge_motion(c, q, qd, code, describe(code))
        if code != 0:
            finite = [k for k in NL_THETA if np.isfinite(g[k])]
            grad = (
                R.Outcome(R.SILENT_WRONG, f"failure status but finite gradient in {finite}")
                if finite
                else R.Outcome(R.FAILURE, "NaN gradient with the failure status")
            )
        elif value.kind != R.RIGHT:
            grad = value
        else:
            grad = judge_gradient(c, g)
        out.append((value, grad))
    return out


# --- linearize ---------------------------------------------------------------------------------

LIN_SPEEDS = ((1, 2), (0, 2))
"""speeds=(1, 2) makes phi1' dependent: solved from the quadratic by Newton's method (the only
choice when a1 = 0); (0, 2) makes phi2' dependent (c is linear in it)."""
LIN_NAMES = r"\bq\b|\bqd\b|\bt\b|params|kinetic|mass|constraint|nonlinear|speeds|dependent"


def lin_known(case: NLCase, speeds) -> str:
    """No known issue is left here (the far root with phi1' dependent was 'nonlinear-far-root':
    linearize now starts Newton's method at the operating point's own dependent velocities)."""
    del case, speeds
    return ""


def run_linearize_eager(case: NLCase, speeds) -> R.Outcome:
    try:
        L = nh.linearize(SHAFTS_NL, _p_call(case.params), case.q0, case.qd0, float(case.ts[0]), speeds=speeds)
    except Exception as e:  # noqa: BLE001
        return R.judge_error(dataclasses.replace(case, names=LIN_NAMES), e)  # pyright: ignore[reportArgumentType]
    return R.judge_linearization(case, (L.A, L.state, L.rates), L.speeds, at_qd=True)  # pyright: ignore[reportArgumentType]


@functools.lru_cache(maxsize=None)
def _lin_jit(speeds):
    def f(p, q, qd, t):
        L = nh.linearize(SHAFTS_NL, p, q, qd, t, speeds=speeds)
        return L.A, L.state, L.rates

    return jax.jit(f)


def run_linearize_jit(case: NLCase, speeds) -> R.Outcome:
    try:
        L = _lin_jit(speeds)(_p_call(case.params), case.q0, case.qd0, case.ts[0])
    except Exception as e:  # noqa: BLE001
        return R.judge_error(dataclasses.replace(case, names=LIN_NAMES), e)  # pyright: ignore[reportArgumentType]
    return R.judge_linearization(case, L, speeds, at_qd=True)  # pyright: ignore[reportArgumentType]


# --- consistent_velocities ------------------------------------------------------------------------


def judge_cv(case: NLCase, out) -> R.Outcome:
    out = np.asarray(out, float)
    if not np.all(np.isfinite(out)):
        return R.Outcome(R.FAILURE, "NaN in the result (consistent_velocities has no status)")
    if not case.valid:
        return R.Outcome(R.SILENT_WRONG, f"finite velocities {out} where c = 0 has no solution")
    p, q, t = case.params, case.q0, float(case.ts[0])
    qd = np.asarray(case.qd, float)
    c = float(abs(MODEL.value(q, out, t, p)[0]))
    scale = float(np.abs(MODEL.jac(q, out, t, p)[0]) @ np.abs(out) + abs(MODEL.value(q, np.zeros(3), t, p)[0]))
    if not c <= SQRT_EPS * scale:
        return R.Outcome(R.SILENT_WRONG, f"|c| = {c:.2e} above √eps × its scale {scale:.2e}")
    ref = ref_projection(p, q, qd, t)
    if ref is None:
        return R.Outcome(R.SILENT_WRONG, "finite velocities, but the reference projection failed")
    err = float(np.max(np.abs(out - ref)) / (np.max(np.abs(qd)) + np.max(np.abs(ref)) + 1e-300))
    if err <= CV_RTOL:
        return R.Outcome(R.RIGHT, f"error {err:.1e}", err)
    branch = np.sign(R.ratio(t, p, np) + 2 * p["nl"] * out[0]) == np.sign(R.ratio(t, p, np) + 2 * p["nl"] * ref[0])
    M = MODEL.mass(q, t, p)
    d_out, d_ref = (float((x - qd) @ M @ (x - qd)) for x in (out, ref))
    return R.Outcome(
        R.SILENT_WRONG,
        f"meets c = 0 but is {'not the nearest point' if branch else 'on the other root'}: off by {err:.1e}, "
        f"½δᵀMδ {d_out / 2:.6g} against {d_ref / 2:.6g} at the projection",
        err,
    )


@functools.partial(jax.jit, static_argnums=0)
def _cv_jit(mech, p, q, qd, t):
    return nh.consistent_velocities(mech, q, qd, t, p)


def run_cv(case: NLCase, jit: bool) -> R.Outcome:
    """nh.consistent_velocities eagerly (a failure must raise, naming the constraint) or under jax.jit."""
    p, t = _p_call(case.params), float(case.ts[0])
    try:
        if jit:
            out = _cv_jit(SHAFTS_NL, p, jnp.asarray(case.q0), jnp.asarray(case.qd), t)
        else:
            out = nh.consistent_velocities(SHAFTS_NL, case.q0, case.qd, t, p)
    except Exception as e:  # noqa: BLE001
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    return judge_cv(case, out)


# --- fit ---------------------------------------------------------------------------------------

FIT_TRUTH_NL = dict(R.FIT_TRUTH, nl=0.2)
"""The shafts fit's truth with nl = 0.2 (y = R + 0.4 phi1' stays ≥ 0.9 · R on the record)."""


def run_fit(record, qd0, start: dict) -> R.Outcome:
    """J2 and c2 from a noise-free record made by the reference, through the shafts fit runner."""
    truth = {"J2": FIT_TRUTH_NL["J2"], "c2": FIT_TRUTH_NL["c2"]}
    over = dict(mech=SHAFTS_NL, params={**FIT_TRUTH_NL, **start}, _truth=truth)
    return R.run_fit("nonlinear", over, r"$^", record, qd0)


def fit_record():
    return R.fit_record(FIT_TRUTH_NL, 1.0, 0.5)


def _draw(strategy, k):
    return R.draw(strategy, k) if k else []


def run_all(n: dict):
    """Every interface on this family: a generator of (interface, class, case, outcome), with n
    giving the cases per class: eager, jit, batches, lin, cv, fit (starts). The rows name the
    method; known-issue territory is marked on the case (`known`)."""
    for cls in NL_CLASSES:
        for c in _draw(nl_cases(cls), n["eager"]):
            for m in METHODS:
                cm = dataclasses.replace(c, known=c.known if m == "appell" else "")
                yield f"nonlinear ({m}), simulate eager", cls, cm, run_eager(cm, m)
    for cls in NL_CLASSES:
        for c in _draw(nl_cases(cls), n["jit"]):
            for m in METHODS:
                cm = dataclasses.replace(c, known=c.known if m == "appell" else "")
                yield f"nonlinear ({m}), simulate jax.jit (throw=True)", cls, cm, run_jit(cm, m)
    batches = _draw(st.tuples(*(nl_cases(c) for c in NL_CLASSES)), n["batches"])
    cases = [c for b in batches for c in b]
    for m in METHODS if cases else ():
        cms = [dataclasses.replace(c, known=c.known if m == "appell" else "") for c in cases]
        for c, (value, grad) in zip(cms, run_vmap_grad(cms, m)):
            yield f"nonlinear ({m}), jit(vmap(value_and_grad)): values", c.cls, c, value
            yield f"nonlinear ({m}), jit(vmap(value_and_grad)): ∂/∂(J2, nl)", c.cls, c, grad
    for cls in NL_CLASSES:
        for c in _draw(nl_cases(cls), n["lin"]):
            for sp in LIN_SPEEDS:
                if c.solve and sp[0] == 0:
                    continue  # a1 = 0: phi2' cannot be dependent (refused, as the shafts family's option case)
                cl = dataclasses.replace(c, known=lin_known(c, sp))
                yield f"nonlinear, linearize eager, speeds={sp}", cls, cl, run_linearize_eager(cl, sp)
                if sp == LIN_SPEEDS[0]:
                    yield f"nonlinear, linearize jax.jit, speeds={sp}", cls, cl, run_linearize_jit(cl, sp)
    for cls in CV_CLASSES:
        for c in _draw(cv_cases(cls), n["cv"]):
            for jit in (False, True):
                api = "nonlinear, consistent_velocities " + ("jax.jit" if jit else "eager")
                yield api, cls, c, run_cv(c, jit)
    if n.get("fit"):
        rec, qd0 = fit_record()
        rng = np.random.default_rng(0)
        for _ in range(n["fit"]):
            start = {
                "J2": FIT_TRUTH_NL["J2"] * rng.uniform(0.6, 1.6),
                "c2": FIT_TRUTH_NL["c2"] * rng.uniform(0.4, 1.6),
            }
            c = NLCase("fit", FIT_TRUTH_NL, 1.0, 0.5, np.zeros(3), rec.t, what="J2, c2 from a reference record")
            yield "nonlinear, fit", "noise-free record, start up to 60 % off", c, run_fit(rec, qd0, start)
