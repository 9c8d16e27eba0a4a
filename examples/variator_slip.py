"""The friction variator slips when its ratio changes too fast.

Run:  python examples/variator_slip.py [OUTDIR]     (default OUTDIR jaxnh_out/)

The seed paper's variator with the torques off: shaft 1 (J1) drives shaft 2
(J2) through a roller of radius r that rolls at the radius ρ(t) on shaft 2.
The roller transmits torque only by friction: its rolling constraint, written
as the slip velocity of the contact in m/s,

    r φ1' − ρ(t) φ2' = 0                                  (paper eq. 4 times ρ)

is held by a `jaxnh.FrictionContact` with the pressing force N and the
coefficients μs, μk. While rolling, the tangential force it needs is
λ = −J1 J2 U U' φ1' / (r (J1 + J2 U²)), U = U21 = r/ρ (from eqs. 8–9): a fast
ratio change at speed needs a large force, and the roller slips where
|λ| = μs N.

The script
1. changes the ratio from 1 to 2 in 0.5 s at 100 rad/s with N = 150 N and
   reports where the drive slips, for how long, and the energy lost (which the
   slip dissipates: the constraint's force does no work), with both
   formulations;
2. checks the slip onset against the closed-form condition
   J1 J2 |U'| |φ1'| = μs N ρ (J1 + J2 U²);
3. differentiates the slip time and the energy lost with respect to N
   through the transitions, against central differences;
4. a design study with `jaxnh.stick_margin`: the smallest pressing force and
   the fastest ratio change that keep the drive rolling, each confirmed by the
   friction solve 1 % on either side;
5. writes `variator_slip.png` (surface speeds and |λ|/(μs N) over time).
"""

from __future__ import annotations

import pathlib
import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh


def rho(t, p):
    """Contact radius on shaft 2, m: a cosine ramp from rho0 to rho1 over [0, Tr] s."""
    s = jnp.clip(t / p["Tr"], 0.0, 1.0)
    return p["rho0"] + (p["rho1"] - p["rho0"]) * 0.5 * (1 - jnp.cos(jnp.pi * s))


def kinetic(q, qd, t, p):
    """T = ½ (J1 φ1'² + J2 φ2'²), J."""
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def rolling(q, qd, t, p):
    """Slip velocity of the roller, m/s."""
    return jnp.stack([p["r"] * qd[0] - rho(t, p) * qd[1]])


ROLLER = nh.FrictionContact(
    0,
    normal_force=lambda q, qd, t, p: p["N"],  # N
    mu_static=lambda q, qd, t, p: p["mu_s"],
    mu_kinetic=lambda q, qd, t, p: 0.8 * p["mu_s"],
    name="roller",
)
VARIATOR = nh.Mechanism(kinetic, constraints=rolling, contacts=(ROLLER,), names=("phi1", "phi2"))
PARAMS = {"J1": 0.02, "J2": 0.05, "r": 0.05, "rho0": 0.05, "rho1": 0.025, "Tr": 0.5, "N": 150.0, "mu_s": 0.3}
W0 = 100.0  # rad/s
Q0 = jnp.zeros(2)
QD0 = jnp.array([W0, W0 * PARAMS["r"] / PARAMS["rho0"]])
TS = jnp.linspace(0.0, 1.0, 401)


def run(p, method="appell", **kw):
    return nh.simulate(VARIATOR, p, Q0, QD0, TS, method=method, rtol=1e-10, atol=1e-12, step_ts=[p["Tr"]], **kw)


def onset_closed_form(p) -> float:
    """First root of J1 J2 |U'| φ1' − μs N ρ (J1 + J2 U²), with φ1' = w0 √(I(0)/I(t)) from eq. (9)."""
    ts = np.linspace(1e-9, p["Tr"], 20001)
    r, rh = p["r"], np.asarray(jax.vmap(lambda t: rho(t, p))(ts))
    drho = np.asarray(jax.vmap(jax.grad(lambda t: rho(t, p)))(ts))
    U, dU = r / rh, -r * drho / rh**2
    inertia = p["J1"] + p["J2"] * U**2
    w = W0 * np.sqrt((p["J1"] + p["J2"] * (r / p["rho0"]) ** 2) / inertia)
    f = p["J1"] * p["J2"] * np.abs(dU) * w - p["mu_s"] * p["N"] * rh * inertia
    i = int(np.argmax(f > 0))
    # bisection on the closed form between the bracketing grid points
    lo, hi = ts[i - 1], ts[i]

    def g(t):
        rh_ = float(rho(t, p))
        dU_ = -r * float(jax.grad(lambda s: rho(s, p))(t)) / rh_**2
        I_ = p["J1"] + p["J2"] * (r / rh_) ** 2
        w_ = W0 * np.sqrt((p["J1"] + p["J2"] * (r / p["rho0"]) ** 2) / I_)
        return p["J1"] * p["J2"] * abs(dU_) * w_ - p["mu_s"] * p["N"] * rh_ * I_

    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) < 0 else (lo, mid)
    return 0.5 * (lo + hi)


def main(outdir: pathlib.Path) -> None:
    outdir.mkdir(parents=True, exist_ok=True)
    print("1. Ratio 1 → 2 in 0.5 s at 100 rad/s, N = 150 N, μs = 0.3, μk = 0.24")
    for method in ("lagrange", "appell"):
        t0 = time.perf_counter()
        sol = run(PARAMS, method, record=("multipliers", "energy"))
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        run(PARAMS, method, record=("multipliers", "energy")).q.block_until_ready()
        again = time.perf_counter() - t0
        print(f"   {method}: first call {first:.1f} s (compile), then {1e3 * again:.1f} ms")
        print("   " + sol.contacts.summary().replace("\n", "\n   "))
        print(f"   transitions {sol.contacts.transitions('roller')}")
        print(f"   energy lost {float(sol.energy[0] - sol.energy[-1]):.9f} J")
    print("\n2. Slip onset against the closed-form condition")
    t_on = sol.contacts.transitions("roller")[0][0]
    exact = onset_closed_form(PARAMS)
    print(f"   solve {t_on:.12f} s, closed form {exact:.12f} s, difference {t_on - exact:.1e} s")

    print("\n3. Derivatives through the transitions, with respect to N")

    def outputs(N):
        c = run({**PARAMS, "N": N}).contacts
        return jnp.stack([c.slip_time[0], c.dissipated_energy[0]])

    N = jnp.asarray(PARAMS["N"])
    J = jax.jit(jax.jacrev(outputs))(N)
    fd = (outputs(N + 0.1) - outputs(N - 0.1)) / 0.2
    print(f"   d(slip time)/dN  = {float(J[0]):.9e} s/N   (central difference {float(fd[0]):.9e})")
    print(f"   d(energy lost)/dN = {float(J[1]):.9e} J/N   (central difference {float(fd[1]):.9e})")

    print("\n4. Design with the stick margin of the rolling motion")
    margin = nh.stick_margin(VARIATOR, PARAMS, Q0, QD0, TS, rtol=1e-10, atol=1e-12, step_ts=[PARAMS["Tr"]])
    N_min = PARAMS["N"] * float(jnp.max(margin.utilisation))
    print(f"   smallest margin at N = 150 N: {float(margin.minimum[0]):+.4f}; smallest pressing force {N_min:.4f} N")
    for factor in (0.99, 1.01):
        print(f"     N = {factor:.2f} N_min: {run({**PARAMS, 'N': factor * N_min}).contacts.transitions('roller')}")

    def smallest_margin(Tr):
        m = nh.stick_margin(
            VARIATOR,
            {**PARAMS, "Tr": Tr},
            Q0,
            QD0,
            TS,
            rtol=1e-10,
            atol=1e-12,
            step_ts=[Tr],
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
        )
        return m.minimum[0]

    value_and_slope = jax.jit(jax.value_and_grad(smallest_margin))
    Tr = jnp.asarray(0.5, dtype=jnp.float64)
    for _ in range(6):
        value, slope = value_and_slope(Tr)
        Tr = Tr - value / slope
    print(f"   fastest ramp that keeps rolling at N = 150 N: Tr = {float(Tr):.9f} s")
    for factor in (0.99, 1.01):
        print(f"     Tr = {factor:.2f} x that: {run({**PARAMS, 'Tr': factor * Tr}).contacts.transitions('roller')}")

    try:
        import matplotlib  # optional dependency (the plot extra)

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # optional dependency (the plot extra)
    except ImportError:
        print("\n(matplotlib not installed: no figure)")
        return
    sol = run(PARAMS, record=("multipliers",))
    fig, axes = plt.subplots(2, 1, figsize=(7, 4.6), sharex=True)
    for ax in axes:
        for a, b in sol.contacts.slip_intervals("roller"):
            ax.axvspan(a, b, color="0.9")
    axes[0].plot(TS, PARAMS["r"] * sol.qd[:, 0], label="r φ1'")
    axes[0].plot(TS, jax.vmap(lambda t, w: rho(t, PARAMS) * w)(TS, sol.qd[:, 1]), "--", label="ρ(t) φ2'")
    axes[0].set(ylabel="surface speed (m/s)", title="Variator, ratio 1 → 2 in 0.5 s: slipping (shaded)")
    axes[0].legend()
    axes[1].plot(TS, jnp.abs(sol.multipliers[:, 0]) / (PARAMS["mu_s"] * PARAMS["N"]))
    axes[1].axhline(1.0, color="k", lw=0.8)
    axes[1].set(xlabel="time t (s)", ylabel="|λ| / (μs N)", ylim=(0, 1.1))
    fig.tight_layout()
    fig.savefig(outdir / "variator_slip.png", dpi=120)
    print(f"\nwrote {outdir / 'variator_slip.png'}")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "jaxnh_out"))
