"""Truth outside the model class: how the fit degrades when U21(t) is not a spline on its knots.

    python -m benchmarks.model_error [--seeds 3]
    python -m benchmarks.model_error --quick     # 1 seed, 3 of the 7 laws: a smoke run

The embedded record's experiment (examples/make_variator_data.py: same J1,
J2, torques, initial state, encoders and noise) is repeated with true ratio
laws the fit's 7-knot natural cubic spline cannot represent:

* `tanh` steps U21 = 1.1 + 0.3 tanh((t − 3 s) / w), sharper and sharper
  (w = 1.5, 0.7, 0.35 s against a knot spacing of 1 s);
* the embedded spline plus a ripple a · sin(2π t / 1.3 s) (a = 0.002 … 0.03),
  faster than the knots can follow;
* the embedded spline itself (inside the model class: the control).

Each record is fitted exactly as `jaxnh fit` does
(`jaxnh.models.variator_fit.fit_variator`: noise levels estimated from the
record, default starting guess). Reported per case (median over `--seeds`
noise realisations): s² and its 1 % significance limit, whether the
lack-of-fit test fires, the model error relative to the noise that the fit
reports (√(s² − 1)), the errors of J1 and J2 (relative, and in reported
standard errors), the rms error of the U21 estimate against the best that
the spline can do (least-squares projection of the true law on the spline
basis), convergence and iterations.

Writes MODEL_ERROR.md and results/model_error.json: into benchmarks/ (a
`--quick` run into benchmarks/quick/), or into $JAXNH_BENCH_OUT when set.
"""

from __future__ import annotations

import argparse
import time
import warnings

from . import common as C


C.pin()  # before JAX starts

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.identify import load_default, Record  # noqa: E402
from jaxnh.models import variator as V  # noqa: E402
from jaxnh.models.variator_fit import fit_variator, ratio_knots  # noqa: E402
from jaxnh.profiles import CubicSpline, Profile  # noqa: E402


class TanhStep(Profile):
    """U21(t) = mean + half · tanh((t − t_mid) / width): a ratio change of width `width` (s)."""

    mean: float
    half: float
    t_mid: float
    width: float

    def __call__(self, t):
        return self.mean + self.half * jnp.tanh((t - self.t_mid) / self.width)


class Ripple(Profile):
    """A base profile plus amp · sin(2π t / period) (period in s)."""

    base: Profile
    amp: float
    period: float

    def __call__(self, t):
        return self.base(t) + self.amp * jnp.sin(2 * jnp.pi * t / self.period)


def cases(mk, quick=False):
    base = CubicSpline(mk.TRUTH["U21_knots"], mk.TRUTH["U21_values"])
    out = [("spline (inside the class)", base)]
    out += [(f"tanh step, width {w} s", TanhStep(1.1, 0.3, 3.0, w)) for w in ((0.7,) if quick else (1.5, 0.7, 0.35))]
    out += [
        (f"spline + {a} sin(2π t/1.3 s)", Ripple(base, a, 1.3)) for a in ((0.01,) if quick else (0.002, 0.01, 0.03))
    ]
    return out


def record_for(mk, U, key) -> Record:
    """A record of the embedded experiment with ratio law U (encoder readings drawn with key)."""
    M1, M2 = mk.torques()
    p = V.VariatorParams(mk.TRUTH["J1"], mk.TRUTH["J2"], U, M1, M2)
    t = mk.sample_times()
    ts = jnp.asarray(t)
    w0 = mk.TRUTH["w0"]
    qd0 = jnp.array([w0, float(U(0.0)) * w0])
    q = nh.simulate(V.mechanism(), p, jnp.asarray(mk.TRUTH["phi0"]), qd0, ts, rtol=1e-12, atol=1e-12).q
    y = np.asarray(mk.measure(q, key))
    m1, m2 = (np.asarray(jax.vmap(M)(ts)) for M in (M1, M2))
    return Record(t, {"phi1": y[:, 0], "phi2": y[:, 1]}, {"M1": m1, "M2": m2}, "model-error study")


def best_spline_rms(U, knots, ts):
    """rms over ts of U minus its least-squares natural spline on `knots` (the model-class limit)."""
    B = np.stack([np.asarray(jax.vmap(CubicSpline(knots, e))(jnp.asarray(ts))) for e in np.eye(len(knots))], axis=1)
    u = np.asarray(jax.vmap(U)(jnp.asarray(ts)))
    c, *_ = np.linalg.lstsq(B, u, rcond=None)
    return float(np.sqrt(np.mean((B @ c - u) ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="noise realisations per case (default 3)")
    ap.add_argument("--quick", action="store_true", help="1 seed; the control, one tanh step and one ripple")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds = 1
    out_dir = C.report_dir(args.quick)
    mk = C.example("make_variator_data")
    T = mk.TRUTH
    knots = ratio_knots(load_default())
    ts = np.linspace(0, T["duration"], 601)
    rows = []
    started = time.perf_counter()
    for name, U in cases(mk, args.quick):
        per = []
        for seed in range(args.seeds):
            rec = record_for(mk, U, jax.random.PRNGKey(100 + seed))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = fit_variator(rec)
            e = r.estimates
            u, us = r.profile_band("U21", ts)
            u_true = np.asarray(jax.vmap(U)(jnp.asarray(ts)))
            per.append(
                {
                    "converged": r.converged,
                    "iterations": r.iterations,
                    "s2": r.chi2_dof,
                    "threshold": r.lack_of_fit.threshold,
                    "significant": r.lack_of_fit.significant,
                    "model_error_over_noise": r.lack_of_fit.model_error_over_noise,
                    "autocorrelation": r.lack_of_fit.autocorrelation,
                    **{f"{k}_rel_err": e[k]["value"] / T[k] - 1 for k in ("J1", "J2")},
                    **{f"{k}_z": (e[k]["value"] - T[k]) / e[k]["std"] for k in ("J1", "J2")},
                    **{f"{k}_rel_std": e[k]["std"] / e[k]["value"] for k in ("J1", "J2")},
                    "U21_rms_err": float(np.sqrt(np.mean((u - u_true) ** 2))),
                    "U21_mean_band": float(np.mean(us)),
                    "U21_inside_95": float(np.mean(np.abs(u - u_true) <= 1.96 * us)),
                }
            )
        med = {k: float(np.median([p[k] for p in per])) for k in per[0] if k != "autocorrelation"}
        med["converged"] = all(p["converged"] for p in per)
        med["significant"] = f"{sum(p['significant'] for p in per)}/{len(per)}"
        med["iterations"] = max(p["iterations"] for p in per)
        med["autocorrelation"] = {
            c: float(np.median([p["autocorrelation"][c] for p in per])) for c in per[0]["autocorrelation"]
        }
        med["U21_best_spline_rms"] = best_spline_rms(U, knots, ts)
        rows.append({"case": name, **med, "runs": per})
        C.log(
            f"{name}: s² {med['s2']:.3g} (limit {med['threshold']:.3g}), flagged {med['significant']}, "
            f"J1 {100 * med['J1_rel_err']:+.3f} % (z {med['J1_z']:+.1f}), J2 {100 * med['J2_rel_err']:+.3f} % "
            f"(z {med['J2_z']:+.1f}), U21 rms err {med['U21_rms_err']:.2e} (spline limit "
            f"{med['U21_best_spline_rms']:.2e})"
        )
    elapsed = time.perf_counter() - started
    res = {
        "seeds": args.seeds,
        "quick": args.quick,
        "cases": rows,
        "elapsed_s": elapsed,
        "noise_std_rad": mk.noise_std().tolist(),
    }
    C.save("model_error", res, out_dir)
    m = C.machine()
    lines = [
        "# Truth outside the model class",
        "",
        C.stamp_line(C.command("model_error", argv)),
        "",
        "The embedded record's experiment with true ratio laws that the fit's 7-knot natural cubic spline cannot "
        "represent, fitted as `jaxnh fit` does (noise estimated from each record). Median over "
        f"{args.seeds} encoder-noise realisations; "
        f"reading noise {1e3 * mk.noise_std()[0]:.3f} / {1e3 * mk.noise_std()[1]:.3f} mrad.",
        "",
        "| true U21 law | s² | 1 % limit | flagged | model error / noise | J1 error | J1 z | J2 error | J2 z | "
        "U21 rms error | spline limit | U21 in 95 % band | residual autocorr. (phi1, phi2) | converged, max iter. |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ac = ", ".join(f"{v:+.2f}" for v in r["autocorrelation"].values())
        lines.append(
            f"| {r['case']} | {r['s2']:.3g} | {r['threshold']:.3g} | {r['significant']} | "
            f"{r['model_error_over_noise']:.2f} | {100 * r['J1_rel_err']:+.3f} % | {r['J1_z']:+.1f} | "
            f"{100 * r['J2_rel_err']:+.3f} % | {r['J2_z']:+.1f} | {r['U21_rms_err']:.2e} | "
            f"{r['U21_best_spline_rms']:.2e} | {100 * r['U21_inside_95']:.0f} % | {ac} | "
            f"{'yes' if r['converged'] else 'NO'}, {r['iterations']} |"
        )
    lines += [
        "",
        "s²: weighted residual variance (≈ 1 when the model fits); flagged: the fit's lack-of-fit test "
        "(s² above its 1 % limit) fired, out of the realisations; model error / noise: √(s² − 1), what the fit "
        "reports; J z: (estimate − truth) / reported standard error (scaled by s²); U21 rms error: estimate "
        "against the true law on 601 points; spline limit: rms distance of the true law from its best "
        "least-squares natural spline on the same knots (no fit can do better in that norm); U21 in 95 % band: "
        "fraction of those points where the truth lies in the fit's pointwise band.",
        "",
        f"Total {elapsed:.0f} s (including compilation) on one core of {m['cores']} (the machine may be shared).",
    ]
    path = out_dir / "MODEL_ERROR.md"
    path.write_text("\n".join(lines) + "\n")
    C.log("\n".join(lines))
    C.log(f"wrote {path}")
    return res


if __name__ == "__main__":
    main()
