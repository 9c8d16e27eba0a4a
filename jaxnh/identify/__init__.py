"""Parameter identification: fit a mechanism's parameters to measured motion.

* `fit(mech, params, record, free=..., positive=...)` — least squares of the
  simulated against the measured coordinates, with the Jacobian from forward
  differentiation through the ODE solver; Levenberg–Marquardt
  or an optax optimiser; optional multiple shooting. Returns a `FitResult`:
  estimates with standard errors (Gauss–Newton covariance scaled by the
  residual variance), bands of derived quantities (`result.band`,
  `result.profile_band("U21", ts)`), residual statistics, convergence, and
  an identifiability report that names undetermined combinations. It is an
  `Estimates` (names, values, standard errors, covariance, bands), as is a
  `Prediction`.
* `Record`, `read_csv`, `load_default`, `noise_level` — measured data.
* `prepare`, `Problem`, `solve_least_squares`, `statistics` — the pure-JAX
  core, for batched fits under `jax.vmap`.
* Before measuring: `experiment(...)` → `Experiment`, `predict(exp)` →
  `Prediction` (Fisher information, predicted standard errors, the
  identifiability diagnosis), `optimal_design(...)` → `DesignResult`
  (inputs minimising a D-, A- or named-variance criterion within `Limits`:
  contact force, energy, power); `encoder_noise`, `ChannelNoise` the noise model.

The friction variator's own identification (`fit_variator`, `report`,
`variator_experiment`) is in `jaxnh.models.variator_fit`.
"""

from jaxnh.identify._experiment import (
    ChannelNoise,
    DesignResult,
    encoder_noise,
    Experiment,
    experiment,
    Limits,
    optimal_design,
    predict,
    Prediction,
    StickLimit,
)
from jaxnh.identify._fit import fit, FitResult, prepare
from jaxnh.identify.data import load_default, MIN_SAMPLES, noise_level, read_csv, Record, write_csv
from jaxnh.identify.diagnostics import Identifiability
from jaxnh.identify.estimates import Estimates
from jaxnh.identify.problem import Observations, Problem, solve_least_squares, statistics, value_and_jacobian


__all__ = [
    "fit",
    "FitResult",
    "prepare",
    "Record",
    "read_csv",
    "write_csv",
    "load_default",
    "noise_level",
    "MIN_SAMPLES",
    "Identifiability",
    "Estimates",
    "Observations",
    "Problem",
    "solve_least_squares",
    "statistics",
    "value_and_jacobian",
    "experiment",
    "Experiment",
    "predict",
    "Prediction",
    "optimal_design",
    "DesignResult",
    "Limits",
    "StickLimit",
    "ChannelNoise",
    "encoder_noise",
]
