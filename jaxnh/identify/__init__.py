"""Parameter identification: fit a mechanism's parameters to measured motion.

* `fit(mech, params, record, free=..., positive=...)` — least squares of the
  simulated against the measured coordinates, with the Jacobian from forward
  differentiation through the ODE solver; Levenberg–Marquardt
  or an optax optimiser; optional multiple shooting. Returns a `FitResult`:
  estimates with standard errors (Gauss–Newton covariance scaled by the
  residual variance), bands of derived quantities (`result.band`,
  `result.profile_band("U21", ts)`), residual statistics, convergence, and
  an identifiability report that names undetermined combinations.
* `Record`, `read_csv`, `load_default`, `noise_level` — measured data.
* `prepare`, `Problem`, `solve_least_squares`, `statistics` — the pure-JAX
  core, for batched fits under `jax.vmap`.
* `variator` — the friction variator: `fit_variator(record)`, `report(result)`.
* Before measuring: `experiment(...)` → `Experiment`, `predict(exp)` →
  `Prediction` (Fisher information, predicted standard errors, the
  identifiability diagnosis), `optimal_design(...)` → `DesignResult`
  (inputs minimising a D-, A- or named-variance criterion within `Limits`:
  contact force, energy, power); `variator_experiment()` is the embedded
  record's set-up; `encoder_noise`, `ChannelNoise` the noise model.
"""

from . import variator
from ._experiment import (
    ChannelNoise,
    DesignResult,
    encoder_noise,
    Experiment,
    experiment,
    Limits,
    optimal_design,
    predict,
    Prediction,
    variator_experiment,
)
from ._fit import fit, FitResult, prepare
from .data import load_default, MIN_SAMPLES, noise_level, read_csv, Record, write_csv
from .diagnostics import Identifiability
from .problem import Observations, Problem, solve_least_squares, statistics, value_and_jacobian


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
    "Observations",
    "Problem",
    "solve_least_squares",
    "statistics",
    "value_and_jacobian",
    "variator",
    "experiment",
    "Experiment",
    "predict",
    "Prediction",
    "optimal_design",
    "DesignResult",
    "Limits",
    "ChannelNoise",
    "encoder_noise",
    "variator_experiment",
]
