"""Stability map of the Whipple bicycle over forward speed and trail.

Run:  python examples/bicycle_stability_map.py [OUTDIR] [--nv 100] [--nc 101]   (default OUTDIR jaxnh_out/)

The benchmark bicycle of Meijaard, Papadopoulos, Ruina & Schwab (2007),
linearised about upright straight running by automatic differentiation of
the nonlinear rigid-body model (`jaxnh.models.bicycle.linear_lean_steer`):
a 4×4 state matrix for (lean, steer, lean rate, steer rate). Upright running
is asymptotically stable where every eigenvalue has a negative real part, so
the map shows max Re(eigenvalue) (1/s) over the forward speed v (0 … 10 m/s)
and the trail c (−0.02 … 0.18 m; the benchmark's is 0.08 m), with the
stability boundary (zero level) drawn in black.

All nv × nc cases (default 10 100) go through `jaxnh.sweep`. A second sweep
along v at the benchmark trail (2001 speeds, the same compiled chunk) finds
the weave and capsize speeds from the sign changes and compares them with
the published 4.29238 and 6.02426 m/s. The first call compiles the
linearisation of the full model (tens of seconds); the sweep itself takes a
few seconds. Writes `bicycle_stability_map.png`.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax.numpy as jnp
import numpy as np

import jaxnh  # noqa: F401  (64-bit mode)
from jaxnh._analysis.sweep import sweep
from jaxnh.models import bicycle


P0 = bicycle.default_params()
CHUNK = 512


def max_real_eigenvalue(v, trail):
    """max Re λ (1/s) of the lean–steer state matrix at speed v (m/s) and trail (m)."""
    A = bicycle.linear_lean_steer(v, dict(P0, c=trail))
    return jnp.max(jnp.real(jnp.linalg.eigvals(A)))


def sign_changes(x, y):
    """x where y changes sign, by linear interpolation between samples."""
    i = np.nonzero(np.sign(y[:-1]) != np.sign(y[1:]))[0]
    return x[i] - y[i] * (x[i + 1] - x[i]) / (y[i + 1] - y[i])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir", nargs="?", default="jaxnh_out")
    ap.add_argument("--nv", type=int, default=100, help="speeds")
    ap.add_argument("--nc", type=int, default=101, help="trails")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)

    v = np.linspace(0.0, 10.0, args.nv)
    c = np.linspace(-0.02, 0.18, args.nc)
    V, C = np.meshgrid(v, c, indexing="ij")
    t0 = time.perf_counter()
    grid = sweep(max_real_eigenvalue, V.ravel(), C.ravel(), chunk_size=CHUNK, progress=True).reshape(V.shape)
    print(f"{V.size} linearisations and eigenvalue problems in {time.perf_counter() - t0:.1f} s (compile included)")

    # the benchmark trail, finely in speed: same function, same chunk shape, no recompilation
    vf = np.linspace(0.0, 10.0, 2001)
    t0 = time.perf_counter()
    line = sweep(max_real_eigenvalue, vf, np.full_like(vf, float(P0["c"])), chunk_size=CHUNK)
    print(f"{vf.size} speeds at the benchmark trail in {time.perf_counter() - t0:.2f} s")
    crossings = sign_changes(vf, line)
    pub = (bicycle.PUBLISHED["weave_speed"], bicycle.PUBLISHED["capsize_speed"])
    print(
        f"stability boundaries at c = {float(P0['c'])} m: {np.array2string(crossings, precision=5)} m/s "
        f"(published weave {pub[0]:.5f}, capsize {pub[1]:.5f} m/s)"
    )
    stable = [(c[j], v[grid[:, j] < 0]) for j in range(len(c))]
    widest = max(stable, key=lambda s: np.ptp(s[1]) if s[1].size else -1)
    if widest[1].size:
        print(
            f"widest stable speed range on the grid: c = {widest[0]:.3f} m, "
            f"v ≈ {widest[1].min():.2f} … {widest[1].max():.2f} m/s"
        )
    _plot(out, v, c, grid, crossings)
    return grid, crossings


def _plot(out, v, c, grid, crossings):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    fig, ax = plt.subplots(figsize=(8, 5.2))
    # blue spans the stable values actually reached, red the unstable ones
    norm = TwoSlopeNorm(0.0, min(float(grid.min()), -1e-3), max(float(grid.max()), 1e-3))
    m = ax.pcolormesh(v, c, grid.T, cmap="RdBu_r", norm=norm, shading="auto")
    fig.colorbar(m, ax=ax, label="max Re(eigenvalue), 1/s")
    ax.contour(v, c, grid.T, levels=[0.0], colors="k", linewidths=1.5)
    ax.axhline(float(P0["c"]), color="k", ls=":", lw=1)
    ax.plot(
        crossings,
        np.full_like(crossings, float(P0["c"])),
        "ko",
        ms=5,
        label="weave / capsize speeds at the benchmark trail",
    )
    ax.set(
        xlabel="forward speed v, m/s",
        ylabel="trail c, m",
        title="Whipple bicycle, upright running: stable where max Re < 0 (blue)",
    )
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(out / "bicycle_stability_map.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out / 'bicycle_stability_map.png'}")


if __name__ == "__main__":
    main()
