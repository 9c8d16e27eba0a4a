"""Optimal ratio law: start the variator's output shaft with least motor energy.

Run:  python examples/optimal_ratio.py [OUTDIR] [--steps N]     (default OUTDIR jaxnh_out/)

The problem. The variator starts from rest. A torque-controlled motor drives
shaft 1 with a constant M1 = 0.3 N·m; shaft 2 carries a constant load
M2 = −0.1 N·m. The ratio U21(t), which the roller's geometry keeps within
[0.4, 2.5], is ours to choose. Bring shaft 2 to ω2 = 10 rad/s at T = 4 s
drawing the least motor energy E = ∫ M1 φ1' dt = M1 φ1(T) (J), without the
contact multiplier |λ| (tangential contact force × roller radius) exceeding
0.5 N·m — a slipping limit.

Why there is something to gain: the constraint does no work, so
E = T(T) + |M2| φ2(T): the kinetic energy at the end, ½ (J1/U21(T)² + J2) ω2²,
plus the work against the load, |M2| ∫ ω2 dt. A law that ends at a high
ratio (shaft 1 slow) and keeps ω2 low until late spends less — limited by
the contact force that a fast ratio change demands. The optimum found does
just that: a high ratio first (both shafts slow, little motor work), then a
low ratio that lets shaft 1 spin up like a flywheel, then a fast rise of the
ratio that hands shaft 1's kinetic energy to shaft 2, as fast as the
contact-force limit allows.

Baseline: the constant ratio that reaches the target speed exactly (found
by root-finding). Design: U21(t) = Bounded(Chebyshev(8 coefficients)),
optimised with optax's Adam by gradients through diffrax, with quadratic
penalties on the terminal speed and on |λ| above the limit, tightened in
three stages (weights 1e2, 1e3, 1e4). Prints the baseline and the optimum
and writes `optimal_ratio.png` (laws, speeds, contact multiplier) and
`optimal_ratio_history.png` (objective vs step).

A caution about gradients through an adaptive solver: they are the exact
derivatives of the *discrete* solution along the steps chosen for the current
law. At the constant baseline the motion is a polynomial in t that the
Runge–Kutta method integrates exactly, so the solver takes 4 steps over 4 s;
those steps cannot resolve a perturbation like T_7(t), and the gradient with
respect to the high Chebyshev coefficients is wrong there (it is right again
as soon as the law varies and the steps shorten). Adam's first, normalised
step moves off the constant law regardless; the gradient is checked against
central differences at a generic law below (and in tests/test_design.py).
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy.optimize import brentq

import jaxnh as nh
from jaxnh.design import Bounded, Chebyshev, fd_gradient, optimize
from jaxnh.models import variator


MECH = variator.mechanism()
J1, J2 = 0.02, 0.05  # kg·m²
M1, M2 = 0.3, -0.1  # motor and load torque, N·m
U_MIN, U_MAX = 0.4, 2.5  # reachable ratios
T_END = 4.0  # s
W_TARGET = 10.0  # rad/s, output shaft speed at T_END
LAMBDA_MAX = 0.5  # N·m, contact multiplier limit
N_COEF = 8  # Chebyshev coefficients of the (inner) ratio law
TS = jnp.linspace(0.0, T_END, 161)  # report times: the force limit is checked here
RTOL = 1e-8


def ratio_law(coef) -> Bounded:
    """U21(t) in (U_MIN, U_MAX) from unconstrained Chebyshev coefficients."""
    return Bounded(Chebyshev(coef, 0.0, T_END), U_MIN, U_MAX)


def constant_law(U: float, n: int = N_COEF):
    """Coefficients of the constant law U21 = U."""
    return jnp.zeros(n).at[0].set(Bounded.inverse(U, U_MIN, U_MAX))


def run(coef, ts=TS, rtol=RTOL):
    """Start-up from rest with the ratio law `coef`; a `Solution` with multipliers."""
    p = variator.VariatorParams(J1=J1, J2=J2, U21=ratio_law(coef), M1=M1, M2=M2)
    return nh.simulate(
        MECH,
        p,
        jnp.zeros(2),
        jnp.zeros(2),
        ts,
        record=("multipliers",),
        rtol=rtol,
        atol=rtol * 1e-2,
        max_steps=4096,
        throw=False,
    )


def metrics(coef, ts=TS):
    """Motor energy E (J), final output speed ω2(T) (rad/s), peak |λ| (N·m) on `ts`."""
    sol = run(coef, ts)
    return {
        "energy": M1 * sol.q[-1, 0],
        "w2": sol.qd[-1, 1],
        "lam_max": jnp.max(jnp.abs(sol.multipliers)),
        "ok": sol.success,
    }


def objective(coef, weight, energy_ref=1.0, rtol=RTOL):
    """E / E_ref + weight · [((ω2(T) − ω*)/ω*)² + mean((|λ|/λ_max − 1)₊²)] (dimensionless)."""
    sol = run(coef, rtol=rtol)
    energy = M1 * sol.q[-1, 0]
    miss = (sol.qd[-1, 1] - W_TARGET) / W_TARGET
    over = jax.nn.relu(jnp.abs(sol.multipliers[:, 0]) / LAMBDA_MAX - 1.0)
    return energy / energy_ref + weight * (miss**2 + jnp.mean(over**2))


def baseline():
    """The constant ratio that reaches ω2(T) = ω* exactly; (U, its coefficients)."""
    w2 = jax.jit(lambda U: metrics(constant_law(U))["w2"])
    U = brentq(lambda U: float(w2(U)) - W_TARGET, 1.0, 1.3, xtol=1e-13)
    return U, constant_law(U)


STAGES = ((1e2, 0.1), (1e3, 0.03), (1e4, 0.01))  # (penalty weight, initial learning rate)


def design(coef0, energy_ref, steps=300, stages=STAGES, log=print):
    """Penalty continuation: Adam with a warm-up and cosine decay of the
    learning rate per stage (the rate shrinks as the penalty stiffens the objective)."""
    coef, history = coef0, []
    for w, lr in stages:
        schedule = optax.warmup_cosine_decay_schedule(lr / 100, lr, max(1, steps // 12), steps, lr / 100)
        opt = optax.adam(schedule)  # warm-up: Adam's first steps are full-size whatever the gradient
        coef, h = optimize(lambda c: objective(c, w, energy_ref), coef, optimizer=opt, steps=steps)
        history.append(h)
        m = {k: float(v) for k, v in jax.jit(metrics)(coef).items()}
        log(
            f"  penalty weight {w:.0e}: objective {h.min():.5f}, E = {m['energy']:.4f} J, "
            f"ω2(T) = {m['w2']:.5f} rad/s, max|λ| = {m['lam_max']:.4f} N·m"
        )
    return coef, history


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir", nargs="?", default="jaxnh_out")
    ap.add_argument("--steps", type=int, default=300, help="Adam steps per penalty stage")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    U_b, coef_b = baseline()
    mb = {k: float(v) for k, v in jax.jit(metrics)(coef_b).items()}
    print(
        f"baseline: constant U21 = {U_b:.6f}: E = {mb['energy']:.4f} J, ω2(T) = {mb['w2']:.6f} rad/s, "
        f"max|λ| = {mb['lam_max']:.4f} N·m"
    )

    print(f"optimising {N_COEF} Chebyshev coefficients of the ratio law ...")
    coef, history = design(coef_b, mb["energy"], steps=args.steps)

    # The gradient the optimiser used, against central differences, at a law
    # between the baseline and the optimum (a generic, non-stationary point).
    probe = 0.5 * (coef_b + coef)
    f = lambda c: objective(c, 1e3, mb["energy"])  # noqa: E731
    g = np.asarray(jax.jit(jax.grad(f))(probe))
    g_fd = np.asarray(fd_gradient(f, probe, h=1e-5))
    print(
        f"gradient check: max |autodiff − central difference| / max |gradient| = "
        f"{np.max(np.abs(g - g_fd)) / np.max(np.abs(g)):.1e}"
    )

    dense = jnp.linspace(0.0, T_END, 801)  # check the force limit between report times too
    mo = {k: float(v) for k, v in jax.jit(lambda c: metrics(c, dense))(coef).items()}
    sol_o, sol_b = run(coef, dense), run(coef_b, dense)
    gain = 1 - mo["energy"] / mb["energy"]
    for name, sol in (("baseline", sol_b), ("optimum", sol_o)):
        kin = float(0.5 * (J1 * sol.qd[-1, 0] ** 2 + J2 * sol.qd[-1, 1] ** 2))
        load = float(-M2 * sol.q[-1, 1])
        print(
            f"  {name:<8}: kinetic energy at T {kin:.4f} J (ω1(T) = {float(sol.qd[-1, 0]):.3f} rad/s) + work "
            f"against the load {load:.4f} J = {kin + load:.6f} J; motor work M1 φ1(T) = "
            f"{float(M1 * sol.q[-1, 0]):.6f} J (equal: the constraint does no work)"
        )
    print(
        f"optimum:  E = {mo['energy']:.4f} J, ω2(T) = {mo['w2']:.6f} rad/s "
        f"(miss {abs(mo['w2'] - W_TARGET) / W_TARGET:.1e}), max|λ| = {mo['lam_max']:.4f} N·m on 801 points"
    )
    print(
        f"improvement over the constant-ratio baseline: {100 * gain:.1f}% less motor energy "
        f"({mb['energy']:.4f} J → {mo['energy']:.4f} J)   [{time.perf_counter() - t0:.0f} s]"
    )

    _plot(out, dense, sol_b, sol_o, coef_b, coef, history, mb, mo)
    return {"baseline": mb, "optimum": mo, "gain": gain, "U_baseline": U_b}


def _plot(out, ts, sol_b, sol_o, coef_b, coef, history, mb, mo):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(ts)
    U_b = np.asarray(jax.vmap(ratio_law(coef_b))(ts))
    U_o = np.asarray(jax.vmap(ratio_law(coef))(ts))
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
    ax[0].plot(t, U_b, label=f"constant baseline (E = {mb['energy']:.2f} J)")
    ax[0].plot(t, U_o, label=f"optimised (E = {mo['energy']:.2f} J)")
    ax[0].axhspan(U_MIN, U_MAX, color="0.93", zorder=0, label="reachable ratios")
    ax[0].set(xlabel="t, s", ylabel="U21", title="ratio law")
    ax[0].legend(fontsize=8)
    for sol, name in ((sol_b, "baseline"), (sol_o, "optimised")):
        ax[1].plot(t, np.asarray(sol.qd[:, 1]), label=f"ω2, {name}")
        ax[1].plot(t, np.asarray(sol.qd[:, 0]), ls=":", label=f"ω1, {name}")
        ax[2].plot(t, np.asarray(sol.multipliers[:, 0]), label=name)
    ax[1].plot([T_END], [W_TARGET], "k*", ms=10, label="target")
    ax[1].set(xlabel="t, s", ylabel="rad/s", title="shaft speeds")
    ax[1].legend(fontsize=8)
    for s in (-1, 1):
        ax[2].axhline(s * LAMBDA_MAX, color="r", ls="--", lw=1)
    ax[2].set(xlabel="t, s", ylabel="λ, N·m", title="contact multiplier (limit dashed)")
    ax[2].legend(fontsize=8)
    fig.suptitle("Variator start-up to 10 rad/s in 4 s: least motor energy under a contact-force limit")
    fig.tight_layout()
    fig.savefig(out / "optimal_ratio.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    k0 = 0
    for h, (w, _) in zip(history, STAGES):
        ax.semilogy(np.arange(k0, k0 + len(h)), h, label=f"penalty weight {w:.0e}")
        k0 += len(h)
    ax.axhline(1.0, color="k", lw=0.8, ls=":", label="baseline (E / E_baseline = 1)")
    ax.set(xlabel="Adam step", ylabel="objective (E / E_baseline + penalties)", title="optimisation history")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "optimal_ratio_history.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out / 'optimal_ratio.png'} and {out / 'optimal_ratio_history.png'}")


if __name__ == "__main__":
    main()
