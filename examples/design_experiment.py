"""Design an identification experiment, run it (simulated), fit it, and check the prediction.

Run:  python examples/design_experiment.py [--starts 1] [--steps 400]

1. The embedded record's experiment (6 s at 250 Hz, two quantised encoders,
   motor torque M1(t), load torque M2(t)) predicts, before any data, the
   standard errors a fit of J1, J2 and the U21(t) spline will have.
2. `optimal_design` chooses new torques M1(t), M2(t) — Fourier series (12
   harmonics over the record) bounded
   by the record's largest |M1| and |M2| — that minimise the predicted
   variance of J1 while the contact force (the constraint multiplier,
   N·m) stays within the largest |λ| of the embedded experiment and J2 and
   every U21 knot stay at least as precise.
3. A "measurement" of the true variator driven by the designed torques is
   simulated the way the embedded record was made (quantised encoders with
   jitter), fitted with `fit_variator`, and the realised standard errors
   are printed next to the predicted ones.

Takes a few minutes (compilation of the nested forward derivatives, then
about 0.1 s per design step). `jaxnh design` does steps 1–2 from the command
line; benchmarks/experiment_design.py repeats step 3 1200 times.
"""

import argparse
import importlib.util
import os

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.identify._experiment import Limits, optimal_design, predict
from jaxnh.identify.data import Record
from jaxnh.models import variator as V
from jaxnh.models.variator_fit import fit_variator, variator_experiment
from jaxnh.profiles import Bounded, Fourier, Sampled


HERE = os.path.dirname(os.path.abspath(__file__))


def _maker():
    spec = importlib.util.spec_from_file_location("make_variator_data", os.path.join(HERE, "make_variator_data.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=1)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--seed", type=int, default=7, help="seed of the simulated measurement")
    args = ap.parse_args(argv)

    # 1. the present experiment, predicted before any data
    exp, params = variator_experiment()
    base = predict(exp)
    print("Embedded record's experiment, predicted:")
    print(base.summary())
    P = exp.n_params
    t = np.asarray(exp.ts)
    m1_max = float(np.max(np.abs(np.asarray(params.M1.values))))
    m2_max = float(np.max(np.abs(np.asarray(params.M2.values))))
    lam_max = float(np.max(base.max_multiplier))

    # 2. design M1, M2: minimise var(J1); keep J2 and the knots; contact force within the record's
    rng = np.random.default_rng(0)

    def law(bound, mean, K=12):
        # start near the record's mean torque with small random harmonics (as `jaxnh design` does)
        return Bounded(
            Fourier(
                float(Bounded.inverse(mean, -bound, bound)),
                cos=0.3 * rng.standard_normal(K),
                sin=0.3 * rng.standard_normal(K),
                period=float(t[-1] - t[0]),
            ),
            -bound,
            bound,
        )

    start = V.VariatorParams(
        params.J1, params.J2, params.U21, law(m1_max, np.mean(params.M1.values)), law(m2_max, np.mean(params.M2.values))
    )
    keep = {lab: float(s / v) for lab, s, v in zip(exp.labels[1:P], base.std[1:P], base.values[1:P])}
    res = optimal_design(
        exp,
        start,
        ("M1", "M2"),
        "A",
        of=("J1",),
        limits=Limits(multiplier=lam_max, std=keep),
        starts=args.starts,
        steps=args.steps,
        spread=0.3,
        progress=True,
    )
    tj = jnp.asarray(t)
    m1 = np.asarray(jax.vmap(res.params.M1)(tj))
    m2 = np.asarray(jax.vmap(res.params.M2)(tj))
    designed = V.VariatorParams(params.J1, params.J2, params.U21, Sampled(t, m1), Sampled(t, m2))
    pred = predict(exp, designed)
    print(
        f"\nDesign: feasible {res.feasible}, limits used {res.violations} (≤ 1 holds); "
        f"max |λ| {float(np.max(pred.max_multiplier)):.4g} N·m (limit {lam_max:.4g})"
    )

    # 3. run the designed experiment (simulated measurement), fit, compare
    mk = _maker()
    truth = mk.truth()
    p_true = V.VariatorParams(truth.J1, truth.J2, truth.U21, Sampled(t, m1), Sampled(t, m2))
    w0 = mk.TRUTH["w0"]
    sol = nh.simulate(
        V.mechanism(), p_true, jnp.zeros(2), jnp.array([w0, float(truth.U21(0.0)) * w0]), tj, rtol=1e-12, atol=1e-12
    )
    y = np.asarray(mk.measure(sol.q, jax.random.PRNGKey(args.seed)))
    rec = Record(t, {"phi1": y[:, 0], "phi2": y[:, 1]}, {"M1": m1, "M2": m2}, "designed experiment (simulated)")
    fit = fit_variator(rec)
    print(
        f"\nFit of the simulated designed experiment: {fit.iterations} iterations, converged {fit.converged}, "
        f"ODE rtol {fit.problem.rtol:.2g}"
    )
    true = np.concatenate([[truth.J1, truth.J2], mk.TRUTH["U21_values"]])
    print(
        f"{'parameter':<10}{'true':>9}{'estimate':>12}{'std fitted':>12}{'predicted':>11}{'baseline':>11}"
        f"{'fit/pred':>9}"
    )
    for j in range(P):
        print(
            f"{exp.labels[j]:<10}{true[j]:>9.5g}{fit.values[j]:>12.7g}{fit.std[j]:>12.3g}{pred.std[j]:>11.3g}"
            f"{base.std[j]:>11.3g}{fit.std[j] / pred.std[j]:>9.3f}"
        )
    print(
        f"\nSE(J1): baseline / designed = {base.std[0] / pred.std[0]:.2f} (predicted), "
        f"{base.std[0] / fit.std[0]:.2f} (realised in this one fit)"
    )


if __name__ == "__main__":
    main()
