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

The variator is the fuzz suite's shafts family with its third shaft idle, so the matrix runs on
the fuzz suite's compiled program (`VALUE_AND_GRAD`, batches of 10), compiling nothing of its own.
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
    """Outside the known steep-step issue, every case is right to GM_RTOL, or a failure with NaN gradients."""
    cases, outcomes = matrix
    plain = [(c, o) for c, o in zip(cases, outcomes) if not c["known"]]
    bad = [(c, o) for c, o in plain if o.kind not in (R.RIGHT, R.FAILURE)]
    assert not bad, _report(bad)
    # the check is not vacuous: every damping rate has right answers on the short horizon,
    # and the long, light-damping runs through the fast (1 ms) step are right too
    for damping in R.GM_DAMPING:
        assert any(o.kind == R.RIGHT for c, o in plain if c["p"]["c"] == damping and c["T"] == 2.0), damping
    assert all(o.kind == R.RIGHT for c, o in plain if c["p"]["c"] <= 1e2), _report(plain)


def test_steep_steps(matrix):
    """The 0.1 µs step (k = 1e7 /s): right, or failed — a success off the reference is the known
    issue 'steep-step-skipped' (reported, xfail)."""
    cases, outcomes = matrix
    steep = [(c, o) for c, o in zip(cases, outcomes) if c["known"]]
    assert steep and all(o.kind in (R.RIGHT, R.FAILURE, R.SILENT_WRONG) for _, o in steep)
    wrong = [(c, o) for c, o in steep if o.kind == R.SILENT_WRONG]
    # the plain solve (simulate eagerly, no derivative) of the same cases: right, or stepped over too
    eager = list(zip([c for c, _ in steep], R.run_gradient_matrix_eager([c for c, _ in steep])))
    assert all(o.kind in (R.RIGHT, R.FAILURE, R.SILENT_WRONG) for _, o in eager)
    wrong += [
        (c, R.dataclasses.replace(o, detail="values, eagerly: " + o.detail))
        for c, o in eager
        if o.kind == R.SILENT_WRONG
    ]
    if wrong:
        pytest.xfail("steep-step-skipped: " + R.KNOWN_ISSUES["steep-step-skipped"] + "\n" + _report(wrong))


@pytest.mark.slow
def test_long_stiff_corner():
    """c = 1e4 and 1e5 /s over 100 s: right (the forward sensitivities keep their error control
    on the stability-limited steps) or max_steps_reached with NaN gradients."""
    cases = [c for c in R.gradient_matrix_cases() if _long_stiff(c)]
    outcomes = R.run_gradient_matrix(cases)
    bad = [(c, o) for c, o in zip(cases, outcomes) if o.kind not in (R.RIGHT, R.FAILURE)]
    assert not bad, _report(bad)
