"""`fit` with friction contacts (issue 43): the pressing force N of a variator's roller and its
kinetic friction coefficient μk, identified from a noisy record of the drive slipping.

The scene: shaft 1 (J1) drives shaft 2 (J2) through a roller of radius r rolling at the radius ρ(t)
on shaft 2; ρ halves in 0.5 s at 100 rad/s, so the roller slips (the rolling force it needs passes
μs N) and later sticks again. While it slips, the kinetic force μk N sets the slip; the onset is set
by μs N (μs fixed and known here), so N and μk are both determined: N by when the slip starts, μk by
how it proceeds. The record: φ1, φ2 at 201 times, made by jaxnh's own friction solve at rtol 1e-10
from the true values, plus seeded Gaussian noise σ = 1e-4 rad.

What is judged:
* the fit converges, its residual variance s² is consistent with the noise (the 99.9 % interval of
  χ²/dof for 402 − 5 degrees of freedom is about [0.79, 1.25]);
* each estimate is within 4 of its own standard errors of the truth (a 4σ test of calibrated
  intervals, 6e-5 false-alarm rate per parameter for a right fit);
* with the mechanism's noise-free record fitted from the same start, the estimates reach the truth
  to within the record's own error: the record and the fit's solves carry a global error of order
  1e2 × rtol of the motion, which maps into the estimates through the standard errors per unit
  noise (σ̂/σ), so |θ̂ − θ| ≤ 1e2 rtol (σ̂/σ) × scale of φ is the bound.
"""

import jax


jax.config.update("jax_enable_x64", True)

import functools  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxnh as nh  # noqa: E402


def rho(t, p):
    """Contact radius on shaft 2, m: a cosine ramp from rho0 to rho1 over [0, Tr] s."""
    s = jnp.clip(t / p["Tr"], 0.0, 1.0)
    return p["rho0"] + (p["rho1"] - p["rho0"]) * 0.5 * (1 - jnp.cos(jnp.pi * s))


def kinetic(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def rolling(q, qd, t, p):  # slip velocity of the roller, m/s
    return jnp.stack([p["r"] * qd[0] - rho(t, p) * qd[1]])


ROLLER = nh.FrictionContact(
    0,
    normal_force=lambda q, qd, t, p: p["N"],
    mu_static=lambda q, qd, t, p: p["mu_s"],
    mu_kinetic=lambda q, qd, t, p: p["mu_k"],
    name="roller",
)
MECH = nh.Mechanism(kinetic, constraints=rolling, contacts=(ROLLER,), names=("phi1", "phi2"))
TRUTH = {
    "J1": 0.02,
    "J2": 0.05,
    "r": 0.05,
    "rho0": 0.05,
    "rho1": 0.025,
    "Tr": 0.5,
    "N": 150.0,
    "mu_s": 0.3,
    "mu_k": 0.24,
}
START = dict(TRUTH, N=130.0, mu_k=0.2)
Q0 = jnp.zeros(2)
QD0 = jnp.array([100.0, 100.0])  # rad/s; rolling at the start (r = rho0)
TS = jnp.linspace(0.0, 1.0, 201)
RTOL_RECORD = 1e-10
SIGMA = 1e-4  # rad


@functools.lru_cache(maxsize=None)
def record(noisy: bool) -> nh.Record:
    sol = nh.simulate(MECH, TRUTH, Q0, QD0, TS, rtol=RTOL_RECORD, atol=1e-12)
    assert sol.message == "success"
    # the drive slips and sticks again inside the record, so both N and μk act on it
    assert len(sol.contacts.transitions("roller")) >= 2
    q = np.asarray(sol.q)
    if noisy:
        q = q + SIGMA * np.random.default_rng(0).normal(size=q.shape)
    return nh.Record(t=np.asarray(TS), channels={"phi1": q[:, 0], "phi2": q[:, 1]}, sigma=SIGMA, source="test")


@functools.lru_cache(maxsize=None)
def fitted(noisy: bool):
    return nh.fit(MECH, START, record(noisy), free=["N", "mu_k"], positive=["N", "mu_k"], q0=Q0, qd0=QD0)


@pytest.mark.slow
def test_fit_with_contacts_recovers_normal_force_and_kinetic_coefficient():
    res = fitted(True)
    assert res.converged, res.message
    assert 0.79 <= res.chi2_dof <= 1.25, res.summary()
    for name in ("N", "mu_k"):
        est, std = (float(res.estimates[name][k]) for k in ("value", "std"))
        assert np.isfinite(std) and std > 0
        assert abs(est - TRUTH[name]) <= 4 * std, (name, est, std)
        assert std < 1e-3 * TRUTH[name]  # the record determines both (measured 4e-5 and 5e-5 relative)


@pytest.mark.slow
def test_fit_with_contacts_noise_free_reaches_the_truth():
    res = fitted(False)
    noisy = fitted(True)
    assert res.converged, res.message
    scale = float(jnp.max(jnp.abs(QD0))) * float(TS[-1])  # rad: the angles' scale
    for name in ("N", "mu_k"):
        per_unit_noise = float(noisy.estimates[name]["std"]) / SIGMA  # estimate change per rad of misfit
        bound = 1e2 * RTOL_RECORD * scale * per_unit_noise
        est = float(res.estimates[name]["value"])
        assert abs(est - TRUTH[name]) <= bound, (name, est, bound)
