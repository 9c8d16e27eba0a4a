"""A knife edge on an inclined plane against its closed form.

Run:  python examples/knife_edge.py [OUT_DIR]     (default jaxnh_out/)

Released at rest, spinning at ω, the blade turns uniformly and its contact
point traces x = (g sin α/2ω²) sin² ωt, y = (g sin α/2ω²)(ωt − ½ sin 2ωt):
it does not slide down the slope but drifts across it. Lagrange's
equations with multipliers handle all headings; so does Appell's default,
which re-chooses the independent velocities when φ nears π/2 (a fixed split
(ẋ, φ̇ independent) would fail there with STATUS.singular_split). Writes
knife_edge.png.
"""

import sys
from pathlib import Path

import jax.numpy as jnp
import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import knife_edge  # noqa: E402


out = Path(sys.argv[1] if len(sys.argv) > 1 else "jaxnh_out")
out.mkdir(parents=True, exist_ok=True)
p = knife_edge.default_params()  # m = 1 kg, J = 0.2 kg m², α = 0.3 rad
omega = 1.2  # initial spin, rad/s
ts = jnp.linspace(0.0, 15.0, 301)
sol = nh.simulate(
    knife_edge.mechanism(),
    p,
    jnp.zeros(3),
    jnp.array([0.0, 0.0, omega]),
    ts,
    method="lagrange",
    rtol=1e-11,
    atol=1e-12,
    record=("multipliers",),
)
q, _ = knife_edge.closed_form(p, ts, omega)
print(f"lagrange over {float(ts[-1])} s: max error vs closed form {float(np.abs(sol.q - q).max()):.1e}")
ts_a = jnp.linspace(0.0, 1.2, 25)  # φ < π/2: the split is regular
sol_a = nh.simulate(
    knife_edge.mechanism(), p, jnp.zeros(3), jnp.array([0.0, 0.0, omega]), ts_a, method="appell", rtol=1e-11, atol=1e-12
)
q_a, _ = knife_edge.closed_form(p, ts_a, omega)
print(f"appell over {float(ts_a[-1])} s: max error {float(np.abs(sol_a.q - q_a).max()):.1e}")

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
ax1.plot(q[:, 1], q[:, 0], "k-", lw=3, alpha=0.3, label="closed form")
ax1.plot(sol.q[:, 1], sol.q[:, 0], "tab:blue", label="lagrange")
ax1.plot(sol_a.q[:, 1], sol_a.q[:, 0], "r.", label="appell (φ < π/2)")
ax1.invert_yaxis()
ax1.set(xlabel="y, across the slope (m)", ylabel="x, down the slope (m)", title="knife edge on an incline")
ax1.legend(fontsize=8)
ax2.plot(ts, sol.multipliers[:, 0], label="multiplier λ (N): sideways blade force")
ax2.set(xlabel="time (s)", title="constraint force")
ax2.legend(fontsize=8)
fig.tight_layout()
fig.savefig(out / "knife_edge.png", dpi=120)
print(f"figure in {out}/knife_edge.png")
