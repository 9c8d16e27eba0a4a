"""First answers in fresh processes: jaxnh against a hand-written diffrax program of the same equations.

For the README's variator (hand: eq. (9) in `diffrax.Tsit5`, jitted) and the
car with 4 trailers (hand: SymPy's Kane equations printed as JAX source into
a module file, `diffrax.Tsit5`, jitted), each repeat runs in new processes
(every core, the user's XLA settings):

* cold: a default process, no compilation cache (JAX's default);
* cache, first: `jaxnh.enable_compilation_cache()` right after the import,
  with `JAXNH_CACHE_DIR` an empty temporary folder; the hand-written program
  with `JAX_COMPILATION_CACHE_DIR` another empty folder (and every program
  written, `JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0`, as jaxnh does);
* cache, second: the same again, reading the folder the first one wrote.

Times are from before the first import to the answer on the host, wall and
CPU; errors against the closed form (variator) and a Dopri8 reference at
rtol 1e-12 (the chain, see benchmarks/size.py).

    python -m benchmarks.first_answer [--quick] [--repeats 5]
"""

from __future__ import annotations

import argparse
import inspect
import os
import tempfile

from . import common as C


C.pin()  # before JAX starts

from .mechanisms import chain as CH, variator as VV  # noqa: E402
from .size import Case  # noqa: E402


N_CHAIN = 4

VARIATOR_JAXNH = """
import jax, jax.numpy as jnp, numpy as np
import jaxnh as nh
{cache}
{imported}

def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)
def U21(t):
    return 1.0 + 0.4 * jnp.sin(jnp.pi * t)
def rolling(q, qd, t, p):
    return jnp.stack([U21(t) * qd[0] - qd[1]])
def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])

mech = nh.Mechanism(T, constraints=rolling, forces=torques, names=("phi1", "phi2"))
p = {{"J1": 0.02, "J2": 0.05, "M1": 0.3, "M2": -0.1}}
ts = jnp.linspace(0.0, 10.0, 101)
sol = nh.simulate(mech, p, jnp.zeros(2), jnp.array([2.0, 2.0]), ts)
OUT.update(q=np.asarray(sol.q), qd=np.asarray(sol.qd))
"""

HAND = """
import jax, jax.numpy as jnp, numpy as np, diffrax
jax.config.update("jax_enable_x64", True)
{imported}
{define}

@jax.jit
def solve(y0, args):
    ts = jnp.linspace(0.0, {T}, {n})
    sol = diffrax.diffeqsolve(diffrax.ODETerm(rhs), diffrax.Tsit5(), 0.0, {T}, None, y0, args=args,
                              saveat=diffrax.SaveAt(ts=ts),
                              stepsize_controller=diffrax.PIDController(rtol={rtol}, atol={atol}))
    return sol.ys

OUT["ys"] = np.asarray(solve(jnp.array({y0}), jnp.array({args})))
"""


def programs(folder: str) -> dict:
    """name -> (jaxnh child(cache), hand child, errors(jaxnh out), errors(hand out))."""
    q_ref, qd_ref = VV.reference()
    eq9 = inspect.getsource(VV.eq9).replace("def eq9(", "def rhs(")
    out = {
        "variator": (
            lambda cache: VARIATOR_JAXNH.format(
                imported=C.IMPORTED, cache="nh.enable_compilation_cache()" if cache else ""
            ),
            HAND.format(
                imported=C.IMPORTED,
                define=eq9,
                T=10.0,
                n=101,
                rtol=C.RTOL,
                atol=C.ATOL,
                y0=list(VV.EQ9_Y0),
                args=list(VV.EQ9_ARGS),
            ),
            lambda o: C.max_error(o["q"], o["qd"], q_ref, qd_ref),
            lambda o: C.max_error(*VV.eq9_unpack(o["ys"], VV.TS), q_ref, qd_ref),
        )
    }
    case = Case(N_CHAIN, CH.sympy_namespace())
    with open(os.path.join(folder, "chain_rhs.py"), "w") as f:
        f.write(CH.jax_source(N_CHAIN))
    define = f"import sys\nsys.path.insert(0, {folder!r})\nfrom chain_rhs import rhs"
    out[f"car with {N_CHAIN} trailers"] = (
        lambda cache: case.child("appell", cache),
        HAND.format(
            imported=C.IMPORTED,
            define=define,
            T=CH.T_END,
            n=CH.N_REPORT,
            rtol=C.RTOL,
            atol=C.ATOL,
            y0=list(case.y0),
            args=list(case.P),
        ),
        lambda o: case.error("appell", o),
        lambda o: C.max_error(*CH.kane_unpack(o["ys"]), case.q_ref, case.qd_ref),
    )
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one repeat")
    ap.add_argument("--repeats", type=int, default=None, help="default 5 (quick 1)")
    a = ap.parse_args(argv)
    R = a.repeats or (1 if a.quick else 5)
    folder = tempfile.mkdtemp(prefix="jaxnh-bench-hand-")
    progs = programs(folder)
    kinds = (
        "jaxnh cold",
        "hand cold",
        "jaxnh cache, first",
        "jaxnh cache, second",
        "hand cache, first",
        "hand cache, second",
    )
    rows = {m: {k: dict(wall=[], cpu=[], imports=[], error=None) for k in kinds} for m in progs}
    for r in range(R):
        for m, (jx, hand, err_j, err_h) in progs.items():
            d_j, d_h = C.cache_dirs(2)
            hand_env = {"JAX_COMPILATION_CACHE_DIR": d_h, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}
            runs = {
                "jaxnh cold": (jx(False), {}, err_j),
                "hand cold": (hand, {}, err_h),
                "jaxnh cache, first": (jx(True), {"JAXNH_CACHE_DIR": d_j}, err_j),
                "jaxnh cache, second": (jx(True), {"JAXNH_CACHE_DIR": d_j}, err_j),
                "hand cache, first": (hand, hand_env, err_h),
                "hand cache, second": (hand, hand_env, err_h),
            }
            for k, (code, env, err) in runs.items():
                row = rows[m][k]
                try:
                    o = C.fresh(code, env)
                except RuntimeError as ex:
                    row["note"] = str(ex).strip().splitlines()[-1][:300]
                    C.log(f"[first_answer] {m}, {k}: FAILED {row['note']}")
                    continue
                row["wall"].append(o["wall"])
                row["cpu"].append(o["cpu"])
                row["imports"].append(o["import"])
                if row["error"] is None:
                    row["error"] = err(o)
                if k.endswith("first"):
                    row.setdefault("cache_entries", len(os.listdir(env.get("JAXNH_CACHE_DIR") or d_h)))
                C.log(
                    f"[first_answer] {m}, {k}: {o['wall']:.2f} s wall, {o['cpu']:.2f} s CPU, error {row['error']:.1e}"
                )
    ratios = {}
    for m, rr in rows.items():
        for row in rr.values():
            row["wall_median"], row["cpu_median"] = C.median(row["wall"]), C.median(row["cpu"])
            row["import_median"] = C.median(row["imports"])
        hc = rr["hand cold"]
        ratios[m] = {
            "cold / hand cold": C.paired_ratio(rr["jaxnh cold"]["wall"], hc["wall"]),
            "cold / hand cold (CPU)": C.paired_ratio(rr["jaxnh cold"]["cpu"], hc["cpu"]),
            "cache second / hand cold": C.paired_ratio(rr["jaxnh cache, second"]["wall"], hc["wall"]),
            "cache second / hand cold (CPU)": C.paired_ratio(rr["jaxnh cache, second"]["cpu"], hc["cpu"]),
            "cache second / hand cache second": C.paired_ratio(
                rr["jaxnh cache, second"]["wall"], rr["hand cache, second"]["wall"]
            ),
        }
        C.log(f"[first_answer] {m}: {ratios[m]}")
    C.save("first_answer", dict(rows=rows, ratios=ratios, repeats=R, n_chain=N_CHAIN, quick=a.quick))


if __name__ == "__main__":
    main()
