"""Benchmark of batched sweeps and design gradients.

    python -m benchmarks.sweep_bench [--out DIR]   # DIR: benchmarks/ (or $JAXNH_BENCH_OUT)
    python -m benchmarks.sweep_bench --quick       # small batches; DIR: benchmarks/quick/

Measures, on the variator (T = 5 s, U21 = 1 + a sin(πt), J2 and a drawn at
random, simulate's default rtol = 1e-8, atol = 1e-10, its default solver and formulation, Lagrange's):

1. time per trajectory of `jaxnh.sweep` against the batch size (1 … 10⁴;
   `--quick`: 1 … 10³), and of one `jax.jit(jax.vmap(...))` call on the
   whole batch;
2. the same cases as a Python loop of single jitted `simulate` calls;
3. the same cases with SciPy `solve_ivp` (DOP853, hand-written NumPy
   right-hand side of eq. 9) at matched accuracy: the loosest rtol whose
   error against the closed form is no larger than jaxnh's;
4. scaling from 1 to 2 devices (a fresh process per device count with
   XLA_FLAGS=--xla_force_host_platform_device_count=N, every core);
5. chunk size at a fixed batch (full run only);
6. the cost of the gradient of the optimal-ratio design objective
   (examples/optimal_ratio.py, 8 coefficients, reverse mode through diffrax)
   relative to one evaluation of the objective.

Times are the best of several runs after compilation (compile times are
reported separately); this process runs on one core (`common.pin`), the
device-scaling processes on every core. Writes SWEEP.md, sweep.png and
results/sweep_bench.json into DIR.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

from . import common as C


C.pin()  # before JAX starts (a scaling worker keeps every core: JAXNH_BENCH_XLA_THREADS=default)

import numpy as np  # noqa: E402


T_END = 5.0
J1, M1, M2, W0 = 0.02, 0.3, -0.1, 2.0


# --- the cases -------------------------------------------------------------------------


def draw(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.01, 0.2, n), rng.uniform(0.0, 0.6, n)


def jax_case():
    """(make_params, case) for the variator; imported lazily so workers set XLA_FLAGS first."""
    import jax.numpy as jnp

    import jaxnh as nh
    from jaxnh.models import variator
    from jaxnh.profiles import Fourier

    mech = variator.mechanism()
    ts = jnp.linspace(0.0, T_END, 11)

    def make_params(J2, amp):
        return variator.VariatorParams(J1=J1, J2=J2, U21=Fourier(1.0, sin=[amp], period=2.0), M1=M1, M2=M2)

    def case(p):
        qd0 = jnp.stack([jnp.asarray(W0), p.U21(0.0) * W0])
        sol = nh.simulate(mech, p, jnp.zeros(2), qd0, ts, throw=False)
        return {"q": sol.q[-1], "qd": sol.qd[-1], "ok": sol.success, "steps": sol.stats["num_steps"]}

    return make_params, case


def best_of(fn, repeats):
    """(best wall time, best process CPU time) over `repeats` runs, s. On a shared
    machine the CPU time is the steadier measure of cost; wall time is what a user waits."""
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


# --- 1, 2: sweep vs vmap vs loop -------------------------------------------------------


def bench_batches(sizes, loop_n, repeats, with_vmap=True):
    import jax

    from jaxnh import sweep

    make_params, case = jax_case()
    rows = []
    for B in sizes:
        J2, amp = draw(B)
        ps = jax.vmap(make_params)(J2, amp)
        t = time.perf_counter()
        sweep(case, ps)
        compile_s = time.perf_counter() - t
        t_sweep, c_sweep = best_of(lambda: sweep(case, ps), repeats if B <= 1000 else 2)
        row = {
            "batch": B,
            "sweep_s": t_sweep,
            "sweep_per_traj_ms": 1e3 * t_sweep / B,
            "sweep_cpu_per_traj_ms": 1e3 * c_sweep / B,
            "sweep_first_call_s": compile_s,
        }
        if with_vmap and B <= 1000:
            vm = jax.jit(jax.vmap(case))
            jax.block_until_ready(vm(ps))
            t_vm, c_vm = best_of(lambda: jax.block_until_ready(vm(ps)), repeats)
            row["vmap_per_traj_ms"] = 1e3 * t_vm / B
            row["vmap_cpu_per_traj_ms"] = 1e3 * c_vm / B
        rows.append(row)
        print(
            f"  batch {B:>6}: sweep {row['sweep_per_traj_ms']:.4f} ms/trajectory "
            f"(CPU {row['sweep_cpu_per_traj_ms']:.4f})"
            + (f", one jit(vmap) call {row['vmap_per_traj_ms']:.4f}" if "vmap_per_traj_ms" in row else "")
            + f"  (first call {compile_s:.1f} s)",
            flush=True,
        )

    single = jax.jit(case)
    J2, amp = draw(loop_n)
    plist = [make_params(J2[i], amp[i]) for i in range(loop_n)]  # built outside the timing
    jax.block_until_ready(single(plist[0]))

    def loop():
        for p in plist:
            jax.block_until_ready(single(p))

    t_loop, c_loop = best_of(loop, repeats)
    print(
        f"  Python loop of single jitted solves: {1e3 * t_loop / loop_n:.4f} ms/trajectory "
        f"(CPU {1e3 * c_loop / loop_n:.4f})",
        flush=True,
    )
    return rows, {"n": loop_n, "per_traj_ms": 1e3 * t_loop / loop_n, "cpu_per_traj_ms": 1e3 * c_loop / loop_n}, single


# --- 3: SciPy at matched accuracy -------------------------------------------------------


def bench_scipy(n, repeats, single):
    import jax
    from scipy.integrate import solve_ivp

    from jaxnh.models import variator

    make_params, case = jax_case()
    exact_at_end = jax.jit(lambda J2, a: variator.closed_form(make_params(J2, a), np.array([0.0, T_END]), w0=W0))
    J2, amp = draw(n, seed=1)
    exact = []
    for i in range(n):
        q, qd = exact_at_end(J2[i], amp[i])
        exact.append(np.concatenate([np.asarray(q[-1]), np.asarray(qd[-1])]))
    exact = np.array(exact)
    out = [single(make_params(J2[i], amp[i])) for i in range(n)]
    jx = np.array([np.concatenate([np.asarray(o["q"]), np.asarray(o["qd"])]) for o in out])
    err_jax = float(np.max(np.abs(jx - exact) / np.abs(exact)))

    def rhs(t, y, J2, a):  # eq. (9) for w = phi1', with phi1' and phi2' = U21 w
        U = 1.0 + a * np.sin(np.pi * t)
        dU = a * np.pi * np.cos(np.pi * t)
        w = y[2]
        return [w, U * w, (M1 + U * M2 - J2 * U * dU * w) / (J1 + J2 * U * U)]

    def run(rtol):
        res = []
        for i in range(n):
            s = solve_ivp(
                rhs, (0.0, T_END), [0.0, 0.0, W0], method="DOP853", rtol=rtol, atol=rtol * 1e-2, args=(J2[i], amp[i])
            )
            w = s.y[2, -1]
            U = 1.0 + amp[i] * np.sin(np.pi * T_END)
            res.append([s.y[0, -1], s.y[1, -1], w, U * w])
        return np.array(res)

    chosen = None
    for rtol in (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12):
        err = float(np.max(np.abs(run(rtol) - exact) / np.abs(exact)))
        if err <= err_jax:
            chosen = (rtol, err)
            break
    if chosen is None:
        chosen = (1e-12, err)
    t, c = best_of(lambda: run(chosen[0]), repeats)
    print(
        f"  SciPy DOP853 at rtol={chosen[0]:g} (error {chosen[1]:.1e} ≤ jaxnh's {err_jax:.1e}): "
        f"{1e3 * t / n:.4f} ms/trajectory (CPU {1e3 * c / n:.4f})",
        flush=True,
    )
    return {
        "n": n,
        "rtol": chosen[0],
        "error": chosen[1],
        "jaxnh_error": err_jax,
        "per_traj_ms": 1e3 * t / n,
        "cpu_per_traj_ms": 1e3 * c / n,
    }


# --- 4: devices -------------------------------------------------------------------------


def scaling_worker(B, chunk, repeats):
    """Run in a subprocess: time one sweep of B cases on all local devices."""
    import jax

    from jaxnh import sweep

    make_params, case = jax_case()
    J2, amp = draw(B)
    ps = jax.vmap(make_params)(J2, amp)
    t = time.perf_counter()
    sweep(case, ps, chunk_size=chunk)
    first = time.perf_counter() - t
    import resource

    runs = []
    for _ in range(repeats):
        r0, t = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        sweep(case, ps, chunk_size=chunk)
        wall, r1 = time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF)
        runs.append((wall, r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime))
    wall, cpu = min(runs)
    print(
        json.dumps(
            {"devices": jax.device_count(), "batch": B, "chunk": chunk, "s": wall, "cpu_s": cpu, "first_call_s": first}
        )
    )


def bench_devices(B, chunk, repeats):
    rows = []
    for d in (1, 2):
        flags = (C._ENV0.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={d}").strip()
        env = dict(C._ENV0, XLA_FLAGS=flags, JAX_PLATFORMS="cpu", JAXNH_BENCH_XLA_THREADS="default")
        env["PYTHONPATH"] = os.pathsep.join([str(C.ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        unpin = f"import os; os.sched_setaffinity(0, {set(C._CPUS0)!r}); " if C._CPUS0 else ""
        code = unpin + "import runpy; runpy.run_module('benchmarks.sweep_bench', run_name='__main__')"
        cmd = [sys.executable, "-c", code, "--scaling-worker", str(B), str(chunk), str(repeats)]
        proc = subprocess.run(cmd, env=env, cwd=str(C.ROOT), capture_output=True, text=True, timeout=1200)
        if proc.returncode != 0:
            raise RuntimeError(proc.stderr[-2000:])
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"  {d} device(s): {B} cases in {row['s']:.3f} s ({1e3 * row['s'] / B:.4f} ms/trajectory), "
            f"process CPU time {row['cpu_s']:.3f} s",
            flush=True,
        )
    return rows


def bench_chunks(B, chunks, repeats):
    import jax

    from jaxnh import sweep

    make_params, case = jax_case()
    J2, amp = draw(B)
    ps = jax.vmap(make_params)(J2, amp)
    rows = []
    for c in chunks:
        sweep(case, ps, chunk_size=c)
        t, cpu = best_of(lambda: sweep(case, ps, chunk_size=c), repeats)
        rows.append({"chunk": c, "batch": B, "per_traj_ms": 1e3 * t / B, "cpu_per_traj_ms": 1e3 * cpu / B})
        print(f"  chunk {c:>5}: {1e3 * t / B:.4f} ms/trajectory (CPU {1e3 * cpu / B:.4f})", flush=True)
    return rows


# --- 6: gradient cost -------------------------------------------------------------------


def bench_gradient(repeats):
    import jax
    import jax.numpy as jnp

    O = C.example("optimal_ratio")
    probe = O.constant_law(1.1).at[1:].set(jnp.array([0.8, -0.6, 1.2, 0.3, -0.4, 0.2, 0.1]))

    def f(c):
        return O.objective(c, 1e3, 5.0)

    fwd, grad = jax.jit(f), jax.jit(jax.value_and_grad(f))
    t = time.perf_counter()
    jax.block_until_ready(fwd(probe))
    c_f = time.perf_counter() - t
    t = time.perf_counter()
    jax.block_until_ready(grad(probe))
    c_g = time.perf_counter() - t
    t_f = best_of(lambda: jax.block_until_ready(fwd(probe)), repeats * 5)[1]
    t_g = best_of(lambda: jax.block_until_ready(grad(probe)), repeats * 5)[1]
    steps = int(O.run(probe).stats["num_steps"])
    print(
        f"  design objective (CPU time): forward {1e3 * t_f:.3f} ms, "
        f"value and gradient (8 coefficients) {1e3 * t_g:.3f} ms "
        f"= {t_g / t_f:.1f}× ({steps} solver steps; compile {c_f:.1f} s and {c_g:.1f} s)",
        flush=True,
    )
    return {
        "forward_ms": 1e3 * t_f,
        "value_and_grad_ms": 1e3 * t_g,
        "ratio": t_g / t_f,
        "n_params": int(probe.size),
        "solver_steps": steps,
        "compile_forward_s": c_f,
        "compile_grad_s": c_g,
    }


# --- report ------------------------------------------------------------------------------


def write_report(res, out: pathlib.Path, command: str):
    out.mkdir(parents=True, exist_ok=True)
    C.save("sweep_bench", res, out)
    _plot(res, out / "sweep.png")
    L = []
    L.append("# Sweep and design-gradient benchmark")
    L.append("")
    L.append(C.stamp_line(command))
    L.append("")
    L.append(
        f"Load average {res['load_before']} before the run ({res['cpu_count']} CPUs). Variator, 5 s, rtol = 1e-8, "
        "atol = 1e-10, simulate's default solver and formulation (Lagrange's). Times: best of several runs after "
        "compilation, as "
        "wall-clock time and as the process's CPU time, in a process pinned to one core (the device scaling: fresh "
        "processes on every core); the machine may be shared with other jobs, so wall times (and the device "
        "scaling) are noisy and the CPU times are the steadier measure of cost."
    )
    L.append("")
    L.append("## Time per trajectory against batch size")
    L.append("")
    L.append(
        "| batch | `nh.sweep` wall (ms/trajectory) | `nh.sweep` CPU (ms/trajectory) "
        "| one `jit(vmap)` call, wall / CPU (ms/trajectory) | first sweep call incl. compile (s) |"
    )
    L.append("|---:|---:|---:|---:|---:|")
    for r in res["batches"]:
        vm = f"{r['vmap_per_traj_ms']:.4f} / {r['vmap_cpu_per_traj_ms']:.4f}" if "vmap_per_traj_ms" in r else "—"
        L.append(
            f"| {r['batch']} | {r['sweep_per_traj_ms']:.4f} | {r['sweep_cpu_per_traj_ms']:.4f} | {vm} | "
            f"{r['sweep_first_call_s']:.1f} |"
        )
    lp, sp = res["loop"], res["scipy"]
    big = res["batches"][-1]
    L.append("")
    L.append(
        f"| same cases, one at a time | wall (ms/trajectory) | CPU (ms/trajectory) | sweep at batch "
        f"{big['batch']} is cheaper by (CPU) |"
    )
    L.append("|---|---:|---:|---:|")
    L.append(
        f"| Python loop of single jitted `simulate` calls ({lp['n']} cases) | {lp['per_traj_ms']:.4f} | "
        f"{lp['cpu_per_traj_ms']:.4f} | {lp['cpu_per_traj_ms'] / big['sweep_cpu_per_traj_ms']:.1f}× |"
    )
    L.append(
        f"| SciPy `solve_ivp` DOP853, NumPy right-hand side, rtol = {sp['rtol']:g} ({sp['n']} cases) | "
        f"{sp['per_traj_ms']:.4f} | {sp['cpu_per_traj_ms']:.4f} | "
        f"{sp['cpu_per_traj_ms'] / big['sweep_cpu_per_traj_ms']:.1f}× |"
    )
    L.append("")
    L.append(
        f"Matched accuracy: max relative error of φ, φ' at 5 s against the closed form, jaxnh "
        f"{sp['jaxnh_error']:.1e}, SciPy {sp['error']:.1e} (the loosest SciPy rtol in 1e-6 … 1e-12 that is "
        "no less accurate)."
    )
    L.append("")
    L.append("## Devices")
    L.append("")
    L.append(
        "| devices | batch | chunk | wall time (s) | ms/trajectory | speed-up | process CPU time (s) "
        "| cores used (CPU/wall) |"
    )
    L.append("|---:|---:|---:|---:|---:|---:|---:|---:|")
    t1 = res["devices"][0]["s"]
    for r in res["devices"]:
        L.append(
            f"| {r['devices']} | {r['batch']} | {r['chunk']} | {r['s']:.3f} | {1e3 * r['s'] / r['batch']:.4f} | "
            f"{t1 / r['s']:.2f}× | {r['cpu_s']:.3f} | {r['cpu_s'] / r['s']:.2f} |"
        )
    L.append("")
    L.append(
        "Two host-platform CPU devices (`XLA_FLAGS=--xla_force_host_platform_device_count=2`) on a "
        f"{res['cpu_count']}-CPU machine: the ceiling is 2× only when both cores are free; the last column "
        "shows how many cores the process actually got (below 1 means other work held the CPUs). "
        "Total CPU time also falls with 2 devices when each device's half-chunk waits for fewer "
        "stragglers."
    )
    if res.get("chunks"):
        L.append("")
        L.append("## Chunk size")
        L.append("")
        L.append("| chunk | batch | wall (ms/trajectory) | CPU (ms/trajectory) |")
        L.append("|---:|---:|---:|---:|")
        for r in res["chunks"]:
            L.append(f"| {r['chunk']} | {r['batch']} | {r['per_traj_ms']:.4f} | {r['cpu_per_traj_ms']:.4f} |")
        L.append("")
        L.append(
            "A vmapped adaptive solve steps its whole chunk until the slowest member finishes: small chunks "
            "pay per-call overhead, large ones wait for stragglers."
        )
    g = res["gradient"]
    L.append("")
    L.append("## Gradient of a design objective")
    L.append("")
    L.append("| objective | forward, CPU (ms) | value and gradient, CPU (ms) | ratio |")
    L.append("|---|---:|---:|---:|")
    L.append(
        f"| optimal-ratio objective, {g['n_params']} coefficients, {g['solver_steps']} solver steps, reverse "
        f"mode (RecursiveCheckpointAdjoint) | {g['forward_ms']:.3f} | {g['value_and_grad_ms']:.3f} | "
        f"{g['ratio']:.1f}× |"
    )
    L.append("")
    L.append(f"Compile: forward {g['compile_forward_s']:.1f} s, gradient {g['compile_grad_s']:.1f} s.")
    L.append("")
    L.append("![time per trajectory](sweep.png)")
    L.append("")
    (out / "SWEEP.md").write_text("\n".join(L))


def _plot(res, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.4), gridspec_kw={"width_ratios": [2, 1]})
    B = [r["batch"] for r in res["batches"]]
    ax[0].loglog(B, [r["sweep_cpu_per_traj_ms"] for r in res["batches"]], "o-", label="nh.sweep (chunked, sharded)")
    vb = [r for r in res["batches"] if "vmap_per_traj_ms" in r]
    if vb:
        ax[0].loglog(
            [r["batch"] for r in vb], [r["vmap_cpu_per_traj_ms"] for r in vb], "s--", label="one jit(vmap) call"
        )
    ax[0].axhline(res["loop"]["cpu_per_traj_ms"], color="C2", ls=":", label="Python loop of single solves")
    ax[0].axhline(
        res["scipy"]["cpu_per_traj_ms"], color="C3", ls="-.", label=f"SciPy DOP853 loop (rtol {res['scipy']['rtol']:g})"
    )
    ax[0].set(
        xlabel="batch size",
        ylabel="CPU ms per trajectory",
        title=f"variator, 5 s, error ≤ {res['scipy']['jaxnh_error']:.0e}",
    )
    ax[0].legend(fontsize=8)
    d = res["devices"]
    ax[1].bar([str(r["devices"]) for r in d], [1e3 * r["s"] / r["batch"] for r in d], color=["C0", "C1"])
    ax[1].set(xlabel="devices", ylabel="wall ms per trajectory", title=f"batch {d[0]['batch']}, 1 vs 2 CPU devices")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small batches (a smoke run)")
    ap.add_argument(
        "--out", default=None, help="folder (default: benchmarks/, benchmarks/quick/ for --quick, or $JAXNH_BENCH_OUT)"
    )
    ap.add_argument("--scaling-worker", nargs=3, type=int, metavar=("B", "CHUNK", "REPEATS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.scaling_worker:
        scaling_worker(*args.scaling_worker)
        return
    t0 = time.perf_counter()
    quick = args.quick
    out = pathlib.Path(args.out) if args.out else C.report_dir(quick)
    import jaxnh  # noqa: F401  (64-bit mode)

    res = {
        "quick": quick,
        "cpu_count": os.cpu_count(),
        "load_before": round(os.getloadavg()[0], 2),
    }
    sizes = (1, 1000) if quick else (1, 10, 100, 1000, 10000)
    print("batch sizes:", flush=True)
    res["batches"], res["loop"], single = bench_batches(sizes, 20 if quick else 200, 2 if quick else 3, not quick)
    print("SciPy:", flush=True)
    res["scipy"] = bench_scipy(10 if quick else 50, 1 if quick else 3, single)
    print("devices:", flush=True)
    res["devices"] = bench_devices(2048 if quick else 8192, 1024 if quick else 1024, 2 if quick else 3)
    if not quick:
        print("chunk size:", flush=True)
        res["chunks"] = bench_chunks(4096, (32, 128, 256, 512, 1024, 4096), 3)
    print("gradient:", flush=True)
    res["gradient"] = bench_gradient(1 if quick else 3)
    res["total_s"] = time.perf_counter() - t0
    write_report(res, out, C.command("sweep_bench", argv))
    print(f"wrote {out}/SWEEP.md, sweep.png, results/sweep_bench.json in {res['total_s']:.0f} s")


if __name__ == "__main__":
    main()
