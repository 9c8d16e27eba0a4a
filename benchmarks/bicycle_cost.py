"""What it costs to get the Whipple bicycle's equations: jaxnh (autodiff) against SymPy (KanesMethod).

Run from the repository root:

    python -m benchmarks.bicycle_cost              # jaxnh, then SymPy if installed
    python -m benchmarks.bicycle_cost --no-sympy   # jaxnh only
    python -m benchmarks.bicycle_cost --quick      # jaxnh only, without the vmapped program and Tsit5 (a smoke run)
    python -m benchmarks.bicycle_cost --sympy-timeout 1800
    python -m benchmarks.bicycle_cost --sympy-numeric   # SymPy with the benchmark numbers substituted first

Writes BICYCLE.md and results/bicycle_cost.json into benchmarks/ (a `--quick`
run into benchmarks/quick/, or $JAXNH_BENCH_OUT when set); `--out` changes
the Markdown path (results/ goes beside it).

Measured, wall clock, in this process (pinned to one core, `common.pin`),
with no persistent compilation cache (importing jaxnh turns none on) unless
`--warm-cache` (`jaxnh.enable_compilation_cache()`: the user's cache folder).
First calls include tracing and XLA compilation; the machine's load matters,
so the script also prints CPU time:

1. jaxnh: from the model definition (`jaxnh.models.bicycle`: four rigid bodies,
   one holonomic and four nonholonomic contact constraints) to the 4×4
   lean/steer state matrix at 5 m/s — first call and a repeat call — and to
   the matrices at 101 speeds, as concrete calls (one-speed programs, stacked)
   and as one vmapped program under `jax.jit`.
2. jaxnh: a 5 s nonlinear simulation (Lagrange's equations with multipliers,
   8 coordinates, rtol 1e-8, the default solver — for this large vector field
   diffrax's Dopri8, see `jaxnh.default_solver`), first call and the
   median of 5 repeats, with its error against a reference run at rtol 1e-12
   (not timed); and the same with diffrax's Tsit5, for comparison.
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
import pathlib
import sys
import time

from . import common as C


C.pin()  # before JAX starts

import numpy as np  # noqa: E402


def clock():
    return time.perf_counter(), time.process_time()


def since(start):
    w, c = clock()
    return w - start[0], c - start[1]


def median_of(fn, n=5):
    """(wall, CPU) medians of n timed calls of fn (one call is noisy on a shared machine)."""
    times = []
    for _ in range(n):
        start = clock()
        fn()
        times.append(since(start))
    return tuple(float(np.median([t[i] for t in times])) for i in (0, 1))


def jaxnh_costs(quick=False):
    import diffrax
    import jax
    import jax.numpy as jnp

    import jaxnh as nh
    from jaxnh.models import bicycle

    out = {}
    p = bicycle.default_params()
    start = clock()
    lin = jax.jit(bicycle.linear_lean_steer)  # the model is defined at this point
    A = np.asarray(lin(5.0, p))
    out["state matrix, first call (trace + compile + run)"] = since(start)
    start = clock()
    A = np.asarray(lin(5.0, p))
    out["state matrix, repeat call"] = since(start)
    start = clock()
    jax.block_until_ready(bicycle.linearized_speeds(jnp.linspace(0.0, 10.0, 101), p).A)
    out["101 speeds, concrete (one-speed programs, stacked), first"] = since(start)
    start = clock()
    jax.block_until_ready(bicycle.linearized_speeds(jnp.linspace(0.0, 10.0, 101) + 0.01, p).A)
    out["101 speeds, concrete, repeat"] = since(start)
    if not quick:
        batched = jax.jit(bicycle.linearized_speeds)
        start = clock()
        jax.block_until_ready(batched(jnp.linspace(0.0, 10.0, 101), p).A)
        out["101 speeds in one vmapped program (jax.jit), first (trace + compile + run)"] = since(start)
        start = clock()
        jax.block_until_ready(batched(jnp.linspace(0.0, 10.0, 101) + 0.01, p).A)
        out["101 speeds in one vmapped program, repeat"] = since(start)

    q, qd = bicycle.upright(5.0, p)
    qd = qd.at[bicycle.ROLL].set(0.5)
    ts = jnp.linspace(0.0, 5.0, 101)
    mech = bicycle.mechanism("lagrange")

    def simulate(solver=None, rtol=1e-8, atol=1e-10):
        sol = nh.simulate(
            mech,
            p,
            q,
            qd,
            ts,
            method="lagrange",
            rtol=rtol,
            atol=atol,
            solver=solver,
            record=("energy",),
        )
        jax.block_until_ready(sol.q)
        return sol

    start = clock()
    sol = simulate()
    out["5 s nonlinear simulation, first call (default solver)"] = since(start)
    out["5 s nonlinear simulation, repeat (median of 5)"] = median_of(simulate)
    sol_d = None
    if not quick:
        start = clock()
        sol_d = simulate(diffrax.Tsit5())
        out["5 s nonlinear simulation, first call, diffrax.Tsit5"] = since(start)
        out["5 s nonlinear simulation, repeat (median of 5), diffrax.Tsit5"] = median_of(
            lambda: simulate(diffrax.Tsit5())
        )
    ref = simulate(diffrax.Dopri8(), rtol=1e-12, atol=1e-14)  # reference, not timed
    out["_steps"] = int(sol.stats["num_steps"])
    out["_sim_error"] = float(np.abs(np.asarray(sol.q) - np.asarray(ref.q)).max())
    if sol_d is not None:
        out["_steps_diffrax"] = int(sol_d.stats["num_steps"])
        out["_sim_error_diffrax"] = float(np.abs(np.asarray(sol_d.q) - np.asarray(ref.q)).max())
    out["_energy_drift"] = float(np.ptp(np.asarray(sol.energy)))
    out["_final_roll"] = float(sol.q[-1, bicycle.ROLL])
    out["_eig5"] = np.sort_complex(np.linalg.eigvals(A))
    pub = np.sort_complex(np.array(bicycle.PUBLISHED["eigenvalues_v5"], dtype=complex))
    out["_eig5_error"] = float(np.abs(out["_eig5"] - pub).max())
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
    names = [
        "w",
        "c",
        "lam",
        "g",
        "rR",
        "mR",
        "IRxx",
        "IRyy",
        "xB",
        "zB",
        "mB",
        "IBxx",
        "IByy",
        "IBzz",
        "IBxz",
        "xH",
        "zH",
        "mH",
        "IHxx",
        "IHyy",
        "IHzz",
        "IHxz",
        "rF",
        "mF",
        "IFxx",
        "IFyy",
    ]
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
    P = O.locatenew("P", q[0] * N.x + q[1] * N.y)  # rear contact
    Rc = P.locatenew("Rc", -s["rR"] * L.z)  # rear hub
    Bc = Rc.locatenew("Bc", s["xB"] * C.x + (s["zB"] + s["rR"]) * C.z)  # rear frame mass centre
    S = Rc.locatenew("S", (s["w"] + s["c"]) * C.x + s["rR"] * C.z)  # steer axis meets the ground
    Hc = S.locatenew("Hc", (s["xH"] - s["w"] - s["c"]) * E.x + s["zH"] * E.z)
    Fc = S.locatenew("Fc", -s["c"] * E.x - s["rF"] * E.z)  # front hub
    down = E.y.cross(N.z.cross(E.y))  # in the wheel plane, towards the ground
    Fn = Fc.locatenew("Fn", s["rF"] * down / sm.sqrt(down.dot(down)))  # front contact
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
        N,
        q_ind=[q[i] for i in (0, 1, 2, 3, 5, 6, 7)],
        u_ind=[u[3], u[5], u[6]],
        kd_eqs=[qi.diff() - ui for qi, ui in zip(q, u)],
        q_dependent=[q[4]],
        configuration_constraints=[holonomic],
        u_dependent=[u[0], u[1], u[2], u[4], u[7]],
        velocity_constraints=constraints,
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
    A4 = A5[np.ix_(idx, idx)]
    if np.all(np.isfinite(A4)):
        res["_eig5"] = np.sort_complex(np.linalg.eigvals(A4))
    else:
        n_bad = int(np.sum(~np.isfinite(A4)))
        res["_note"] = f"SymPy's linearised matrix is not finite at the operating point ({n_bad} of 16 entries)"
    queue.put(dict(res))


def _rows(res):
    return [(k, w, c) for k, (w, c) in ((k, v) for k, v in res.items() if not k.startswith("_"))]


def write_report(path, jx, sy, sympy_status, cache, command):
    """BICYCLE.md (Markdown) and results/bicycle_cost.json beside it, from the measured numbers."""
    m = C.machine()
    L = [
        "# Cost of the Whipple bicycle: jaxnh (autodiff) and SymPy (KanesMethod)",
        "",
        C.stamp_line(command),
        "",
        "See the script's docstring for what is timed. "
        f"Machine: {m['cores']} cores, this process pinned to one (the machine may be shared: wall times include "
        "waiting for a core, CPU times are all threads of the process). "
        f"jaxnh's compilation cache: {cache} (first calls trace and compile).",
        "",
    ]
    if jx:
        L += ["## jaxnh", "", "| step | wall s | CPU s |", "|---|---:|---:|"]
        L += [f"| {k} | {w:.2f} | {c:.2f} |" for k, w, c in _rows(jx)]
        tsit = (
            f"diffrax.Tsit5 {jx['_steps_diffrax']} steps, error {jx['_sim_error_diffrax']:.1e}; "
            if "_steps_diffrax" in jx
            else ""
        )
        L += [
            "",
            f"* State matrix at 5 m/s: eigenvalues {np.array2string(jx['_eig5'], precision=10)}; "
            f"max |jaxnh − published| = {jx['_eig5_error']:.1e}.",
            f"* Nonlinear run (roll-rate kick 0.5 rad/s at 5 m/s, 5 s, rtol 1e-8, atol 1e-10): default solver "
            f"{jx['_steps']} steps, max coordinate error {jx['_sim_error']:.1e} against a run at rtol 1e-12 "
            f"(diffrax.Dopri8); {tsit}"
            f"energy drift {jx['_energy_drift']:.1e} J; final roll {jx['_final_roll']:+.6f} rad.",
            "",
        ]
    L += ["## SymPy", "", sympy_status, ""]
    if sy:
        L += ["| step | wall s | CPU s |", "|---|---:|---:|"]
        L += [f"| {k} | {w:.2f} | {c:.2f} |" for k, w, c in _rows(sy)]
        L += [""]
        if "_note" in sy:
            L += [f"* {sy['_note']}.", ""]
        if "_eig5" in sy:
            L += [
                f"* Eigenvalues at 5 m/s {np.array2string(sy['_eig5'], precision=10)}; "
                f"max |SymPy − published| = {sy['_eig5_error']:.1e}.",
                "",
            ]
    path = pathlib.Path(path)
    path.write_text("\n".join(L))

    def clean(d):
        return {
            k: (np.asarray(v).tolist() if not np.iscomplexobj(v) else [[z.real, z.imag] for z in np.ravel(v)])
            for k, v in d.items()
        }

    jpath = C.save("bicycle_cost", dict(jaxnh=clean(jx), sympy=clean(sy), sympy_status=sympy_status, cache=cache),
                   path.parent)  # fmt: skip
    print(f"wrote {path} and {jpath}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--no-sympy", action="store_true")
    ap.add_argument(
        "--quick", action="store_true", help="--no-sympy, and neither the vmapped program nor diffrax.Tsit5"
    )
    ap.add_argument("--no-jaxnh", action="store_true", help="SymPy only")
    ap.add_argument("--sympy-timeout", type=float, default=1200.0, help="seconds before giving up on SymPy")
    ap.add_argument(
        "--sympy-numeric",
        action="store_true",
        help="give SymPy the benchmark numbers from the start instead of symbolic parameters",
    )
    ap.add_argument(
        "--out",
        default=None,
        help="Markdown report (default: BICYCLE.md in benchmarks/, benchmarks/quick/ for --quick, or $JAXNH_BENCH_OUT)",
    )
    ap.add_argument(
        "--warm-cache",
        action="store_true",
        help="turn on jaxnh's compilation cache in the user's folder (default: no persistent cache, so that "
        "first calls are first calls)",
    )
    args = ap.parse_args(argv)
    out = args.out or str(C.report_dir(args.quick) / "BICYCLE.md")
    cache = "none (a first run)"
    if args.warm_cache:
        import jaxnh as nh

        nh.enable_compilation_cache()
        cache = "the user's cache folder (`jaxnh.enable_compilation_cache()`)"
    print(f"CPU cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}")
    jx = {} if args.no_jaxnh else jaxnh_costs(args.quick)
    if jx:
        print("jaxnh (autodiff, jit):                                  wall s    CPU s")
        for k, w, c in _rows(jx):
            print(f"  {k:<54}{w:8.2f} {c:8.2f}")
        print(
            f"  (eigenvalues at 5 m/s {jx['_eig5']}, |jaxnh − published| = {jx['_eig5_error']:.1e}; nonlinear run: "
            f"{jx['_steps']} steps, error {jx['_sim_error']:.1e})"
        )
    res, status = {}, "Not run (`--no-sympy`)." if args.no_sympy else "Not run (`--quick`)."
    if not (args.no_sympy or args.quick):
        try:
            import sympy
        except ImportError:
            sympy = None
            status = "SymPy not installed (pip install 'jaxnh[bench]'): the KanesMethod comparison was skipped."
            print(status)
        if sympy is not None:
            res, status = run_sympy(args)
    write_report(out, jx, res, status, cache, C.command("bicycle_cost", argv))


def run_sympy(args):
    import sympy

    queue = mp.get_context("spawn").Queue()
    proc = mp.get_context("spawn").Process(target=sympy_costs, args=(queue, args.sympy_numeric))
    proc.start()
    res = {}
    deadline = time.perf_counter() + args.sympy_timeout
    while proc.is_alive() and time.perf_counter() < deadline:
        try:
            res = queue.get(timeout=1.0)  # drain as phases finish (a full pipe would block the child)
        except Exception:
            pass
    while not queue.empty():
        res = queue.get()
    kind = "numeric parameters" if args.sympy_numeric else "symbolic parameters"
    if proc.is_alive():
        proc.terminate()
        status = (
            f"SymPy {sympy.__version__} (KanesMethod, same model, {kind}) did not finish within "
            f"{args.sympy_timeout:.0f} s (wall); the phases it completed are listed."
        )
    else:
        status = f"SymPy {sympy.__version__} (KanesMethod, same model, {kind}):"
    print(status)
    for k, w, c in _rows(res):
        print(f"  {k:<54}{w:8.2f} {c:8.2f}")
    if "_note" in res:
        print("  " + res["_note"])
    if "_eig5" in res:
        from jaxnh.models.bicycle import PUBLISHED

        res["_eig5_error"] = float(np.abs(res["_eig5"] - np.sort_complex(np.array(PUBLISHED["eigenvalues_v5"]))).max())
        print(f"  eigenvalues at 5 m/s {res['_eig5']}; |SymPy − published| = {res['_eig5_error']:.1e}")
    return res, status


if __name__ == "__main__":
    sys.exit(main())
