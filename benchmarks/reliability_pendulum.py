"""The "pendulum" family of the reliability checks: a holonomic constraint, events and dense output.

A point mass m on a circle of radius L about the origin, in Cartesian coordinates (x, y):
kinetic energy T = ½ m (ẋ² + ẏ²), potential V = m G y, viscous damping Q = −c m q̇ and the
holonomic constraint g(q) = x² + y² − L² = 0. Every number (m, L, G, c, and the event level xe)
is a traced parameter, so each interface compiles one program per treatment.

Both of jaxnh's treatments of a holonomic constraint, each with Lagrange's and Appell's equations:

* "imposed" — `Mechanism(T, holonomic=g, ...)`: ġ = 0 appended to the velocity constraints;
* "eliminated" — `Mechanism(T, holonomic=g, dependent=(1,), guess=−L)`: y solved by Newton's
  method on the lower branch, x integrated alone.

The reference shares no code with jaxnh: the angle equation θ'' = −(G/L) sin θ − c θ' integrated
by SciPy's DOP853 at rtol 1e-12 (its events located by `solve_ivp(events=...)`, its dense output
by `dense_output=True`), mapped to x = L sin θ, y = −L cos θ; for linearisations and
`consistent_velocities`, the Cartesian equations written out by hand in NumPy (below,
`PendulumModel`, fed to the shafts family's KKT reference).

The outcomes (right / clear error / failure status / unclear error / silent wrong) are those
of `benchmarks/reliability_cases.py`, and so is the motion's tolerance (MOTION_RTOL × each
component's scale + MOTION_ATOL, scaled with the tolerances asked for).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Optional

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

import jaxnh as nh
from benchmarks import reliability_cases as R
from jaxnh._base.status import describe


# =====================================================================================
# The mechanism, in both treatments
# =====================================================================================

P_KEYS = ("m", "L", "G", "c", "xe")
P_THETA = ("L", "c")
"""The parameters differentiated in the gradient checks: the length (which moves q0 with it,
q0 = L (sin θ0, −cos θ0)) and the damping rate."""
P_WQ = (1.0, 0.4)
P_WQD = (0.3, -0.2)
"""The differentiated scalar: L = P_WQ · q(t_end) + P_WQD · q̇(t_end)."""
P_N_TS = 5
N_DENSE = 6
"""Report times per case, and random times at which the dense output is evaluated."""
DENSE_MAX_STEPS = 4096
"""max_steps for dense output (diffrax keeps a buffer of max_steps steps for it; these runs
take at most a few hundred).

Dense output is judged by the motion's tolerance (R.MOTION_RTOL × each component's scale +
R.MOTION_ATOL, scaled with the tolerances asked for): between steps the solver's interpolant
(4th order for the 5th-order Tsit5) adds about rtol^(4/5) ≈ 4e-7 relative at the default
rtol = 1e-8 to the global error bounded there, well inside 1000 × rtol; measured: at most
2e-8 of the scale (benchmarks/RELIABILITY.md)."""


def pend_kinetic(q, qd, t, p):
    return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2)


def pend_potential(q, t, p):
    return p["m"] * p["G"] * q[1]


def pend_holonomic(q, t, p):
    return jnp.stack([q[0] ** 2 + q[1] ** 2 - p["L"] ** 2])


def pend_forces(q, qd, t, p):
    return -p["c"] * p["m"] * qd


def pend_guess(q_independent, t, p):
    return -p["L"] * jnp.ones(1, dtype=q_independent.dtype)


_COMMON = dict(potential=pend_potential, holonomic=pend_holonomic, forces=pend_forces, names=("x", "y"))
TREATMENTS = {
    "imposed": nh.Mechanism(pend_kinetic, **_COMMON),
    "eliminated": nh.Mechanism(pend_kinetic, dependent=(1,), guess=pend_guess, **_COMMON),
}
VARIANTS = tuple((t, m) for t in TREATMENTS for m in ("lagrange", "appell"))
"""(treatment, method): each interface compiles one program per variant it runs."""


def vname(variant) -> str:
    return f"{variant[0]}, {variant[1]}"


# =====================================================================================
# The reference: the angle equation, SciPy
# =====================================================================================


def angle_start(p, th0, w0, xp=np):
    """(q0, q̇0) on the circle and tangent to it, from the angle θ0 and rate ω0."""
    L = p["L"]
    return xp.stack([L * xp.sin(th0), -L * xp.cos(th0)]), L * w0 * xp.stack([xp.cos(th0), xp.sin(th0)])


def ref_angle(p, th0, w0, t0, t1, *, t_eval=None, event=False, dense=False, rtol=1e-12):
    """SciPy's solve_ivp of θ'' = −(G/L) sin θ − c θ' (DOP853, rtol 1e-12); None if it failed.
    event=True: terminal event L sin θ = xe (either direction)."""
    G, L, c = p["G"], p["L"], p["c"]

    def f(t, y):
        return np.array([y[1], -(G / L) * math.sin(y[0]) - c * y[1]])

    events = None
    if event:

        def crossing(t, y):
            return L * math.sin(y[0]) - p["xe"]

        crossing.terminal = True  # pyright: ignore[reportFunctionMemberAccess]
        events = crossing
    scale = abs(th0) + abs(w0) + math.sqrt(G / L) * math.pi + 1e-300
    try:
        sol = solve_ivp(
            f, (t0, t1), [th0, w0], method="DOP853", t_eval=t_eval, rtol=rtol, atol=rtol * 1e-3 * scale,
            events=events, dense_output=dense,
        )  # fmt: skip
    except (ValueError, ZeroDivisionError, OverflowError):
        return None
    if sol.status < 0 or not np.all(np.isfinite(sol.y)):
        return None
    return sol


def to_cartesian(p, th, w):
    L = p["L"]
    q = np.stack([L * np.sin(th), -L * np.cos(th)], axis=-1)
    qd = np.stack([L * w * np.cos(th), L * w * np.sin(th)], axis=-1)
    return q, qd


class PendulumModel:
    """The pendulum's Cartesian equations written out by hand in NumPy (for the shafts family's KKT
    reference `R.ref_accelerations`, `R.ref_project`, `R.ref_linearization`): the velocity constraint
    ġ/2 = x ẋ + y ẏ, its Jacobian (x, y), and `dt` = the rest of its time derivative, ẋ² + ẏ²."""

    s, m = 2, 1

    @staticmethod
    def mass(q, t, p):
        return p["m"] * np.eye(2)

    @staticmethod
    def jac(q, qd, t, p):
        return np.array([[q[0], q[1]]])

    @staticmethod
    def value(q, qd, t, p):
        return np.array([q[0] * qd[0] + q[1] * qd[1]])

    @staticmethod
    def dt(q, qd, t, p):
        return np.array([qd[0] ** 2 + qd[1] ** 2])

    @staticmethod
    def forces(q, qd, t, p):
        return np.array([-p["c"] * p["m"] * qd[0], -p["c"] * p["m"] * qd[1] - p["m"] * p["G"]])


# =====================================================================================
# Cases
# =====================================================================================


@dataclasses.dataclass
class PCase:
    """One pendulum call: parameters, the start as an angle and rate plus deliberate offsets
    (dq off the circle, dqd off its tangent), report times, dense-output times."""

    cls: str
    params: dict
    th0: float
    w0: float
    ts: Any
    dq: Any = dataclasses.field(default_factory=lambda: np.zeros(2))
    dqd: Any = dataclasses.field(default_factory=lambda: np.zeros(2))
    tt: Any = None
    valid: bool = True
    names: str = r"$^"
    what: str = ""
    kw: dict = dataclasses.field(default_factory=dict)
    known: str = ""
    family: str = "pendulum"

    @property
    def q0(self):
        return angle_start(self.params, self.th0, self.w0)[0] + self.dq

    @property
    def qd0(self):
        return angle_start(self.params, self.th0, self.w0)[1] + self.dqd

    @functools.cached_property
    def _ref(self):
        if not self.valid:
            return None
        p = self.params
        if not all(np.isfinite([p[k] for k in P_KEYS] + [self.th0, self.w0])) or not np.all(np.isfinite(self.ts)):
            return None
        return ref_angle(p, self.th0, self.w0, float(self.ts[0]), float(self.ts[-1]), dense=True)

    def reference(self, ts=None):
        """(q, q̇) of the right answer at ts (default the report times), or None."""
        sol = self._ref
        if sol is None:
            return None
        y = sol.sol(np.asarray(self.ts if ts is None else ts, float))
        return to_cartesian(self.params, y[0], y[1])

    @functools.cached_property
    def event_reference(self):
        """(event time or None, end time): the first time L sin θ = xe, by SciPy's event location."""
        sol = ref_angle(self.params, self.th0, self.w0, float(self.ts[0]), float(self.ts[-1]), event=True)
        if sol is None:
            return None
        te = sol.t_events[0]
        return (float(te[0]) if len(te) else None), float(sol.t[-1])


def report_times_p(draw, period):
    t0 = draw(st.floats(-1.0, 1.0))
    span = draw(st.floats(0.8, 1.5)) * period
    gaps = np.asarray(draw(st.lists(st.floats(0.2, 1.0), min_size=P_N_TS - 1, max_size=P_N_TS - 1)))
    return t0 + span * np.concatenate([[0.0], np.cumsum(gaps) / np.sum(gaps)])


def rate_for_amplitude(p, th0, amplitude):
    """|ω0| that takes the undamped pendulum from θ0 to the amplitude θmax (energy)."""
    return math.sqrt(max(0.0, 2 * p["G"] / p["L"] * (math.cos(th0) - math.cos(amplitude))))


PENDULUM_CLASSES = (
    "valid",
    "tiny amplitude",
    "start above the pivot",
    "swing to or past the horizontal",
    "q0 off the circle",
    "qd0 with ġ ≠ 0",
    "non-finite value",
    "mass not positive",
)
"""Classes that vary values only (every interface runs them). 'start above the pivot': valid for
the imposed treatment; for the eliminated one the guess −L is on the other branch (expected:
STATUS.holonomic_branch). 'swing to or past the horizontal': the motion reaches θmax = 1.45..2.5 rad,
where the eliminated treatment's ∂g/∂y = 2y vanishes (right, or a failure status; never a
motion on the wrong branch)."""


@st.composite
def physical_p(draw):
    p = dict(
        m=draw(R.logu(0.05, 20.0)),
        L=draw(R.logu(0.2, 3.0)),
        G=draw(st.floats(1.0, 20.0)),
        c=0.0,
        xe=0.0,
    )
    omega = math.sqrt(p["G"] / p["L"])
    p["c"] = draw(st.sampled_from([0.0, 1.0])) * draw(st.floats(0.0, 0.5)) * omega  # under-damped
    return p, 2 * math.pi / omega


@st.composite
def pendulum_cases(draw, cls=None):
    """One pendulum case of a class (drawn when cls is None)."""
    cls = draw(st.sampled_from(PENDULUM_CLASSES)) if cls is None else cls
    p, period = draw(physical_p())
    th0 = draw(R.signed(0.1, 1.0))
    amp = draw(st.floats(max(abs(th0), 0.15) + 0.02, 1.2))
    w0 = draw(st.sampled_from([1.0, -1.0])) * rate_for_amplitude(p, th0, amp)
    ts = report_times_p(draw, period)
    dq, dqd = np.zeros(2), np.zeros(2)
    valid, what, names = True, "", r"$^"
    if cls == "valid":
        what = "random m, L, G, damping (under-damped), angle ±0.1..1 rad, rate up to an amplitude ≤ 1.2 rad"
    elif cls == "tiny amplitude":
        scale = draw(R.logu(1e-12, 1e-4))
        th0, w0 = th0 * scale, w0 * scale
        what = "angle and rate scaled by 1e-12..1e-4 (x ≈ 0, y ≈ −L)"
    elif cls == "start above the pivot":
        th0 = draw(R.signed(2.2, 3.0))
        w0 = draw(st.floats(-0.5, 0.5)) * math.sqrt(p["G"] / p["L"])
        what = "θ0 = ±2.2..3.0 rad (y0 > 0): the other branch than the eliminated treatment's guess −L"
    elif cls == "swing to or past the horizontal":
        th0 = draw(R.signed(0.3, 1.2))
        amp = draw(st.floats(1.45, 2.5))
        p["c"] = 0.0
        w0 = math.copysign(1.0, th0) * rate_for_amplitude(p, th0, amp)
        what = "undamped swing up to θmax = 1.45..2.5 rad, where ∂g/∂y = 2y of the eliminated y vanishes"
    elif cls == "q0 off the circle":
        phi = draw(st.floats(0.0, 2 * math.pi))
        dq = np.array([math.cos(phi), math.sin(phi)]) * p["L"] * draw(R.logu(1e-6, 0.2))
        valid = False
        what = "q0 moved off the circle by 1e-6..0.2 L in any direction (expected: STATUS.holonomic_violated)"
    elif cls == "qd0 with ġ ≠ 0":
        q0 = angle_start(p, th0, w0)[0]
        radial = q0 / p["L"]
        speed = abs(w0) * p["L"] + math.sqrt(p["G"] * p["L"])
        dqd = radial * speed * draw(R.signed(1e-6, 0.5))
        valid = False
        what = (
            "a radial velocity of 1e-6..0.5 of the speed scale added to qd0 (expected: STATUS.inconsistent_velocities)"
        )
    elif cls == "non-finite value":
        bad = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        where = draw(st.sampled_from(["m", "L", "G", "c", "q0", "qd0", "ts"]))
        if where in p:
            p[where] = bad
        elif where == "q0":
            dq = np.array([bad, 0.0])
        elif where == "qd0":
            dqd = np.array([0.0, bad])
        else:
            ts = ts.copy()
            ts[draw(st.integers(0, P_N_TS - 1))] = bad
        valid = False
        what = "NaN or ±inf in a parameter, q0, qd0 or ts"
    elif cls == "mass not positive":
        p["m"] = -draw(st.sampled_from([0.0, 1.0])) * draw(R.logu(1e-6, 1.0))
        valid = False
        what = "m ≤ 0 (mass matrix m I not positive definite)"
    tt = np.sort(draw(st.lists(st.floats(0.0, 1.0), min_size=N_DENSE, max_size=N_DENSE)))
    tt = ts[0] + tt * (ts[-1] - ts[0]) if np.all(np.isfinite(ts)) else np.linspace(0.0, 1.0, N_DENSE)
    return PCase(cls, p, th0, w0, ts, dq, dqd, tt, valid=valid, names=names, what=what)


EVENT_CLASSES = ("event: x crosses a level", "event out of reach")


@st.composite
def event_cases(draw, cls):
    """A valid case with a terminating event x = xe: a level between 0 and x0 (crossed
    transversally on the way to the bottom), or one beyond the circle (|xe| > L: never crossed)."""
    c = draw(pendulum_cases("valid"))
    p = dict(c.params)
    x0 = p["L"] * math.sin(c.th0)
    if cls == "event: x crosses a level":
        p["xe"] = draw(st.floats(0.1, 0.8)) * x0
        what = "a terminating event at x = xe, xe between 0 and x0 (0.1..0.8 x0): crossed on the way down"
    else:
        p["xe"] = draw(st.sampled_from([1.0, -1.0])) * draw(st.floats(1.05, 2.0)) * p["L"]
        what = "a terminating event at |xe| = 1.05..2 L, beyond the circle: never crossed (the run ends at ts[-1])"
    return dataclasses.replace(c, cls=cls, params=p, what=what)


def dense_cases(draw_n):
    return [dataclasses.replace(c, cls="dense output", what=DENSE_WHAT) for c in draw_n]


DENSE_WHAT = "SaveAt(ts=ts, dense=True), sol.evaluate at 6 random times in [ts[0], ts[-1]] of a valid case"


# =====================================================================================
# Judging
# =====================================================================================


def _p_call(p):
    return {k: float(v) for k, v in p.items()}


def judge_motion(case: PCase, q, qd, code, message, ts=None) -> R.Outcome:
    """As `R.judge_solution`, with the angle reference at ts (default the report times)."""
    ts = case.ts if ts is None else ts
    ref = case.reference(ts) if case.valid and code == 0 else None
    view = dataclasses.replace(case)
    view.ts = np.asarray(ts, float)  # the span the motion's scale is measured over
    if code == 0 and case.valid and ref is None:
        return R.Outcome(R.SILENT_WRONG, "success, but the reference integration failed")
    return R.judge_solution(view, q, qd, code, message, ref)  # pyright: ignore[reportArgumentType]


def run_eager(case: PCase, variant) -> R.Outcome:
    """`simulate` eagerly (throw=False, then throw=True must raise the same status)."""
    mech = TREATMENTS[variant[0]]
    p = _p_call(case.params)
    try:
        sol = nh.simulate(mech, p, case.q0, case.qd0, case.ts, method=variant[1], throw=False, **case.kw)
    except Exception as e:  # noqa: BLE001
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    code = R._status_code(sol)
    out = judge_motion(case, sol.q, sol.qd, code, sol.message)
    again = lambda: nh.simulate(mech, p, case.q0, case.qd0, case.ts, method=variant[1], throw=True, **case.kw)  # noqa: E731
    return R.throw_agrees(again, code) or out


@functools.lru_cache(maxsize=None)
def _jitted(variant):
    mech = TREATMENTS[variant[0]]

    def f(p, q0, qd0, ts):
        sol = nh.simulate(mech, p, q0, qd0, ts, method=variant[1], throw=True)
        return sol.q, sol.qd

    return jax.jit(f)


def run_jit(case: PCase, variant) -> R.Outcome:
    """`simulate` under the user's jax.jit with throw=True: a failure is an in-graph error."""
    try:
        q, qd = _jitted(variant)(_p_call(case.params), case.q0, case.qd0, case.ts)
        q, qd = np.asarray(q), np.asarray(qd)
    except Exception as e:  # noqa: BLE001
        text = str(e)
        hit = [m for m in R.STATUS_MESSAGES if m[:60] in text]
        if hit:
            return R.Outcome(R.FAILURE, "in-graph error: " + hit[0][:80])
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    return judge_motion(case, q, qd, 0, "success")


# --- jit(vmap(value_and_grad)): motions, events and dense output --------------------------------


def _start(p, th0, w0, dq, dqd):
    q0, qd0 = angle_start(p, th0, w0, jnp)
    return q0 + dq, qd0 + dqd


def _loss_motion(theta, rest, th0, w0, dq, dqd, ts, tt, variant):
    p = {**rest, **theta}
    q0, qd0 = _start(p, th0, w0, dq, dqd)
    sol = nh.simulate(TREATMENTS[variant[0]], p, q0, qd0, ts, method=variant[1], throw=False)
    L = jnp.dot(jnp.asarray(P_WQ), sol.q[-1]) + jnp.dot(jnp.asarray(P_WQD), sol.qd[-1])
    return L, (sol.q, sol.qd, sol.status._value)


def _loss_event(theta, rest, th0, w0, dq, dqd, ts, tt, variant, forward=False):
    """The terminating event's time (the solve's last time, saved with SaveAt(t1=True))."""
    p = {**rest, **theta}
    q0, qd0 = _start(p, th0, w0, dq, dqd)
    kw = dict(adjoint=diffrax.ForwardMode()) if forward else {}
    sol = nh.simulate(
        TREATMENTS[variant[0]], p, q0, qd0, ts, method=variant[1], throw=False, event=EVENT,
        saveat=diffrax.SaveAt(t1=True), **kw,
    )  # fmt: skip
    return sol.ts[-1], (sol.q, sol.qd, sol.status._value)


def _loss_dense(theta, rest, th0, w0, dq, dqd, ts, tt, variant):
    """Σ P_WQ · q(tt_i) + P_WQD · q̇(tt_i) over the dense output at the random times tt."""
    p = {**rest, **theta}
    q0, qd0 = _start(p, th0, w0, dq, dqd)
    sol = nh.simulate(
        TREATMENTS[variant[0]], p, q0, qd0, ts, method=variant[1], throw=False,
        saveat=diffrax.SaveAt(ts=ts, dense=True), max_steps=DENSE_MAX_STEPS,
    )  # fmt: skip
    q, qd = jax.vmap(sol.evaluate)(tt)
    L = jnp.sum(q @ jnp.asarray(P_WQ)) + jnp.sum(qd @ jnp.asarray(P_WQD))
    return L, (q, qd, sol.status._value)


def event_condition(t, y, params, **kw):
    return y[0][0] - params["xe"]


EVENT = diffrax.Event(event_condition)


@functools.lru_cache(maxsize=None)
def _program(kind, variant):
    loss = {"motion": _loss_motion, "event": _loss_event, "dense": _loss_dense}[kind]
    f = functools.partial(loss, variant=variant)
    return jax.jit(jax.vmap(jax.value_and_grad(f, has_aux=True)))


@functools.lru_cache(maxsize=None)
def _program_jacfwd(variant):
    f = functools.partial(_loss_event, variant=variant, forward=True)
    return jax.jit(jax.vmap(jax.jacfwd(f, has_aux=True)))


def _stack(cases):
    f = lambda xs: jnp.asarray(np.stack([np.asarray(x, float) for x in xs]))  # noqa: E731
    theta = {k: f([c.params[k] for c in cases]) for k in P_THETA}
    rest = {k: f([c.params[k] for c in cases]) for k in P_KEYS if k not in P_THETA}
    return (
        theta,
        rest,
        f([c.th0 for c in cases]),
        f([c.w0 for c in cases]),
        f([c.dq for c in cases]),
        f([c.dqd for c in cases]),
        f([c.ts for c in cases]),
        f([c.tt if c.tt is not None else np.zeros(N_DENSE) for c in cases]),
    )


def batched(kind, cases, variant):
    """(value, q, q̇, status, gradient dict) per case, BATCH cases per call of one compiled program.
    kind: "motion", "event", "dense" (jax.value_and_grad) or "event-jacfwd" (jax.jacfwd with
    adjoint=diffrax.ForwardMode(); no value: NaN)."""
    out = []
    for i in range(0, len(cases), R.BATCH):
        chunk = list(cases[i : i + R.BATCH])
        n = len(chunk)
        chunk += [chunk[0]] * (R.BATCH - n)
        if kind == "event-jacfwd":
            grad, (q, qd, status) = _program_jacfwd(variant)(*_stack(chunk))
            value = np.full(R.BATCH, np.nan)
        else:
            (value, (q, qd, status)), grad = _program(kind, variant)(*_stack(chunk))
        value, q, qd, status = (np.asarray(x) for x in (value, q, qd, status))
        grad = {k: np.asarray(v) for k, v in grad.items()}
        out += [
            (float(value[j]), q[j], qd[j], int(status[j]), {k: float(grad[k][j]) for k in P_THETA}) for j in range(n)
        ]
    return out


# --- the references of the differentiated scalars -------------------------------------------------


def ref_scalar(kind, case: PCase, theta: dict) -> Optional[float]:
    """The differentiated scalar by the reference at parameters theta."""
    p = {**case.params, **theta}
    c = dataclasses.replace(case, params=p)
    if kind == "motion":
        ref = c.reference()
        if ref is None:
            return None
        return float(np.dot(P_WQ, ref[0][-1]) + np.dot(P_WQD, ref[1][-1]))
    if kind == "dense":
        ref = c.reference(c.tt)
        if ref is None:
            return None
        return float(np.sum(ref[0] @ np.asarray(P_WQ)) + np.sum(ref[1] @ np.asarray(P_WQD)))
    er = c.event_reference
    if er is None:
        return None
    return er[0] if er[0] is not None else er[1]


def p_direction(case: PCase) -> dict:
    rng = np.random.default_rng(abs(hash(tuple(np.round(np.asarray(case.ts, float), 12)))) % 2**32)
    return {k: float(rng.normal()) * (abs(float(case.params[k])) + 0.1) for k in P_THETA}


def judge_p_gradient(kind, case: PCase, grad: dict, floor: float, h: float = 1e-4) -> R.Outcome:
    """The gradient along a random direction v against the reference's central difference, to
    R.GRAD_RTOL of the terms' size plus `floor` (what the absolute tolerance allows per unit of v)."""
    v = p_direction(case)
    terms = np.array([grad[k] * v[k] for k in P_THETA])
    plus = ref_scalar(kind, case, {k: case.params[k] + h * v[k] for k in P_THETA})
    minus = ref_scalar(kind, case, {k: case.params[k] - h * v[k] for k in P_THETA})
    if plus is None or minus is None:
        return R.Outcome(R.SILENT_WRONG, "success, but the reference failed near the parameters")
    fd = (plus - minus) / (2 * h)
    gv = float(np.sum(terms))
    err = abs(gv - fd) / (R.GRAD_RTOL * (abs(fd) + np.sum(np.abs(terms))) + floor * sum(abs(x) for x in v.values()))
    if np.isfinite(gv) and err <= 1.0:
        return R.Outcome(R.RIGHT, f"gradient error {err * R.GRAD_RTOL:.1e}", err * R.GRAD_RTOL)
    return R.Outcome(
        R.SILENT_WRONG, f"gradient along v {gv:.6g} vs reference {fd:.6g} ({err:.3g} × the allowed error)",
        err * R.GRAD_RTOL,
    )  # fmt: skip


def _failed_gradient(g) -> R.Outcome:
    finite = [k for k in P_THETA if np.isfinite(g[k])]
    if finite:
        return R.Outcome(R.SILENT_WRONG, f"failure status but finite gradient in {finite}")
    return R.Outcome(R.FAILURE, "NaN gradient with the failure status")


EVENT_RTOL = R.MOTION_RTOL
"""An event time is right when |t_e − t_ref| ≤ (MOTION_RTOL · scale_x + MOTION_ATOL) / |ẋ(t_ref)|:
the time at which the motion's x, itself right to MOTION_RTOL of its scale (max |x| + span ·
max |ẋ|) + MOTION_ATOL, crosses the level at the speed ẋ; the root finder (Newton, 1e-3 √eps)
and SciPy's event location (brentq on the rtol-1e-12 dense output) add nothing at that size.
Scaled, like the motion's, with the tolerances asked for."""


def judge_event(case: PCase, t_end, q_end, code, message) -> R.Outcome:
    """The solve's end time (the event's, or ts[-1] when it never fires) against the reference;
    a failure must leave NaN/inf in the state it reports."""
    if code != 0:
        if np.all(np.isfinite(np.asarray(q_end))):
            return R.Outcome(R.SILENT_WRONG, f"failure status but finite values: {message[:60]}")
        return R.Outcome(R.FAILURE, message[:100])
    er = case.event_reference
    ref = case.reference(np.linspace(case.ts[0], case.ts[-1], 65))
    if er is None or ref is None:
        return R.Outcome(R.SILENT_WRONG, "success, but the reference integration failed")
    te_ref, end = er
    t_ref = te_ref if te_ref is not None else end
    span = float(case.ts[-1] - case.ts[0])
    xs = np.max(np.abs(ref[0][:, 0])) + span * np.max(np.abs(ref[1][:, 0]))
    rtol = EVENT_RTOL * float(case.kw.get("rtol", 1e-8)) / 1e-8
    atol = R.MOTION_ATOL * float(case.kw.get("atol", 1e-10)) / 1e-10
    if te_ref is None:
        xdot, allowed = 1.0, 1e-12 * (abs(end) + 1)  # no event: the run ends at ts[-1] exactly
    else:
        xdot = abs(float(case.reference([te_ref])[1][0, 0]))
        allowed = (rtol * xs + atol) / xdot
    err = abs(float(t_end) - t_ref)
    if not err <= allowed:
        what = f"event at {t_ref:.10g}" if te_ref is not None else f"no event (end {end:.10g})"
        return R.Outcome(
            R.SILENT_WRONG, f"success but the run ends at {float(t_end):.10g}; reference: {what}", err * xdot / xs
        )
    return R.Outcome(R.RIGHT, f"end-time error {err:.1e} s (allowed {allowed:.1e} s)", err * xdot / xs)


def run_event_eager(case: PCase, variant) -> R.Outcome:
    """`simulate(..., event=EVENT, saveat=SaveAt(t1=True))` eagerly: the end time and state."""
    try:
        sol = nh.simulate(
            TREATMENTS[variant[0]], _p_call(case.params), case.q0, case.qd0, case.ts, method=variant[1],
            throw=False, event=EVENT, saveat=diffrax.SaveAt(t1=True),
        )  # fmt: skip
    except Exception as e:  # noqa: BLE001
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    return judge_event(case, float(sol.ts[-1]), sol.q[-1], R._status_code(sol), sol.message)


def run_dense_eager(case: PCase, variant) -> R.Outcome:
    """`simulate(..., saveat=SaveAt(ts=ts, dense=True))` eagerly, `sol.evaluate` at the random times."""
    try:
        sol = nh.simulate(
            TREATMENTS[variant[0]], _p_call(case.params), case.q0, case.qd0, case.ts, method=variant[1],
            throw=False, saveat=diffrax.SaveAt(ts=case.ts, dense=True), max_steps=DENSE_MAX_STEPS,
        )  # fmt: skip
        code = R._status_code(sol)
        pairs = [sol.evaluate(float(t)) for t in case.tt]
    except Exception as e:  # noqa: BLE001
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    q = np.stack([np.asarray(a) for a, _ in pairs])
    qd = np.stack([np.asarray(b) for _, b in pairs])
    return judge_motion(case, q, qd, code, sol.message, ts=case.tt)


def run_batched(kind, cases, variant):
    """(value outcome, gradient outcome) per case through one compiled jit(vmap(value_and_grad))
    (or jit(vmap(jacfwd)) for kind "event-jacfwd", whose value is judged by the state it returns)."""
    out = []
    floor = R.MOTION_ATOL * (np.sum(np.abs(P_WQ)) + np.sum(np.abs(P_WQD)))
    for c, (value, q, qd, code, g) in zip(cases, batched(kind, cases, variant)):
        msg = describe(code)
        if kind == "motion":
            vo = judge_motion(c, q, qd, code, msg)
        elif kind == "dense":
            vo = judge_motion(c, q, qd, code, msg, ts=c.tt)
        elif kind == "event":
            vo = judge_event(c, value, q[-1], code, msg)
        else:  # jacfwd: no value; the state at the end must be finite on success (and right: x = xe or t1)
            vo = R.Outcome(R.RIGHT, "state at the end finite") if code == 0 and np.all(np.isfinite(q)) else (
                R.Outcome(R.FAILURE, msg[:100]) if code != 0 and not np.all(np.isfinite(q[-1]))
                else R.Outcome(R.SILENT_WRONG, f"status {msg[:40]} with state {q[-1]}"))  # fmt: skip
        if code != 0:
            go = _failed_gradient(g)
        elif vo.kind != R.RIGHT:
            go = vo
        else:
            scalar = "event" if kind.startswith("event") else kind
            go = judge_p_gradient(scalar, c, g, floor * (N_DENSE if kind == "dense" else 1.0))
        out.append((vo, go))
    return out


# =====================================================================================
# consistent_velocities
# =====================================================================================

CV_RTOL = 1e-10
"""consistent_velocities is right when every velocity is within CV_RTOL × (|q̇ given| + |q̇ reference|)
of the reference's projection (one Gauss–Newton step for the linear ġ = 0: exact up to rounding,
cond·eps ≈ 1e-15 here; Gauss–Newton on the shafts' nonlinear constraint converges quadratically
to its √eps-of-scale acceptance, whose effect on the velocities is far below 1e-10 after the
second step). A wrong projection (another metric, a missed iteration) is off by 1e-3 or more."""


CV_CLASSES = ("valid", "q off the circle", "non-finite value", "mass not positive")


@st.composite
def cv_cases(draw, cls):
    """q on (or off) the circle and an arbitrary velocity (a tangent part and a radial part)."""
    c = draw(pendulum_cases("valid"))
    p = dict(c.params)
    q = angle_start(p, c.th0, c.w0)[0]
    speed = math.sqrt(p["G"] * p["L"])
    qd = np.array([draw(st.floats(-1.0, 1.0)), draw(st.floats(-1.0, 1.0))]) * speed
    valid = True
    what = "a random velocity (radial part up to the speed scale) at a point of the circle"
    if cls == "q off the circle":
        q = q * draw(st.floats(0.5, 2.0))
        what = "q off the circle (0.5..2 L): ġ = 2 q·q̇ = 0 still defines the nearest velocity"
    elif cls == "non-finite value":
        where = draw(st.sampled_from(["m", "q", "qd"]))
        bad = draw(st.sampled_from([math.nan, math.inf]))
        if where == "m":
            p["m"] = bad
        elif where == "q":
            q = np.array([bad, q[1]])
        else:
            qd = np.array([qd[0], bad])
        valid = False
        what = "NaN or inf in m, q or qd"
    elif cls == "mass not positive":
        p["m"] = -draw(R.logu(1e-6, 1.0))
        valid = False
        what = "m < 0: no kinetic-energy metric"
    q_on, qd_on = angle_start(p, c.th0, c.w0)
    return PCase(
        cls, p, c.th0, c.w0, c.ts, q - q_on, qd - qd_on, valid=valid, what=what,
        names=r"\bq\b|\bqd\b|params|mass|kinetic|finite|positive|\bm\b",
    )  # fmt: skip


def judge_cv(case, q, qd, out, model) -> R.Outcome:
    out = np.asarray(out)
    if not np.all(np.isfinite(out)):
        return R.Outcome(R.FAILURE, "NaN in the result (consistent_velocities has no status)")
    if not case.valid:
        return R.Outcome(R.SILENT_WRONG, f"finite velocities {out} for an input without an answer")
    p = {k: float(v) for k, v in case.params.items()}
    ref = R.ref_project(model, np.asarray(q, float), np.asarray(qd, float), float(case.ts[0]), p)
    err = float(np.max(np.abs(out - ref)) / (np.max(np.abs(qd)) + np.max(np.abs(ref)) + 1e-300))
    if err <= CV_RTOL:
        return R.Outcome(R.RIGHT, f"error {err:.1e}", err)
    return R.Outcome(R.SILENT_WRONG, f"velocities {out} vs reference {ref} ({err:.1e})", err)


def run_cv(case, mech, model, jit: bool, q=None, qd=None) -> R.Outcome:
    """nh.consistent_velocities eagerly (errors judged by their message) or under jax.jit."""
    p = _p_call(case.params)
    q = case.q0 if q is None else q
    qd = case.qd0 if qd is None else qd
    try:
        if jit:
            out = _CV_JIT(mech, p, jnp.asarray(q), jnp.asarray(qd), float(case.ts[0]))
        else:
            out = nh.consistent_velocities(mech, q, qd, float(case.ts[0]), p)
    except Exception as e:  # noqa: BLE001
        return R.judge_error(case, e)  # pyright: ignore[reportArgumentType]
    return judge_cv(case, q, qd, out, model)


@functools.partial(jax.jit, static_argnums=0)
def _cv_jit(mech, p, q, qd, t):
    return nh.consistent_velocities(mech, q, qd, t, p)


def _CV_JIT(mech, p, q, qd, t):
    return _cv_jit(mech, p, q, qd, t)


# =====================================================================================
# Which variant each interface runs (one compiled program per variant and interface)
# =====================================================================================

EAGER_VARIANTS = VARIANTS
JIT_VARIANTS = (("imposed", "lagrange"), ("eliminated", "appell"))
VMAP_VARIANTS = (("imposed", "appell"), ("eliminated", "lagrange"))
EVENT_EAGER_VARIANTS = (("imposed", "appell"), ("eliminated", "lagrange"))
EVENT_GRAD_VARIANT = ("eliminated", "appell")
EVENT_JACFWD_VARIANT = ("imposed", "lagrange")
DENSE_EAGER_VARIANT = ("eliminated", "lagrange")
DENSE_GRAD_VARIANT = ("imposed", "appell")
"""Compilation dominates (5–25 s of CPU per program): each interface runs the variants listed,
so that every treatment and every method meets every interface at least once."""
