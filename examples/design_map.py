"""Design map of the variator: output speed and contact force over (J2, ratio amplitude).

Run:  python examples/design_map.py [OUTDIR] [--n 100] [--chunk 1024]   (default OUTDIR jaxnh_out/)

A grid of n × n variators (default 100 × 100 = 10⁴ cases) differing in the
output shaft's inertia J2 (0.01 … 0.2 kg·m²) and in the amplitude a (0 … 0.6)
of the ratio law U21(t) = 1 + a sin(π t) (period 2 s). Each starts at
φ1' = 2 rad/s with the motor torque M1 = 0.3 N·m and the load M2 = −0.1 N·m
and runs for 6 s. For each case the sweep keeps only three numbers:

* the mean output-shaft speed φ2(6 s) / 6 s, rad/s;
* the output-shaft speed at the end, φ2'(6 s), rad/s;
* the peak contact multiplier max |λ| over 241 report times, N·m — the
  tangential contact force times the roller radius: the roller slips when it
  exceeds μ N r, so this map shows which designs need more contact load.

All cases run through `jaxnh.sweep`: vmapped in chunks, sharded over every
device JAX sees (set XLA_FLAGS=--xla_force_host_platform_device_count=2 to
try two CPU devices). Three cases are checked against the closed form. Writes
`design_map.png`.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh._analysis.sweep import sweep
from jaxnh.models import variator
from jaxnh.profiles import Fourier


MECH = variator.mechanism()
T_END = 6.0
TS = jnp.linspace(0.0, T_END, 241)
W0 = 2.0  # rad/s


def make_params(J2, amp):
    """A variator with output inertia J2 (kg·m²) and ratio law 1 + amp·sin(πt)."""
    return variator.VariatorParams(J1=0.02, J2=J2, U21=Fourier(1.0, sin=[amp], period=2.0), M1=0.3, M2=-0.1)


def case(p):
    """One design: mean and final output speed (rad/s), peak |λ| (N·m), status, steps."""
    qd0 = jnp.stack([W0, p.U21(0.0) * W0])
    sol = nh.simulate(MECH, p, jnp.zeros(2), qd0, TS, record=("multipliers",), throw=False)
    return {
        "w2_mean": sol.q[-1, 1] / T_END,
        "w2_end": sol.qd[-1, 1],
        "lam_peak": jnp.max(jnp.abs(sol.multipliers)),
        "ok": sol.success,
        "steps": sol.stats["num_steps"],
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir", nargs="?", default="jaxnh_out")
    ap.add_argument("--n", type=int, default=100, help="grid points per axis (n² cases)")
    ap.add_argument("--chunk", type=int, default=None, help="members per compiled call")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)

    J2s = np.linspace(0.01, 0.2, args.n)
    amps = np.linspace(0.0, 0.6, args.n)
    J2g, ampg = np.meshgrid(J2s, amps, indexing="ij")  # case (i, j) = (J2s[i], amps[j])
    params = jax.vmap(make_params)(J2g.ravel(), ampg.ravel())
    print(f"{J2g.size} cases on {jax.device_count()} device(s)")
    t0 = time.perf_counter()
    res = sweep(case, params, chunk_size=args.chunk, progress=True)
    wall = time.perf_counter() - t0
    grid = {k: np.asarray(v).reshape(J2g.shape) for k, v in res.items()}
    n_ok = int(grid["ok"].sum())
    print(
        f"{n_ok}/{J2g.size} solves succeeded in {wall:.1f} s (compile included), "
        f"{1e3 * wall / J2g.size:.3f} ms per case; steps per case {grid['steps'].min()}–{grid['steps'].max()}"
    )

    # spot checks against the closed form (eq. 9 integrated by quadrature)
    for i, j in ((0, 0), (args.n // 2, args.n - 1), (args.n - 1, args.n // 3)):
        p = make_params(J2s[i], amps[j])
        _, qd = variator.closed_form(p, TS, w0=W0)
        err = abs(float(qd[-1, 1]) - grid["w2_end"][i, j]) / abs(float(qd[-1, 1]))
        print(
            f"  J2 = {J2s[i]:.4f}, a = {amps[j]:.3f}: φ2'(6 s) = {grid['w2_end'][i, j]:.8f} rad/s, "
            f"relative error vs closed form {err:.1e}"
        )

    i, j = np.unravel_index(np.argmax(grid["lam_peak"]), J2g.shape)
    print(
        f"largest peak |λ| = {grid['lam_peak'][i, j]:.4f} N·m at J2 = {J2s[i]:.3f} kg·m², a = {amps[j]:.3f}; "
        f"smallest {grid['lam_peak'].min():.4f} N·m"
    )
    _plot(out, J2s, amps, grid)
    return grid


def _plot(out, J2s, amps, grid):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("w2_mean", "mean output speed φ2(6 s)/6 s, rad/s", "viridis"),
        ("w2_end", "output speed φ2'(6 s), rad/s", "viridis"),
        ("lam_peak", "peak contact multiplier max|λ|, N·m", "magma"),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4))
    for ax, (key, title, cmap) in zip(axes, panels):
        z = np.where(grid["ok"], grid[key], np.nan)
        m = ax.pcolormesh(amps, J2s, z, cmap=cmap, shading="auto")
        cs = ax.contour(amps, J2s, z, colors="w", linewidths=0.6, levels=6)
        ax.clabel(cs, fontsize=7, fmt="%.2f")
        fig.colorbar(m, ax=ax)
        ax.set(xlabel="amplitude a of U21 = 1 + a sin(πt)", ylabel="J2, kg·m²", title=title)
    fig.suptitle(
        f"Variator design map: {grid['ok'].size} cases (J1 = 0.02 kg·m², M1 = 0.3 N·m, "
        f"M2 = −0.1 N·m, φ1'(0) = {W0} rad/s, 6 s)"
    )
    fig.tight_layout()
    fig.savefig(out / "design_map.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out / 'design_map.png'}")


if __name__ == "__main__":
    main()
