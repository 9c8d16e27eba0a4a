"""Gradient-check matrix (issue 15): the variator with viscous damping c = 1e0..1e5 /s, a ratio
step U21 = U0 + dU tanh(k (t − tsw)) from smooth (k = 2 /s) to steep (1e3 /s, 1e7 /s), and
horizons of 2 s and 100 s.

The gradient of phi1(T) with respect to c and J2 by the default path (`jax.grad` through
`simulate`: forward sensitivities, error-controlled with the state) must be right to
`GM_RTOL` = 1e-5 against an independent reference — the reduced equation of motion
`I ẇ = M1 + U M2 − (J2 U U̇ + c J1) w` and its sensitivity equations integrated by SciPy's
LSODA (stiff and non-stiff) at rtol 1e-10 — or the case must carry a failure status with NaN
gradients (the stiff, long cases exhaust max_steps with an explicit method; the status message
names the implicit-solver remedy).

The ratio is a `jaxnh.profiles.SmoothStep` in the parameters, as a user writes a ratio step:
its breakpoints make `simulate` end a step at the step's middle and edges, so the 0.1 µs step is
resolved however long the run. The matrix has one compiled program of its own (batches of 10).
The same law written by hand and not declared is a limitation of every step-size control,
measured in benchmarks/RELIABILITY.md, not tested here.
"""

import os
import sys

import numpy as np
import pytest


sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository, for benchmarks/

from benchmarks import reliability_cases as R  # noqa: E402


def _long_stiff(c):
    return c["p"]["c"] >= 1e4 and c["T"] >= 100.0


@pytest.fixture(scope="module")
def matrix():
    """The matrix without its long stiff corner (c ≥ 1e4 /s over 100 s: up to 100 000 explicit steps,
    which a batch runs in lockstep; see the slow test)."""
    cases = [c for c in R.gradient_matrix_cases() if not _long_stiff(c)]
    return cases, R.run_gradient_matrix(cases)


def _report(items):
    return "\n".join(f"{c['label']}: {o.kind}: {o.detail}" for c, o in items)


def test_the_reference_matches_a_closed_form():
    """Constant ratio, no torques: I ẇ = −c J1 w gives w = w0 e^{−λt}, λ = c J1 / I, so
    phi1(T) = w0 (1 − e^{−λT}) / λ, and its derivatives in c and J2 follow by hand."""
    p = dict(J1=0.02, J2=0.05, U0=1.2, dU=0.0, k=1.0, tsw=0.0, M1=0.0, M2=0.0, c=3.0)
    w0, T = 2.0, 1.7
    I = p["J1"] + p["J2"] * p["U0"] ** 2
    lam = p["c"] * p["J1"] / I
    phi = w0 * (1 - np.exp(-lam * T)) / lam
    dphi_dlam = w0 * (T * np.exp(-lam * T) / lam - (1 - np.exp(-lam * T)) / lam**2)
    exact = (phi, dphi_dlam * p["J1"] / I, dphi_dlam * (-lam / I) * p["U0"] ** 2)
    np.testing.assert_allclose(R.gm_reference(p, w0, T), exact, rtol=1e-8)


def test_default_gradients_right_or_failed(matrix):
    """Every case is right to GM_RTOL, or a failure with NaN gradients."""
    cases, outcomes = matrix
    bad = [(c, o) for c, o in zip(cases, outcomes) if o.kind not in (R.RIGHT, R.FAILURE)]
    assert not bad, _report(bad)
    # the check is not vacuous: every damping rate has right answers on the short horizon,
    # and every light-damping run, the 0.1 µs step over 100 s included, is right
    for damping in R.GM_DAMPING:
        assert any(o.kind == R.RIGHT for c, o in zip(cases, outcomes) if c["p"]["c"] == damping and c["T"] == 2.0)
    light = [(c, o) for c, o in zip(cases, outcomes) if c["p"]["c"] <= 1e2]
    assert all(o.kind == R.RIGHT for c, o in light), _report(light)
    assert any(c["p"]["k"] >= 1e6 and c["T"] >= 100.0 for c, _ in light)


def test_steep_steps_plain_solve():
    """The plain solve (simulate eagerly, no derivative) through the 0.1 µs step (k = 1e7 /s),
    light damping, both horizons: right to GM_RTOL."""
    cases = [c for c in R.gradient_matrix_cases(damping=(1.0, 10.0), steepness=(1e7,))]
    outcomes = R.run_gradient_matrix_eager(cases)
    assert all(o.kind == R.RIGHT for o in outcomes), _report(list(zip(cases, outcomes)))


@pytest.mark.slow
def test_long_stiff_corner():
    """c = 1e4 and 1e5 /s over 100 s: right (the forward sensitivities keep their error control
    on the stability-limited steps) or max_steps_reached with NaN gradients."""
    cases = [c for c in R.gradient_matrix_cases() if _long_stiff(c)]
    outcomes = R.run_gradient_matrix(cases)
    bad = [(c, o) for c, o in zip(cases, outcomes) if o.kind not in (R.RIGHT, R.FAILURE)]
    assert not bad, _report(bad)
