"""A rolling disc: steady motions and the stability of upright rolling.

Run:  python examples/rolling_disc.py [OUT_DIR]   (default jaxnh_out/)

A uniform thin disc (m = 1 kg, r = 0.3 m) rolling without slip. Prints the
critical spin of upright rolling from the linearised model next to the
analytic √(g/(3r)), simulates a slightly disturbed upright disc below and
above it, and a steady circular motion against its closed form. Writes
rolling_disc.png.
"""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import disc  # noqa: E402


out = Path(sys.argv[1] if len(sys.argv) > 1 else "jaxnh_out")
out.mkdir(parents=True, exist_ok=True)
p = disc.default_params()
mech = disc.mechanism()
crit = float(disc.critical_spin(p))

# linearised upright rolling over a range of spins, in one compiled vmapped call
spins = jnp.linspace(0.0, 3 * crit, 60)
lin = jax.jit(jax.vmap(lambda s: disc.linearized(*disc.upright(s, p), p)))(spins)
eig = np.array([np.linalg.eigvals(np.asarray(A)) for A in lin.A])
unstable = eig.real.max(axis=1) > 1e-9
lo, hi = float(spins[unstable].max()), float(spins[~unstable].min())
print(
    f"critical spin: analytic √(m g r I1 / (I3 (I3 + m r²))) = {crit:.6f} rad/s "
    f"(= √(g/3r) = {np.sqrt(9.81 / 0.9):.6f}); "
    f"the linearised model turns stable between {lo:.4f} and {hi:.4f} rad/s on this grid"
)

fig, axs = plt.subplots(1, 3, figsize=(14, 4))
axs[0].plot(spins, eig.real, "k.", ms=3)
axs[0].plot(spins, np.abs(eig.imag), ".", color="tab:blue", ms=3)
axs[0].axvline(crit, color="tab:red", label="analytic boundary")
axs[0].set(xlabel="spin Ω (rad/s)", ylabel="eigenvalues: real (black), |imag| (blue)", title="upright rolling")
axs[0].legend(fontsize=8)

# disturbed upright rolling below and above the boundary (nonlinear)
ts = jnp.linspace(0.0, 4.0, 201)
for s, colour in ((0.8 * crit, "tab:red"), (1.5 * crit, "tab:green")):
    q0, qd0 = disc.upright(s, p)
    sol = nh.simulate(mech, p, q0, qd0.at[3].set(0.05), ts, method="appell", rtol=1e-10, atol=1e-12, throw=False)
    axs[1].plot(ts, sol.q[:, 3], color=colour, label=f"Ω = {s / crit:.1f} Ω_crit")
axs[1].set(
    xlabel="time (s)", ylabel="lean φ (rad)", ylim=(-1.6, 1.6), title="upright rolling, lean rate kick 0.05 rad/s"
)
axs[1].legend(fontsize=8)

# a steady circular motion: lean 0.3 rad, yaw rate 2 rad/s
lean, yaw_rate = 0.3, 2.0
q0, qd0 = disc.steady_state(lean, yaw_rate, p)
ts = jnp.linspace(0.0, 5.0, 101)
sol = nh.simulate(mech, p, q0, qd0, ts, method="appell", rtol=1e-11, atol=1e-12)
exact = disc.steady_path(p, ts, lean, yaw_rate)
print(
    f"steady motion (lean {lean} rad, yaw rate {yaw_rate} rad/s, spin {float(qd0[4]):.6f} rad/s): "
    f"max error vs closed form {float(np.abs(sol.q - exact).max()):.1e}"
)
axs[2].plot(exact[:, 0], exact[:, 1], "k-", lw=3, alpha=0.3, label="closed form")
axs[2].plot(sol.q[:, 0], sol.q[:, 1], "tab:blue", label="simulated contact path")
axs[2].set(xlabel="x (m)", ylabel="y (m)", aspect="equal", title="steady circular rolling")
axs[2].legend(fontsize=8)
fig.tight_layout()
fig.savefig(out / "rolling_disc.png", dpi=120)
print(f"figure in {out}/rolling_disc.png")
