"""What it costs to get the Whipple bicycle's equations: jaxnh (autodiff) against SymPy (KanesMethod).

Run from the repository root:

    python benchmarks/bicycle_cost.py              # jaxnh, then SymPy if installed
    python benchmarks/bicycle_cost.py --no-sympy   # jaxnh only
    python benchmarks/bicycle_cost.py --sympy-timeout 1800
    python benchmarks/bicycle_cost.py --sympy-numeric   # SymPy with the benchmark numbers substituted first

Measured, wall clock, in this process (first calls include tracing and XLA
compilation; the machine's load matters, so the script also prints CPU time):

1. jaxnh: from the model definition (`jaxnh.models.bicycle`: four rigid bodies,
   one holonomic and four nonholonomic contact constraints) to the 4×4
   lean/steer state matrix at 5 m/s — first call and a repeat call — and to
   the matrices at 101 speeds in one vmapped call.
2. jaxnh: a 5 s nonlinear simulation (Lagrange's equations with multipliers,
   8 coordinates, Tsit5, rtol 1e-8), first call and repeat.
3. SymPy (the `bench` extra; skipped if absent): the same model, coordinates
   and geometry written for `sympy.physics.mechanics.KanesMethod`: time to
   derive Kane's equations, to linearise them about upright running
   (`KanesMethod.linearize`), and to evaluate the state matrix at the
   benchmark parameters; its eigenvalues at 5 m/s are compared with jaxnh's.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time

import numpy as np


def clock():
    return time.perf_counter(), time.process_time()


def since(start):
    w, c = clock()
    return w - start[0], c - start[1]


def jaxnh_costs():
    import jax
    import jax.numpy as jnp

    import jaxnh as nh
    from jaxnh.models import bicycle

    out = {}
    p = bicycle.default_params()
    start = clock()
    lin = jax.jit(bicycle.linear_lean_steer)            # the model is defined at this point
    A = np.asarray(lin(5.0, p))
    out["state matrix, first call (trace + compile + run)"] = since(start)
    start = clock()
    A = np.asarray(lin(5.0, p))
    out["state matrix, repeat call"] = since(start)
    start = clock()
    batch = bicycle.linearized_speeds(jnp.linspace(0.0, 10.0, 101), p)
    jax.block_until_ready(batch.A)
    out["101 speeds in one vmapped call, first (cheap XLA options)"] = since(start)
    start = clock()
    jax.block_until_ready(bicycle.linearized_speeds(jnp.linspace(0.0, 10.0, 101) + 0.01, p).A)
    out["101 speeds, repeat"] = since(start)

    q, qd = bicycle.upright(5.0, p)
    qd = qd.at[bicycle.ROLL].set(0.5)
    ts = jnp.linspace(0.0, 5.0, 101)
    mech = bicycle.mechanism("lagrange")

    def simulate():
        sol = nh.simulate(mech, p, q, qd, ts, method="lagrange", independent=bicycle.INDEPENDENT, rtol=1e-8, atol=1e-10)
        jax.block_until_ready(sol.q)
        return sol

    start = clock()
    sol = simulate()
    out["5 s nonlinear simulation, first call"] = since(start)
    start = clock()
    sol = simulate()
    out["5 s nonlinear simulation, repeat"] = since(start)
    out["_steps"] = int(sol.stats["num_steps"])
    out["_eig5"] = np.sort_complex(np.linalg.eigvals(A))
    return out


# --- SymPy: the same bicycle for KanesMethod -----------------------------------------------


def sympy_costs(queue, numeric=False):
    """Kane's equations, linearisation and evaluation in SymPy; results go to `queue` phase by phase.

    `numeric=True` puts the benchmark's numbers (and v = 5 m/s) into the model
    from the start, which spares SymPy the symbolic parameters.
    """
    import sympy as sm
    import sympy.physics.mechanics as me

    from jaxnh.models.bicycle import BENCHMARK

    res = {}
    start = clock()
    q = me.dynamicsymbols("q1:9")  # x, y, yaw, roll, pitch, rear wheel, steer, front wheel
    u = me.dynamicsymbols("u1:9")
    names = ["w", "c", "lam", "g", "rR", "mR", "IRxx", "IRyy", "xB", "zB", "mB", "IBxx", "IByy", "IBzz", "IBxz",
             "xH", "zH", "mH", "IHxx", "IHyy", "IHzz", "IHxz", "rF", "mF", "IFxx", "IFyy"]
    s = dict(zip(names, sm.symbols(names)))
    if numeric:
        s = {k: sm.Float(BENCHMARK[k]) for k in names}
    N = me.ReferenceFrame("N")  # x forward, y right, z down
    A = N.orientnew("A", "Axis", (q[2], N.z))
    L = A.orientnew("L", "Axis", (q[3], A.x))
    C = L.orientnew("C", "Axis", (q[4], L.y))
    Rw = C.orientnew("Rw", "Axis", (q[5], C.y))
    E = C.orientnew("E", "Axis", (q[6], sm.sin(s["lam"]) * C.x + sm.cos(s["lam"]) * C.z))
    Fw = E.orientnew("Fw", "Axis", (q[7], E.y))
    O = me.Point("O")
    O.set_vel(N, 0)
    P = O.locatenew("P", q[0] * N.x + q[1] * N.y)                       # rear contact
    Rc = P.locatenew("Rc", -s["rR"] * L.z)                               # rear hub
    Bc = Rc.locatenew("Bc", s["xB"] * C.x + (s["zB"] + s["rR"]) * C.z)  # rear frame mass centre
    S = Rc.locatenew("S", (s["w"] + s["c"]) * C.x + s["rR"] * C.z)      # steer axis meets the ground
    Hc = S.locatenew("Hc", (s["xH"] - s["w"] - s["c"]) * E.x + s["zH"] * E.z)
    Fc = S.locatenew("Fc", -s["c"] * E.x - s["rF"] * E.z)               # front hub
    down = E.y.cross(N.z.cross(E.y))                                     # in the wheel plane, towards the ground
    Fn = Fc.locatenew("Fn", s["rF"] * down / sm.sqrt(down.dot(down)))    # front contact
    qd_to_u = dict(zip([qi.diff(me.dynamicsymbols._t) for qi in q], u))
    for frame in (A, L, C, Rw, E, Fw):
        frame.set_ang_vel(N, frame.ang_vel_in(N).subs(qd_to_u))
    for pt in (P, Rc, Bc, S, Hc, Fc):
        pt.set_vel(N, pt.pos_from(O).dt(N).subs(qd_to_u))
    holonomic = Fn.pos_from(O).dot(N.z)
    v_rear = Rc.vel(N) + Rw.ang_vel_in(N).cross(P.pos_from(Rc))
    v_front = Fc.vel(N) + Fw.ang_vel_in(N).cross(Fn.pos_from(Fc))
    gdot = holonomic.diff(me.dynamicsymbols._t).subs(qd_to_u)
    constraints = [v_rear.dot(N.x), v_rear.dot(N.y), v_front.dot(N.x), v_front.dot(N.y), gdot]
    bodies = [
        me.RigidBody("R", Rc, Rw, s["mR"], (me.inertia(Rw, s["IRxx"], s["IRyy"], s["IRxx"]), Rc)),
        me.RigidBody("B", Bc, C, s["mB"], (me.inertia(C, s["IBxx"], s["IByy"], s["IBzz"], 0, 0, s["IBxz"]), Bc)),
        me.RigidBody("H", Hc, E, s["mH"], (me.inertia(E, s["IHxx"], s["IHyy"], s["IHzz"], 0, 0, s["IHxz"]), Hc)),
        me.RigidBody("F", Fc, Fw, s["mF"], (me.inertia(Fw, s["IFxx"], s["IFyy"], s["IFxx"]), Fc)),
    ]
    loads = [(b.masscenter, b.mass * s["g"] * N.z) for b in bodies]
    KM = me.KanesMethod(
        N, q_ind=[q[i] for i in (0, 1, 2, 3, 5, 6, 7)], u_ind=[u[3], u[5], u[6]],
        kd_eqs=[qi.diff() - ui for qi, ui in zip(q, u)],
        q_dependent=[q[4]], configuration_constraints=[holonomic],
        u_dependent=[u[0], u[1], u[2], u[4], u[7]], velocity_constraints=constraints,
    )
    KM.kanes_equations(bodies, loads)
    res["derive Kane's equations"] = since(start)
    queue.put(dict(res))

    start = clock()
    v = sm.Float(5.0) if numeric else sm.Symbol("v")
    op = {qi: 0 for qi in q}
    op.update({ui: 0 for ui in u})
    op.update({u[0]: v, u[5]: -v / s["rR"], u[7]: -v / s["rF"]})
    op.update({ui.diff(): 0 for ui in u})
    Amat = KM.linearize(op_point=op, A_and_B=True, simplify=False)[0]
    res["linearize (KanesMethod.linearize)"] = since(start)
    queue.put(dict(res))

    start = clock()
    num = {} if numeric else {s[k]: BENCHMARK[k] for k in names}
    if not numeric:
        num[v] = 5.0
    A5 = np.array(sm.N(Amat.subs(num)).tolist(), dtype=complex).real
    # states: x, y, yaw, roll, rear, steer, front, u_roll, u_rear, u_steer
    idx = [3, 5, 7, 9]
    res["evaluate at the benchmark parameters, v = 5 m/s"] = since(start)
    res["_eig5"] = np.sort_complex(np.linalg.eigvals(A5[np.ix_(idx, idx)]))
    queue.put(dict(res))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-sympy", action="store_true")
    ap.add_argument("--no-jaxnh", action="store_true", help="SymPy only")
    ap.add_argument("--sympy-timeout", type=float, default=1200.0, help="seconds before giving up on SymPy")
    ap.add_argument("--sympy-numeric", action="store_true",
                    help="give SymPy the benchmark numbers from the start instead of symbolic parameters")
    args = ap.parse_args()
    print(f"CPU cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}")
    jx = {} if args.no_jaxnh else jaxnh_costs()
    if jx:
        print("jaxnh (autodiff, jit):                                  wall s    CPU s")
        for k, (w, c) in ((k, v) for k, v in jx.items() if not k.startswith("_")):
            print(f"  {k:<54}{w:8.2f} {c:8.2f}")
        print(f"  (nonlinear run: {jx['_steps']} steps; eigenvalues at 5 m/s {jx['_eig5']})")
    if args.no_sympy:
        return
    try:
        import sympy  # noqa: F401
    except ImportError:
        print("SymPy not installed (pip install 'jaxnh[bench]'): skipping the KanesMethod comparison")
        return
    queue = mp.get_context("spawn").Queue()
    proc = mp.get_context("spawn").Process(target=sympy_costs, args=(queue, args.sympy_numeric))
    proc.start()
    proc.join(args.sympy_timeout)
    res = {}
    while not queue.empty():
        res = queue.get()
    if proc.is_alive():
        proc.terminate()
        print(f"SymPy did not finish within {args.sympy_timeout:.0f} s (wall); phases completed:")
    else:
        kind = "numeric parameters" if args.sympy_numeric else "symbolic parameters"
        print(f"SymPy (KanesMethod, same model, {kind}):   wall s    CPU s")
    for k, (w, c) in ((k, v) for k, v in res.items() if not k.startswith("_")):
        print(f"  {k:<54}{w:8.2f} {c:8.2f}")
    if "_eig5" in res:
        from jaxnh.models.bicycle import PUBLISHED

        err = np.abs(res["_eig5"] - np.sort_complex(np.array(PUBLISHED["eigenvalues_v5"]))).max()
        print(f"  eigenvalues at 5 m/s {res['_eig5']}; |SymPy − published| = {err:.1e}")


if __name__ == "__main__":
    sys.exit(main())
