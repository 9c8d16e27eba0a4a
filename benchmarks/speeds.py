"""Speeds and quaternions (issue 44): the rolling disc in Kane's speeds against SymPy's pipeline and a
hand-written diffrax program; the ball on a turntable in a unit quaternion against Euler angles.

1. The rolling disc (`jaxnh.models.disc_speeds`, the disc of `jaxnh.models.disc`): a wobbling disc
   (steady circle at lean 0.3 rad and yaw rate −1 rad/s, spin 6.99 rad/s, plus a lean rate of
   0.5 rad/s), 10 s, 101 report times. Every contender integrates in the same generalized speeds,
   u1, u2, u3 = the disc's angular velocity in the lean frame (SymPy's rolling-disc example):

   * jaxnh: `simulate` with the user's defaults except rtol (atol = rtol/100): "lagrange" (the
     default; state q and the five speeds, the slip speeds u4 = u5 = 0 held by multipliers) and
     "appell" (state q, u1, u2, u3, as SymPy's);
   * SymPy + SciPy: `KanesMethod` with SymPy's example's frames and speeds (the contact point's
     x, y added as two more kinematic equations), `lambdify(cse=True)` with NumPy, SciPy's
     `solve_ivp`, RK45 and DOP853 (the faster at matched error is the peer);
   * hand JAX: SymPy's mass matrix, forcing and kinematics printed as `jax.numpy` source (common
     subexpressions, a dense solve), `diffrax.Tsit5`, jitted: the equations written by hand.

   Errors: largest absolute error over the report times of q and u1, u2, u3 against SciPy's DOP853
   at rtol 1e-13 on SymPy's equations (checked against `jaxnh.models.disc`, in q̇, at rtol 1e-12).
   Matched error: for each target error, each contender's loosest tolerance on a half-decade grid
   that reaches it. Steady solves: CPU time per solve after compilation, medians over interleaved
   rounds. First answers: fresh processes (every core, the user's settings, no compilation cache),
   from before the first import to the answer on the host, of jaxnh, the hand program, SymPy's
   whole pipeline (import, derivation, `lambdify`, `solve_ivp`) and jaxnh's first gradient
   (`jax.grad` of the final coordinates' sum with respect to every parameter; its error, relative,
   along a random direction against a central difference of the reference).

2. The ball on a turntable (`jaxnh.models.turntable`) against the same ball in ZYX Euler angles
   (yaw ψ, pitch θ, roll φ; `euler_mechanism`, written in q̇): from the issue's state, 2000 s at
   rtol 1e-10 (steps, the centre's error against `turntable.closed_form`, how close the pitch comes
   to ±90°, where the Euler solve stops with `simulate`'s default max_steps), and from starts a
   distance δ from gimbal lock (pitch π/2 − δ), 200 s.

    python -m benchmarks.speeds [--quick] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from . import common as C


C.pin()  # before JAX starts

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import disc, disc_speeds as DS, turntable as TT  # noqa: E402
from jaxnh.rigid import quaternion_from_axis_angle, rot_x, rot_y, rot_z, rotation_from_quaternion  # noqa: E402


# --------------------------------------------------------------------------- 1. the rolling disc

LEAN, YAW_RATE, LEAN_RATE = 0.3, -1.0, 0.5  # rad, rad/s, rad/s
T_END, N_REPORT = 10.0, 101
GRID = [10.0 ** (-k / 2) for k in range(6, 27)]  # rtol 1e-3 … 1e-13, half decades
REF_RTOL, REF_ATOL = 1e-13, 1e-15
KEYS = ("m", "r", "I1", "I3", "g")  # the order of SymPy's parameter symbols

DISC_SYMPY = r'''
import numpy as np
import sympy as sm
import sympy.physics.mechanics as me
from scipy.integrate import solve_ivp

def derive():
    """Kane's equations of the rolling disc in SymPy's example's frames and speeds, plus x, y."""
    t = me.dynamicsymbols._t
    x, y, yaw, lean, spin = me.dynamicsymbols("x y yaw lean spin")
    u1, u2, u3 = me.dynamicsymbols("u1 u2 u3")
    m, r, I1, I3, g = sm.symbols("m r I1 I3 g")
    N = me.ReferenceFrame("N")
    Y = N.orientnew("Y", "Axis", (yaw, N.z))
    L = Y.orientnew("L", "Axis", (lean, Y.x))
    R = L.orientnew("R", "Axis", (spin, L.y))
    w_from_rates = R.ang_vel_in(N)
    R.set_ang_vel(N, u1 * L.x + u2 * L.y + u3 * L.z)
    contact = me.Point("C")
    contact.set_vel(N, 0)                                   # rolling: the disc's contact point is at rest
    centre = contact.locatenew("D", r * L.z)
    centre.v2pt_theory(contact, N, R)
    body = me.RigidBody("disc", centre, R, m, (me.inertia(L, I1, I3, I1), centre))
    kd = [(R.ang_vel_in(N) - w_from_rates).dot(e) for e in (L.x, L.y, L.z)]
    kd += [x.diff(t) - r * spin.diff(t) * sm.cos(yaw), y.diff(t) - r * spin.diff(t) * sm.sin(yaw)]
    q, u = [x, y, yaw, lean, spin], [u1, u2, u3]
    kane = me.KanesMethod(N, q_ind=q, u_ind=u, kd_eqs=kd)
    kane.kanes_equations([body], [(centre, -m * g * N.z)])
    return kane, q, u, [m, r, I1, I3, g], t

def numpy_rhs():
    """rhs(t, y, p) for solve_ivp, y = [x, y, yaw, lean, spin, u1, u2, u3], p = [m, r, I1, I3, g]."""
    kane, q, u, params, t = derive()
    qdot = sm.Matrix([kane.kindiffdict()[qi.diff(t)] for qi in q])
    terms = sm.lambdify((q, u, params), [kane.mass_matrix, kane.forcing, qdot], cse=True)

    def rhs(t_, y, p):
        M, f, qd = terms(y[:5], y[5:], p)
        return np.concatenate([np.ravel(qd), np.linalg.solve(M, np.ravel(f))])

    return rhs

def solve(rhs, y0, p, ts, rtol, atol, method):
    return solve_ivp(rhs, (ts[0], ts[-1]), y0, method=method, t_eval=ts, rtol=rtol, atol=atol, args=(p,))
'''
"""A SymPy/SciPy script, as a user writes it from SymPy's example; run by `exec` here and in fresh processes."""


def sympy_namespace() -> dict:
    ns: dict = {}
    exec(compile(DISC_SYMPY, "<disc sympy pipeline>", "exec"), ns)
    return ns


def jax_source(ns: dict) -> str:
    """Python source of `rhs(t, y, p)` (diffrax's signature) computing SymPy's Kane equations with `jnp`."""
    import sympy as sm
    from sympy.printing.numpy import JaxPrinter

    kane, q, u, prm, t = ns["derive"]()
    qdot = sm.Matrix([kane.kindiffdict()[qi.diff(t)] for qi in q])
    names = {s: sm.Symbol(f"q_{i}") for i, s in enumerate(q)}
    names.update({s: sm.Symbol(f"u_{i}") for i, s in enumerate(u)})
    names.update({s: sm.Symbol(f"p_{i}") for i, s in enumerate(prm)})
    o = len(u)
    exprs = [e.xreplace(names) for e in (*kane.mass_matrix, *kane.forcing, *qdot)]
    subs, red = sm.cse(exprs)
    pr = JaxPrinter()
    lines = [
        "import jax",
        "import jax.numpy as jnp",
        "",
        "",
        "def rhs(t, y, p):",
        f"    {', '.join(f'q_{i}' for i in range(len(q)))}, = y[:{len(q)}]",
        f"    {', '.join(f'u_{i}' for i in range(o))}, = y[{len(q)}:]",
        f"    {', '.join(f'p_{i}' for i in range(len(prm)))}, = p",
    ]
    lines += [f"    {s} = {pr.doprint(e)}" for s, e in subs]
    M, f, g = red[: o * o], red[o * o : o * o + o], red[o * o + o :]
    rows = ", ".join("[" + ", ".join(pr.doprint(M[i * o + k]) for k in range(o)) + "]" for i in range(o))
    lines += [
        f"    M = jnp.array([{rows}])",
        f"    f = jnp.array([{', '.join(pr.doprint(e) for e in f)}])",
        f"    qd = jnp.array([{', '.join(pr.doprint(e) for e in g)}])",
        "    return jnp.concatenate([qd, jnp.linalg.solve(M, f)])",
    ]
    return "\n".join(lines) + "\n"


def load_source(src: str):
    ns: dict = {}
    exec(compile(src, "<generated disc rhs>", "exec"), ns)
    return ns["rhs"]


class Disc:
    """The rolling-disc case: initial state, parameters, report times, SymPy's right-hand sides, the reference."""

    def __init__(self, ns: dict):
        self.p = DS.default_params()
        self.q0, self.u0 = DS.initial_state(self.p, LEAN, YAW_RATE, LEAN_RATE)
        self.ts = jnp.linspace(0.0, T_END, N_REPORT)
        self.ts_np = np.asarray(self.ts)
        self.P = np.array([float(self.p[k]) for k in KEYS])
        self.y0 = np.r_[np.asarray(self.q0), np.asarray(self.u0[:3])]
        self.ns = ns
        self.np_rhs = ns["numpy_rhs"]()
        self.src = jax_source(ns)
        self.hand_rhs = load_source(self.src)
        self.y_ref = self.reference(self.P)

    def reference(self, P) -> np.ndarray:
        s = self.ns["solve"](self.np_rhs, self.y0, np.asarray(P), self.ts_np, REF_RTOL, REF_ATOL, "DOP853")
        if s.status != 0:
            raise RuntimeError(f"reference solve failed: {s.message}")
        return s.y.T

    def loss(self, P) -> float:
        """The gradient's loss from the reference: the sum of the final coordinates."""
        return float(np.sum(self.reference(P)[-1, :5]))

    def error(self, q, u) -> float:
        """Largest absolute error over the report times of q (5) and u1, u2, u3."""
        y = np.column_stack([np.asarray(q), np.asarray(u)[:, :3]])
        if y.shape != self.y_ref.shape or not np.all(np.isfinite(y)):
            return float("nan")
        return float(np.max(np.abs(y - self.y_ref)))


def _hand_solver(case: Disc):
    @jax.jit
    def solve(y0, P, rtol, atol):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(case.hand_rhs),
            diffrax.Tsit5(),
            case.ts[0],
            case.ts[-1],
            None,
            y0,
            args=P,
            saveat=diffrax.SaveAt(ts=case.ts),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            max_steps=100_000,
        )
        return sol.ys, sol.stats["num_steps"]

    return solve


def contenders(case: Disc) -> dict:
    """name -> (rtol -> (zero-argument solve, (result -> (error, steps))))."""
    mech = DS.mechanism()
    hand = _hand_solver(case)
    y0, P = jnp.asarray(case.y0), jnp.asarray(case.P)

    def jaxnh(method):
        def at(rtol):
            def call():
                return jax.block_until_ready(
                    nh.simulate(mech, case.p, case.q0, case.u0, case.ts, method=method, rtol=rtol, atol=rtol / 100)
                )

            return call, lambda s: (case.error(s.q, s.u), float(s.stats["num_steps"]))

        return at

    def scipy(method):
        def at(rtol):
            def call():
                return case.ns["solve"](case.np_rhs, case.y0, case.P, case.ts_np, rtol, rtol / 100, method)

            return call, lambda s: (
                case.error(s.y.T[:, :5], s.y.T[:, 5:]) if s.status == 0 else float("nan"),
                float(s.nfev) / (6 if method == "RK45" else 12),
            )

        return at

    def hand_at(rtol):
        def call():
            return jax.block_until_ready(hand(y0, P, rtol, rtol / 100))

        return call, lambda s: (case.error(np.asarray(s[0])[:, :5], np.asarray(s[0])[:, 5:]), float(s[1]))

    return {
        "jaxnh simulate (lagrange, default)": jaxnh("lagrange"),
        "jaxnh simulate (appell)": jaxnh("appell"),
        "SciPy RK45, lambdified SymPy": scipy("RK45"),
        "SciPy DOP853, lambdified SymPy": scipy("DOP853"),
        "hand JAX, diffrax Tsit5": hand_at,
    }


JAXNH, APPELL, RK45, DOP853, HAND = (
    "jaxnh simulate (lagrange, default)",
    "jaxnh simulate (appell)",
    "SciPy RK45, lambdified SymPy",
    "SciPy DOP853, lambdified SymPy",
    "hand JAX, diffrax Tsit5",
)


def match(at, target: float, cache: dict) -> dict:
    """The loosest grid tolerance whose solve reaches `target` (error ≤ target): a walk on GRID from
    rtol = target, looser while it holds, tighter until it does. `cache`: rtol -> (error, steps)."""

    def err(i):
        if GRID[i] not in cache:
            call, measure = at(GRID[i])
            cache[GRID[i]] = measure(call())
        return cache[GRID[i]][0]

    i = min(range(len(GRID)), key=lambda k: abs(np.log(GRID[k] / target)))
    ok = lambda e: bool(np.isfinite(e)) and e <= target  # noqa: E731
    if ok(err(i)):
        while i > 0 and ok(err(i - 1)):
            i -= 1
    else:
        while i + 1 < len(GRID) and not ok(err(i)):
            i += 1
        if not ok(err(i)):
            return dict(rtol=None, error=None, steps=None, tried=len(cache))
    e, steps = cache[GRID[i]]
    return dict(rtol=GRID[i], error=e, steps=steps, tried=len(cache))


def steady(case: Disc, targets, quick: bool) -> dict:
    cons = contenders(case)
    caches = {k: {} for k in cons}
    out = {}
    for target in targets:
        chosen = {k: match(at, target, caches[k]) for k, at in cons.items()}
        for k, c in chosen.items():
            C.log(f"[speeds] disc, target {target:.0e}: {k}: rtol {c['rtol']}, error {c['error']}, steps {c['steps']}")
        calls = {k: cons[k](c["rtol"])[0] for k, c in chosen.items() if c["rtol"] is not None}
        many = {k: C.repeat(fn, 0.05) for k, fn in calls.items()}
        T = C.interleave({k: m for k, (m, _) in many.items()}, rounds=5 if quick else 9, budget=20 if quick else 90)
        per = {k: np.asarray(T[k]["cpu"]) / n for k, (_, n) in many.items()}
        row = {}
        for k, c in chosen.items():
            row[k] = dict(c, cpu=C.median(per[k]) if k in per else None, rounds=len(per.get(k, [])))
        scipy = [k for k in (RK45, DOP853) if k in per]
        better = min(scipy, key=lambda k: C.median(per[k])) if scipy else None
        ratios = {}
        if better and JAXNH in per:
            ratios["SciPy's better / jaxnh"] = C.paired_ratio(per[better], per[JAXNH])
        for k in (APPELL, HAND):
            if better and k in per:
                ratios[f"SciPy's better / {k}"] = C.paired_ratio(per[better], per[k])
        if JAXNH in per and HAND in per:
            ratios["jaxnh / hand JAX"] = C.paired_ratio(per[JAXNH], per[HAND])
        out[f"{target:.0e}"] = dict(target=target, rows=row, better_scipy=better, ratios=ratios)
        C.log(f"[speeds] disc, target {target:.0e}: better SciPy {better}; {ratios}")
    return out


JAXNH_CHILD = """
import jax, jax.numpy as jnp, numpy as np
import jaxnh as nh
from jaxnh.models import disc_speeds
{imported}
p = disc_speeds.default_params()
q0, u0 = disc_speeds.initial_state(p, {lean}, {yaw_rate}, {lean_rate})
ts = jnp.linspace(0.0, {T}, {n})
mech = disc_speeds.mechanism()
if {gradient}:
    loss = lambda p: jnp.sum(nh.simulate(mech, p, q0, u0, ts, rtol={rtol}, atol={atol}).q[-1])
    g = jax.grad(loss)(p)
    OUT["grad"] = np.array([float(g[k]) for k in {keys}])
else:
    sol = nh.simulate(mech, p, q0, u0, ts, rtol={rtol}, atol={atol})
    OUT.update(q=np.asarray(sol.q), u=np.asarray(sol.u))
"""

HAND_CHILD = """
import jax, jax.numpy as jnp, numpy as np, diffrax
jax.config.update("jax_enable_x64", True)
import sys
sys.path.insert(0, {folder!r})
from disc_rhs import rhs
{imported}

@jax.jit
def solve(y0, args):
    ts = jnp.linspace(0.0, {T}, {n})
    sol = diffrax.diffeqsolve(diffrax.ODETerm(rhs), diffrax.Tsit5(), 0.0, {T}, None, y0, args=args,
                              saveat=diffrax.SaveAt(ts=ts),
                              stepsize_controller=diffrax.PIDController(rtol={rtol}, atol={atol}))
    return sol.ys

OUT["ys"] = np.asarray(solve(jnp.array({y0}), jnp.array({P})))
"""

SYMPY_CHILD = """
import numpy as np
{pipeline}
{imported}
rhs = numpy_rhs()
s = solve(rhs, np.array({y0}), np.array({P}), np.linspace(0.0, {T}, {n}), {rtol}, {atol}, {method!r})
OUT.update(ys=s.y.T, message=s.message)
"""


def first_answers(case: Disc, chosen: dict, better: str, repeats: int) -> dict:
    folder = tempfile.mkdtemp(prefix="jaxnh-bench-disc-")
    with open(os.path.join(folder, "disc_rhs.py"), "w") as f:
        f.write(case.src)
    rt = {k: chosen[k]["rtol"] for k in (JAXNH, HAND, better)}
    common = dict(imported=C.IMPORTED, T=T_END, n=N_REPORT)
    jx = dict(common, lean=LEAN, yaw_rate=YAW_RATE, lean_rate=LEAN_RATE, keys=list(KEYS))
    rng = np.random.default_rng(0)
    direction = case.P * rng.choice([-1.0, 1.0], case.P.size)
    fd = {}

    def grad_error(o):
        if "v" not in fd:  # central differences at h and h/2, Richardson-extrapolated (truncation O(h⁴))

            def D(h):
                return (case.loss(case.P + h * direction) - case.loss(case.P - h * direction)) / (2 * h)

            h = 2e-4
            fd["v"] = (4 * D(h / 2) - D(h)) / 3
        return abs(float(np.asarray(o["grad"]) @ direction) - fd["v"]) / max(abs(fd["v"]), 1e-300)

    def ys_error(o):
        ys = np.asarray(o["ys"])
        return case.error(ys[:, :5], ys[:, 5:])

    kinds = {
        "jaxnh": (
            JAXNH_CHILD.format(**jx, gradient=False, rtol=rt[JAXNH], atol=rt[JAXNH] / 100),
            lambda o: case.error(o["q"], o["u"]),
        ),
        "jaxnh, first gradient": (
            JAXNH_CHILD.format(**jx, gradient=True, rtol=rt[JAXNH], atol=rt[JAXNH] / 100),
            grad_error,
        ),
        "hand JAX (diffrax Tsit5)": (
            HAND_CHILD.format(
                **common, folder=folder, rtol=rt[HAND], atol=rt[HAND] / 100, y0=list(case.y0), P=list(case.P)
            ),
            ys_error,
        ),
        f"SymPy + SciPy ({'RK45' if better == RK45 else 'DOP853'})": (
            SYMPY_CHILD.format(
                **common,
                pipeline=DISC_SYMPY,
                rtol=rt[better],
                atol=rt[better] / 100,
                y0=list(case.y0),
                P=list(case.P),
                method="RK45" if better == RK45 else "DOP853",
            ),
            ys_error,
        ),
    }
    rows = {k: dict(wall=[], cpu=[], imports=[], error=None, note="") for k in kinds}
    for r in range(repeats):
        for k, (code, err) in kinds.items():
            row = rows[k]
            try:
                o = C.fresh(code, {"JAXNH_CACHE_DIR": C.cache_dirs()[0]})
            except RuntimeError as ex:
                row["note"] = str(ex).strip().splitlines()[-1][:300]
                C.log(f"[speeds] first answer, {k}: FAILED {row['note']}")
                continue
            row["wall"].append(o["wall"])
            row["cpu"].append(o["cpu"])
            row["imports"].append(o["import"])
            if row["error"] is None:
                row["error"] = err(o)
            C.log(f"[speeds] first answer, {k}: {o['wall']:.2f} s wall, {o['cpu']:.2f} s CPU, error {row['error']:.1e}")
    for row in rows.values():
        for x in ("wall", "cpu", "imports"):
            row[f"{x}_median"] = C.median(row[x]) if row[x] else None
    J, G, H = rows["jaxnh"], rows["jaxnh, first gradient"], rows["hand JAX (diffrax Tsit5)"]
    ratios = {}
    if J["cpu"] and H["cpu"]:
        ratios["jaxnh / hand (CPU)"] = C.paired_ratio(J["cpu"], H["cpu"])
        ratios["jaxnh / hand (wall)"] = C.paired_ratio(J["wall"], H["wall"])
    if J["cpu"] and G["cpu"]:
        ratios["gradient / answer (CPU)"] = C.paired_ratio(G["cpu"], J["cpu"])
        ratios["gradient / answer (wall)"] = C.paired_ratio(G["wall"], J["wall"])
    C.log(f"[speeds] first answers: {ratios}")
    return dict(rows=rows, ratios=ratios, rtols={k: rt[k] for k in rt}, repeats=repeats)


def field_cost(case: Disc, quick: bool) -> dict:
    """CPU time (s) per step of `diffrax.Tsit5` at a constant step (1000 steps of 1 ms, jitted) with
    jaxnh's fields (`nh.ode`, Lagrange's and Appell's) and with the hand-written right-hand side: the
    equations' own cost, without step-size control or reports; and SciPy's lambdified NumPy
    right-hand side per call (a Tsit5 step is six calls)."""
    n = 1000
    terms = {}
    for method in ("lagrange", "appell"):
        o = nh.ode(DS.mechanism(), case.p, case.q0, case.u0, 0.0, method=method)
        terms[f"jaxnh {method}"] = (o.term, o.solver(diffrax.Tsit5()), o.y0, o.args)
    terms["hand JAX"] = (diffrax.ODETerm(case.hand_rhs), diffrax.Tsit5(), jnp.asarray(case.y0), jnp.asarray(case.P))
    calls = {}
    for k, (term, solver, y0, args) in terms.items():

        def solve(y0, args, term=term, solver=solver):
            return diffrax.diffeqsolve(
                term,
                solver,
                0.0,
                n * 1e-3,
                1e-3,
                y0,
                args=args,
                saveat=diffrax.SaveAt(t1=True),
                stepsize_controller=diffrax.ConstantStepSize(),
                max_steps=n,
            ).ys

        f = jax.jit(solve)
        calls[k] = lambda f=f, y0=y0, args=args: jax.block_until_ready(f(y0, args))

    def scipy_calls():
        for _ in range(n // 10):
            case.np_rhs(0.0, case.y0, case.P)

    calls["SciPy (lambdified NumPy), per call"] = scipy_calls
    counts = {k: (n // 10 if k.startswith("SciPy") else n) for k in calls}
    many = {k: C.repeat(fn, 0.05) for k, fn in calls.items()}
    T = C.interleave({k: m for k, (m, _) in many.items()}, rounds=5 if quick else 9, budget=10 if quick else 30)
    out = {k: C.median(np.asarray(T[k]["cpu"]) / (m * counts[k])) for k, (_, m) in many.items()}
    C.log(f"[speeds] disc, CPU per constant Tsit5 step (SciPy: per call): {out}")
    return out


def reference_check(case: Disc) -> float:
    """Largest difference between the reference and `jaxnh.models.disc` (q̇) at rtol 1e-12 (q and u1, u2, u3)."""
    q0, qd0 = disc.steady_state(LEAN, YAW_RATE, case.p)
    qd0 = qd0.at[3].add(LEAN_RATE)
    sol = nh.simulate(disc.mechanism(), case.p, q0, qd0, case.ts, rtol=1e-12, atol=1e-14)
    u = jax.vmap(DS.speeds_from_rates, (0, 0, None))(sol.q, sol.qd, case.p)
    return case.error(sol.q, u)


# --------------------------------------------------------------------------- 2. the ball on a turntable

TT_RTOL, TT_ATOL = 1e-10, 1e-12


def omega_zyx(q: jax.Array, qd: jax.Array) -> jax.Array:
    """Space angular velocity (rad/s) of the orientation Rz(ψ) Ry(θ) Rx(φ), q = (x, y, ψ, θ, φ)."""
    return euler_rates_matrix(q) @ qd[2:]


def euler_rates_matrix(q: jax.Array) -> jax.Array:
    """W (3, 3) with ω = W (ψ̇, θ̇, φ̇): ψ̇ ẑ + θ̇ Rz(ψ) ŷ + φ̇ Rz(ψ) Ry(θ) x̂; singular at θ = ±π/2."""
    cps, sps, cth, sth = jnp.cos(q[2]), jnp.sin(q[2]), jnp.cos(q[3]), jnp.sin(q[3])
    z = jnp.zeros_like(cps)
    return jnp.array([[z, -sps, cps * cth], [z, cps, sps * cth], [z + 1, z, -sth]])


def euler_kinetic(q, qd, t, p):
    """T = ½ m (ẋ² + ẏ²) + ½ k² m a² |ω|², J."""
    w = omega_zyx(q, qd)
    return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * p["k2"] * p["m"] * p["a"] ** 2 * jnp.sum(w**2)


def euler_rolling(q, qd, t, p):
    """Slip velocity of the contact point relative to the table (2,), m/s (as `turntable.constraint`)."""
    w, a, W = omega_zyx(q, qd), p["a"], p["Omega"]
    return jnp.stack([qd[0] - a * w[1] + W * q[1], qd[1] + a * w[0] - W * q[0]])


def euler_mechanism() -> nh.Mechanism:
    """The ball on the turntable in ZYX Euler angles, q = (x, y, yaw, pitch, roll), written in q̇."""
    return nh.Mechanism(euler_kinetic, constraints=euler_rolling, names=("x", "y", "yaw", "pitch", "roll"))


def turntable_states(p, pitch: float):
    """The issue's state (centre at (0.5, 0) m moving at 0.2 m/s along y, spinning at 3 rad/s) with the
    ball turned by `pitch` about y: (q0, u0) for the quaternion model, (q0, q̇0) for the Euler one."""
    q0, u0 = TT.initial_state(p)
    e = quaternion_from_axis_angle(jnp.array([0.0, 1.0, 0.0]), pitch)
    qe = jnp.array([q0[0], q0[1], 0.0, pitch, 0.0])
    rates = jnp.linalg.solve(euler_rates_matrix(qe), u0[2:])
    return (jnp.concatenate([q0[:2], e]), u0), (qe, jnp.concatenate([u0[:2], rates]))


def _rot_zyx(q):
    return rot_z(q[2]) @ rot_y(q[3]) @ rot_x(q[4])


def turntable(quick: bool) -> dict:
    p = TT.default_params()
    quat_mech, euler_mech = TT.mechanism(), euler_mechanism()
    out = {"rtol": TT_RTOL, "atol": TT_ATOL, "ref_rtol": 1e-12}

    def run(kind, state, ts, max_steps=100_000, rtol=TT_RTOL):
        q0, v0 = state
        mech = quat_mech if kind == "quaternion" else euler_mech
        return lambda: jax.block_until_ready(
            nh.simulate(mech, p, q0, v0, ts, rtol=rtol, atol=rtol / 100, throw=False, max_steps=max_steps)
        )

    def describe(sol, ts, x, y, R_ref):
        """Outcome, steps, the centre's error (m) against the closed form and the orientation's (Frobenius
        norm of the rotation matrices' difference) against the reference, over the times reached."""
        q = np.asarray(sol.q)
        ok = np.all(np.isfinite(q), axis=1)
        reached = float(np.asarray(ts)[ok][-1]) if ok.any() else float(ts[0])
        err = np.hypot(q[ok, 0] - np.asarray(x)[ok], q[ok, 1] - np.asarray(y)[ok])
        euler = q.shape[1] == 5
        R = jax.vmap(_rot_zyx if euler else lambda q: rotation_from_quaternion(q[2:]))(jnp.asarray(q[ok]))
        row = dict(
            success=bool(sol.success),
            message=str(sol.message)[:120],
            steps=int(sol.stats["num_steps"]),
            accepted=int(sol.stats.get("num_accepted_steps", sol.stats["num_steps"])),
            reached=reached,
            centre_error=float(err.max()) if err.size else None,
            orientation_error=float(jnp.max(jnp.linalg.norm(R - R_ref[ok], axis=(1, 2)))) if err.size else None,
        )
        if euler:
            c = np.abs(np.cos(q[ok, 3]))
            row["min_cos_pitch"] = float(c.min()) if c.size else None
            row["at"] = float(np.asarray(ts)[ok][np.argmin(c)]) if c.size else None
        else:
            row["unit_norm_error"] = float(np.max(np.abs(np.linalg.norm(q[ok, 2:], axis=1) - 1.0)))
        return row

    def reference(state, ts):
        sol = run("quaternion", state, ts, max_steps=1_000_000, rtol=out["ref_rtol"])()
        if not sol.success:
            raise RuntimeError(f"turntable reference failed: {sol.message}")
        return jax.vmap(rotation_from_quaternion)(sol.q[:, 2:])

    # A: the state (identity orientation), long run
    t_long = 500.0 if quick else 2000.0
    ts = jnp.linspace(0.0, t_long, int(t_long) + 1)
    quat0, euler0 = turntable_states(p, 0.0)
    x, y = TT.closed_form(p, ts, *quat0)
    R_ref = reference(quat0, ts)
    calls = {
        "quaternion": run("quaternion", quat0, ts),
        "Euler ZYX, default max_steps": run("euler", euler0, ts),
        "Euler ZYX, max_steps 10⁶": run("euler", euler0, ts, 1_000_000),
    }
    sols = {k: fn() for k, fn in calls.items()}  # (compiles)
    rows = {}
    for k, s in sols.items():
        rows[k] = describe(s, ts, x, y, R_ref)
        C.log(f"[speeds] turntable {t_long:.0f} s, {k}: {rows[k]}")
    T = C.interleave(calls, rounds=1 if quick else 3)
    for k in rows:
        rows[k]["cpu"] = C.median(T[k]["cpu"])
    out["long"] = dict(t_end=t_long, rows=rows)

    # B: starts at a distance δ from gimbal lock (pitch π/2 − δ)
    ts = jnp.linspace(0.0, 200.0, 201)
    near = {}
    for d in (1e-2, 1e-4) if quick else (1e-2, 1e-4, 1e-6):
        quat0, euler0 = turntable_states(p, float(np.pi / 2 - d))
        x, y = TT.closed_form(p, ts, *quat0)
        R_ref = reference(quat0, ts)
        sq, se = run("quaternion", quat0, ts)(), run("euler", euler0, ts)()
        near[f"{d:g}"] = dict(delta=d, quaternion=describe(sq, ts, x, y, R_ref), euler=describe(se, ts, x, y, R_ref))
        C.log(f"[speeds] turntable near the lock, δ = {d:g}: {near[f'{d:g}']}")
    out["near_lock"] = dict(t_end=200.0, rows=near)
    return out


# --------------------------------------------------------------------------- main


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one target error, one repeat, shorter turntable runs")
    ap.add_argument("--repeats", type=int, default=None, help="fresh processes per contender (default 5, quick 1)")
    a = ap.parse_args(argv)
    R = a.repeats or (1 if a.quick else 5)
    t0 = time.perf_counter()
    case = Disc(sympy_namespace())
    check = reference_check(case)
    C.log(f"[speeds] reference ready; jaxnh.models.disc (q̇) at rtol 1e-12 differs from it by {check:.1e}")
    targets = (1e-6,) if a.quick else (1e-6, 1e-9)
    st = steady(case, targets, a.quick)
    fc = field_cost(case, a.quick)
    first = st[f"{targets[0]:.0e}"]
    fa = first_answers(case, first["rows"], first["better_scipy"], R)
    tt = turntable(a.quick)
    C.save(
        "speeds",
        dict(
            disc=dict(
                steady=st,
                first_answers=fa,
                field_cost=fc,
                reference_check=check,
                lean=LEAN,
                yaw_rate=YAW_RATE,
                lean_rate=LEAN_RATE,
                t_end=T_END,
                n_report=N_REPORT,
                spin=float(DS.steady_spin(LEAN, YAW_RATE, case.p)),
            ),
            turntable=tt,
            repeats=R,
            quick=a.quick,
            seconds=time.perf_counter() - t0,
        ),
    )
    C.log(f"[speeds] done in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
