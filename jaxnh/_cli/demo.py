"""`jaxnh demo`: the seed paper's variator derived three ways, integrated, and checked."""

from __future__ import annotations

import os
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._analysis.friction_margin import stick_margin
from jaxnh._base.atomic import atomic_save_figure
from jaxnh._cli.fit import demo_fit
from jaxnh._equations import accelerations
from jaxnh._model.profiles import Constant, Fourier
from jaxnh._solve.simulate import simulate
from jaxnh.models import balance_assist as BA, variator as V


__all__ = ["run", "equation_coefficients", "friction_limit", "real_bicycle", "plot_methods", "METHODS"]

METHODS = ("lagrange", "appell", "substituted")


def equation_coefficients(method: str, p: V.VariatorParams, w: float, t: float):
    """Coefficients (I, C, F) of `I phi1'' + C phi1' = F` as produced by autodiff.

    The formulation is treated as a black box returning phi1''; then
    `1/I = ∂phi1''/∂M1`, `C = −I ∂phi1''/∂phi1'` and `F = I phi1''(phi1' = 0)`.
    """
    mech = V.mechanism()

    def phi1dd(w, M1):
        q = p.__class__(p.J1, p.J2, p.U21, Constant(M1), p.M2)
        qd = jnp.stack([w, q.U21(t) * w])
        return accelerations(mech, jnp.zeros(2), qd, t, q, method=method)[0][0]

    M1 = p.M1(t)
    inv_I = jax.grad(phi1dd, argnums=1)(w, M1)
    I = 1.0 / inv_I
    C = -I * jax.grad(phi1dd, argnums=0)(w, M1)
    F = I * phi1dd(0.0, M1)
    return float(I), float(C), float(F)


def run(out_dir: str = "jaxnh_out", fit: bool = True, figures: bool = True) -> dict:
    """Run the demo, print the report, write figures (with `figures`, which
    needs matplotlib) and the fit's `fit.json` into `out_dir`; return the numbers."""
    os.makedirs(out_dir, exist_ok=True)
    report = {}
    p = V.default_params()
    w, t = 1.5, 0.3
    U, dU = float(p.U21(t)), float(p.U21.derivative(t))
    J1, J2 = float(p.J1), float(p.J2)
    print("jaxnh demo — the stepless friction variator (s = 2, m = 1, W = 1)")
    print(
        f"  J1 = {J1} kg·m², J2 = {J2} kg·m², U21(t) = 1 + 0.4 sin(πt), "
        f"M1 = {float(p.M1(0))} N·m, M2 = {float(p.M2(0))} N·m"
    )
    print(f"\n1. Equations of motion  I·phi1'' + C·phi1' = F  at t = {t} s, phi1' = {w} rad/s")
    print(f"   (U21 = {U:.6f}, U21' = {dU:.6f})")
    print(f"   {'derived by':<26}{'I [kg·m²]':>14}{'C [kg·m²/s]':>16}{'F [N·m]':>14}")
    paper = {
        "paper eq. (9)": (J1 + J2 * U**2, J2 * U * dU, float(p.M1(t) + U * p.M2(t))),
        "paper eq. (16) (naive)": (J1 + J2 * U**2, 2 * J2 * U * dU, float(p.M1(t) + U * p.M2(t))),
    }
    for name, (I, C, F) in paper.items():
        print(f"   {name:<26}{I:>14.10f}{C:>16.10f}{F:>14.10f}")
    coeffs = {}
    for m in METHODS:
        coeffs[m] = equation_coefficients(m, p, w, t)
        I, C, F = coeffs[m]
        print(f"   {'autodiff ' + m:<26}{I:>14.10f}{C:>16.10f}{F:>14.10f}")
    report["coefficients"] = coeffs
    print("   → 'lagrange' and 'appell' reproduce eq. (9); 'substituted' reproduces the paper's wrong eq. (16).")

    # 2. simulations against the closed form
    ts = jnp.linspace(0.0, 10.0, 501)
    w0 = 2.0
    qd0 = jnp.array([w0, p.U21(0.0) * w0])
    q_ref, qd_ref = V.closed_form(p, ts, w0=w0)
    print("\n2. Simulation over 10 s against the closed form (Dopri8, rtol = atol = 1e-12)")
    sols = {}
    for m in METHODS:
        t0 = time.perf_counter()
        sol = simulate(
            V.mechanism(), p, jnp.zeros(2), qd0, ts, method=m, rtol=1e-12, atol=1e-12, solver=diffrax.Dopri8()
        )
        jax.block_until_ready(sol.q)
        el = time.perf_counter() - t0
        err = float(max(jnp.max(jnp.abs(sol.q - q_ref)), jnp.max(jnp.abs(sol.qd - qd_ref))))
        sols[m] = sol
        report[f"error_{m}"] = err
        print(
            f"   {m:<12} max error {err:9.2e}   steps {int(sol.stats['num_steps']):5d}   {sol.message}  "
            f"({el:.2f} s incl. compile)"
        )

    # 3. energy with M1 = M2 = 0
    pf = V.VariatorParams(p.J1, p.J2, p.U21)
    tf = jnp.linspace(0.0, 200.0, 2001)
    print("\n3. Energy with M1 = M2 = 0 over 100 periods of U21 (the constraint force does no work)")
    energies = {}
    for m in METHODS:
        sol = simulate(
            V.mechanism(),
            pf,
            jnp.zeros(2),
            qd0,
            tf,
            method=m,
            rtol=1e-12,
            atol=1e-12,
            record=("energy",),
            solver=diffrax.Dopri8(),
        )
        E = np.asarray(sol.energy)
        energies[m] = E
        drift = float(np.max(np.abs(E - E[0])) / E[0])
        report[f"energy_drift_{m}"] = drift
        print(f"   {m:<12} max |T − T0| / T0 = {drift:9.2e}")

    if figures:
        fig_path = os.path.join(out_dir, "variator_methods.png")
        _save(plot_methods(ts, q_ref, qd_ref, sols, tf, energies), fig_path)
        print(f"\n   figure: {fig_path}")
        report["figure"] = fig_path
    report["friction"] = friction_limit(p)
    if fit:
        report["fit"] = demo_fit(out_dir, figures=figures)
        report["real_bicycle"] = real_bicycle()
    return report


def real_bicycle() -> dict:
    """Section 6 of the demo: the roll-rate gain slope κ of TU Delft's balance-assist bicycle fitted
    to its measured weave eigenvalues at 1.66–4.44 m/s (`jaxnh.models.balance_assist`). Prints and
    returns, per gain setting: κ (N·m·s/rad per m/s), its standard error and 95 % interval, and the
    RMS residual (1/s); and the seconds taken."""
    print("\n6. A real bicycle: roll-rate feedback steer control fitted to measured weave eigenvalues")
    print("   (TU Delft balance-assist bicycle; data: GitHub mechmotum/fall-probability-paper, public domain)")
    t0 = time.perf_counter()
    fits, _ = BA.fit_measurements()
    elapsed = time.perf_counter() - t0
    out: dict = {"seconds": elapsed}
    for gain, f in fits.items():
        lo, hi = f.interval
        print(
            f"   gain {gain:2d}: κ = {f.kappa:.3f} ± {f.std:.3f} N·m·s/rad per m/s (95 %: {lo:.3f}–{hi:.3f}), "
            f"RMS {f.rms:.2f} 1/s"
        )
        out[gain] = dict(kappa=f.kappa, std=f.std, interval=f.interval, rms=f.rms)
    print(f"   ({elapsed:.1f} s, compilation included; the documentation's page: Fitting a real bicycle)")
    return out


def friction_limit(p: V.VariatorParams, w0: float = 2.0) -> dict:
    """Section 4 of the demo: the roller held by friction (`jaxnh.models.variator.friction_mechanism`;
    radius 50 mm, pressed with 40 N, μs = 0.3, μk = 0.25). The default ratio law keeps it rolling;
    the same law cycled twice as fast needs more tangential force than friction gives, and it slips.
    Prints and returns, per ratio period (s): the largest |F|/(μs N) of the rolling motion
    (`stick_margin`), the transitions of the friction solve (s), the slip time (s) and the
    energy dissipated by slip (J)."""
    mech = V.friction_mechanism()
    ts = jnp.linspace(0.0, 4.0, 401)
    q0 = jnp.zeros(2)
    print("\n4. Friction limit: the roller (r = 50 mm) pressed with N = 40 N, μs = 0.3, μk = 0.25, over 4 s")
    out = {}
    for period in (2.0, 1.0):
        U21 = Fourier(1.0, cos=[0.0], sin=[0.4], period=period)
        drive = V.DriveParams(V.VariatorParams(p.J1, p.J2, U21, p.M1, p.M2), 0.05, 40.0, 0.3, 0.25)
        qd0 = jnp.array([w0, U21(0.0) * w0])
        peak = float(jnp.max(stick_margin(mech, drive, q0, qd0, ts, rtol=1e-10, atol=1e-12).utilisation))
        sol = simulate(mech, drive, q0, qd0, ts, rtol=1e-10, atol=1e-12)
        assert sol.contacts is not None  # the mechanism has a contact
        c = sol.contacts
        moves = c.transitions("roller")
        print(f"   U21 = 1 + 0.4 sin(2πt/{period:g}): rolling would need up to {peak:.3f} × μs N")
        if not moves:
            print("     → it keeps rolling")
        else:
            print("     → " + ", ".join(f"{kind} at {t:.4f} s" for t, kind in moves))
            print(
                f"       slipping {float(c.slip_time[0]):.4f} s in all, dissipating "
                f"{float(c.dissipated_energy[0]):.4f} J (see docs: Friction)"
            )
        out[period] = dict(
            peak_utilisation=peak,
            transitions=moves,
            slip_time=float(c.slip_time[0]),
            dissipated=float(c.dissipated_energy[0]),
        )
    return out


def _save(fig, path: str) -> str:
    """Write `fig` to `path` (through a temporary file, renamed when complete) and close it."""
    try:
        return atomic_save_figure(fig, path, dpi=110)
    finally:
        import matplotlib.pyplot as plt  # optional dependency (the plot extra)

        plt.close(fig)


def plot_methods(ts, q_ref, qd_ref, sols, tf, energies, *, fig=None):
    """The demo's figure: input shaft speed by each method against the closed
    form (rad/s), the error against the closed form (rad), and T/T(0) with
    the torques off.

    Arguments:
        ts: report times (n,), s; q_ref, qd_ref: the closed form (n, 2).
        sols: {method: Solution} at ts; tf, energies: times (s) and
            {method: energy (J)} of the torque-free runs.
        fig: a matplotlib Figure to draw into (cleared); default a new one
            from `matplotlib.pyplot`. The backend is never changed.

    Returns:
        The matplotlib Figure.
    """
    if fig is None:
        import matplotlib.pyplot as plt  # optional dependency (the plot extra)

        fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    else:
        fig.clear()
        ax = fig.subplots(1, 3)
    colors = {"lagrange": "C0", "appell": "C2", "substituted": "C3"}
    ax[0].plot(ts, qd_ref[:, 0], "k-", lw=3, alpha=0.3, label="closed form")
    for m, sol in sols.items():
        ax[0].plot(ts, sol.qd[:, 0], "--" if m != "substituted" else "-", color=colors[m], label=m)
    ax[0].set(xlabel="t [s]", ylabel="phi1' [rad/s]", title="input shaft speed, M1 = 0.3, M2 = −0.1 N·m")
    ax[0].legend()
    for m, sol in sols.items():
        err = np.max(np.abs(np.asarray(sol.q) - np.asarray(q_ref)), axis=1) + 1e-17
        ax[1].semilogy(ts, err, color=colors[m], label=m)
    ax[1].set(xlabel="t [s]", ylabel="max |q − q_exact| [rad]", title="error against the closed form")
    ax[1].legend()
    first = np.asarray(tf) <= 20.0
    for m, E in energies.items():
        ax[2].plot(np.asarray(tf)[first], (E / E[0])[first], color=colors[m], label=m)
    ax[2].set(xlabel="t [s]", ylabel="T / T(0)", title="kinetic energy, M1 = M2 = 0 (first 10 periods)")
    ax[2].legend()
    fig.tight_layout()
    return fig
