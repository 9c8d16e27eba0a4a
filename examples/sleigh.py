"""The Chaplygin sleigh against its closed form.

Run:  python examples/sleigh.py [OUT_DIR]        (default jaxnh_out/)

A body on a knife edge whose mass centre lies a = 0.5 m ahead of the blade,
pushed off slowly while turning: the turning rate is converted into forward
speed (v' = a ω², I ω' = −m a v ω). Integrates Lagrange's and Appell's
equations (T and S from `jaxnh.rigid`), prints the error against the closed
form and writes sleigh.png (the path, and v, ω against time).
"""

import sys
from pathlib import Path

import jax.numpy as jnp
import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import sleigh  # noqa: E402


out = Path(sys.argv[1] if len(sys.argv) > 1 else "jaxnh_out")
out.mkdir(parents=True, exist_ok=True)
p = sleigh.default_params()  # m = 1 kg, I_C = 0.1 kg m², a = 0.5 m
q0 = jnp.array([0.0, 0.0, -0.7])  # blade at the origin, heading −0.7 rad
v0, w0 = 0.2, 1.0  # m/s, rad/s
ts = jnp.linspace(0.0, 10.0, 201)
v, w, th = sleigh.closed_form(p, ts, v0, w0, th0=-0.7)

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
for method, style in (("lagrange", "-"), ("appell", "--")):
    sol = nh.simulate(
        sleigh.mechanism(),
        p,
        q0,
        sleigh.initial_velocities(q0, v0, w0),
        ts,
        method=method,
        rtol=1e-11,
        atol=1e-12,
        record=("energy",),
    )
    err = max(
        np.abs(sleigh.forward_speed(sol.q, sol.qd) - v).max(),
        np.abs(sol.qd[:, 2] - w).max(),
        np.abs(sol.q[:, 2] - th).max(),
    )
    print(f"{method:<8} max error vs closed form {err:.1e}, energy change {float(np.ptp(sol.energy)):.1e} J")
    G = sol.q[:, :2] + p["a"] * jnp.stack([jnp.cos(sol.q[:, 2]), jnp.sin(sol.q[:, 2])], axis=1)
    ax1.plot(sol.q[:, 0], sol.q[:, 1], style, label=f"blade ({method})")
    ax1.plot(G[:, 0], G[:, 1], style, label=f"mass centre ({method})")
ax1.set(xlabel="x (m)", ylabel="y (m)", title="Chaplygin sleigh: path", aspect="equal")
ax1.legend(fontsize=8)
ax2.plot(ts, v, label="forward speed v (m/s)")
ax2.plot(ts, w, label="turning rate ω (rad/s)")
ax2.plot(ts[::10], sleigh.forward_speed(sol.q, sol.qd)[::10], "k.", label="simulated (appell)")
ax2.plot(ts[::10], sol.qd[::10, 2], "k.")
ax2.set(xlabel="time (s)", title="closed form (lines) and simulation (dots)")
ax2.legend(fontsize=8)
fig.tight_layout()
fig.savefig(out / "sleigh.png", dpi=120)
print(f"figure in {out}/sleigh.png")
