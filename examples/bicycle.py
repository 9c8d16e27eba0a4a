"""The Whipple bicycle: the benchmark of Meijaard et al. (2007) from T, contacts and autodiff.

Run:  python examples/bicycle.py [OUT_DIR]        (default jaxnh_out/)

Builds the bicycle from its four rigid bodies (`jaxnh.models.bicycle`),
linearises upright running at 0–10 m/s by automatic differentiation, prints
M, C1, K0, K2, the eigenvalues at 0 and 5 m/s and the weave and capsize
speeds next to the published ones, and simulates the nonlinear bicycle after
a roll-rate kick at 5 m/s (self-stable) and 2 m/s (it falls: a `diffrax.Event`
stops the run when the lean passes 45°, and the event time is checked against a
root of the dense output). Figures:
bicycle_eigenvalues.png, bicycle_nonlinear.png.
"""

import sys
import time
from pathlib import Path

import diffrax
import jax.numpy as jnp
import matplotlib
import optimistix as optx


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import bicycle  # noqa: E402


out = Path(sys.argv[1] if len(sys.argv) > 1 else "jaxnh_out")
out.mkdir(parents=True, exist_ok=True)
p = bicycle.default_params()  # Table 1 of the paper
pub = bicycle.PUBLISHED

# --- linearised: all speeds in one compiled, vmapped call --------------------------------
speeds = jnp.concatenate([jnp.array([0.0, 1.0]), jnp.linspace(0.0, 10.0, 201)])
t0 = time.perf_counter()
lin = bicycle.linearized_speeds(speeds, p, "lagrange")  # Linearization, batched over speeds
print(f"linearised at {speeds.size} speeds in {time.perf_counter() - t0:.1f} s (tracing and compiling included)")
mats = bicycle.canonical_from(lin, p["g"])  # first two speeds are 0 and 1 m/s
for k in ("M", "C1", "K0", "K2"):
    err = np.abs(np.asarray(mats[k]) - np.asarray(pub[k])).max()
    print(f"{k:>2} = {np.array2string(np.asarray(mats[k]), precision=14)}   |Δ published| = {err:.1e}")
vw = bicycle.weave_speed(p, matrices=mats)
vc = bicycle.capsize_speed(p, matrices=mats)
print(f"weave speed   {vw:.14f} m/s   published {pub['weave_speed']:.14f}")
print(f"capsize speed {vc:.14f} m/s   published {pub['capsize_speed']:.14f}")
ls = np.array(bicycle.LEAN_STEER)
eig = np.array([np.linalg.eigvals(np.asarray(A)[ls][:, ls]) for A in lin.A[2:]])
for v, key in ((0.0, "eigenvalues_v0"), (5.0, "eigenvalues_v5")):
    i = int(np.argmin(np.abs(np.asarray(speeds[2:]) - v)))
    print(
        f"eigenvalues at {v} m/s: {np.sort_complex(eig[i])}\n          published: {np.sort_complex(np.array(pub[key]))}"
    )

fig, ax = plt.subplots(figsize=(7, 4.5))
v = np.asarray(speeds[2:])
ax.plot(v, eig.real, "k.", ms=2)
ax.plot(v, np.abs(eig.imag), ".", color="tab:blue", ms=2)
ax.axvspan(vw, vc, color="tab:green", alpha=0.15, label=f"self-stable {vw:.3f}–{vc:.3f} m/s")
ax.axhline(0, color="gray", lw=0.5)
ax.set(
    xlabel="forward speed v (m/s)",
    ylabel="eigenvalues (1/s): real (black), |imag| (blue)",
    ylim=(-10, 10),
    title="Whipple bicycle benchmark, linearised by autodiff",
)
ax.legend(loc="lower left")
fig.tight_layout()
fig.savefig(out / "bicycle_eigenvalues.png", dpi=120)

# --- nonlinear: a roll-rate kick at 5 m/s and at 2 m/s -----------------------------------
system = bicycle.system()  # 8 coordinates, pitch dependent
mech = bicycle.mechanism("lagrange")  # front contact as ġ = 0, multipliers
FALLEN = np.pi / 4  # stop the run when the lean passes 45°


def fallen(t, y, params, **kwargs):
    """Event condition: zero when |roll| reaches 45° (y = (q, qd) of the mechanism)."""
    q, _ = y
    return jnp.abs(q[bicycle.ROLL]) - FALLEN


event = diffrax.Event(fallen, root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
fig, ax = plt.subplots(figsize=(7, 4.5))
for v0, T, colour in ((5.0, 5.0, "tab:green"), (2.0, 4.0, "tab:red")):
    q, qd = bicycle.upright(v0, p)
    q0, qd0 = system.initial_state(q, qd.at[bicycle.ROLL].set(0.5), 0.0, p)
    ts = jnp.linspace(0.0, T, 201)
    t0 = time.perf_counter()
    # diffrax's Dopri8 loops over its stages, so this large vector field is compiled once;
    # dense output and the event need diffrax's adjoint (chosen automatically)
    sol = nh.simulate(
        mech,
        p,
        q0,
        qd0,
        ts,
        method="lagrange",
        rtol=1e-10,
        atol=1e-12,
        solver=diffrax.Dopri8(),
        record=("energy",),
        event=event,
        saveat=diffrax.SaveAt(ts=ts, t1=True, dense=True),
    )
    reached = np.isfinite(np.asarray(sol.ts))  # after an event: the report times reached, then the event time
    t_end = float(np.max(np.asarray(sol.ts)[reached]))
    print(
        f"v = {v0} m/s: {int(sol.stats['num_steps'])} steps, {time.perf_counter() - t0:.1f} s, "
        f"energy drift {float(np.ptp(np.asarray(sol.energy)[reached])):.1e} J, "
        f"final roll {float(np.asarray(sol.q)[reached][-1, bicycle.ROLL]):+.4f} rad at t = {t_end:.6f} s"
    )
    if bool(np.any(np.asarray(sol.event_mask))):
        # the event time against a root of the dense output, by bisection on |roll(t)| − 45°
        lo, hi = t_end - 0.05, min(t_end + 0.05, T)
        g = lambda t: abs(float(sol.evaluate(t)[0][bicycle.ROLL])) - FALLEN  # noqa: E731
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if g(mid) < 0 else (lo, mid)
        print(
            f"  fell past 45° at t = {t_end:.10f} s (event); dense-output root {0.5 * (lo + hi):.10f} s, "
            f"|Δ| = {abs(t_end - 0.5 * (lo + hi)):.1e} s"
        )
    t_plot, q_plot = np.asarray(sol.ts)[reached], np.asarray(sol.q)[reached]
    ax.plot(t_plot, q_plot[:, bicycle.ROLL], color=colour, label=f"roll, v = {v0} m/s")
    ax.plot(t_plot, q_plot[:, bicycle.STEER], "--", color=colour, label=f"steer, v = {v0} m/s")
ax.axhline(FALLEN, color="gray", lw=0.5)
ax.set(
    xlabel="time (s)",
    ylabel="angle (rad)",
    title="Whipple bicycle after a 0.5 rad/s roll-rate kick (stopped at 45° lean)",
    ylim=(-0.6, 1.2),
)
ax.legend()
fig.tight_layout()
fig.savefig(out / "bicycle_nonlinear.png", dpi=120)
print(f"figures in {out}/")
