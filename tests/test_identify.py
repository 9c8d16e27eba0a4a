"""Parameter identification: recovery, identifiability, statistics, data checks, command line.

The fits share one compiled Levenberg–Marquardt solve: every record here has
the shape of the embedded one (1501 samples, two channels, 7 U21 knots) and
the default solver settings, so the solve compiles once per process.
"""

import json
import re
import subprocess
import sys
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxnh as nh
from jaxnh.identify import fit, load_default, noise_level, read_csv, Record, statistics, write_csv
from jaxnh.identify._fit import fit_solver, GN_STEP_TOL
from jaxnh.identify.diagnostics import analyse
from jaxnh.identify.parameters import Parametrisation
from jaxnh.models import variator as V
from jaxnh.models.variator_fit import fit_variator, FREE, params_for, ratio_knots
from jaxnh.profiles import CubicSpline, Profile


TRUE = {
    "J1": 0.025,
    "J2": 0.04,
    "U21": np.array([1.2, 1.1, 0.95, 0.85, 0.9, 1.05, 1.15]),
    "w0": 3.0,
    "phi0": np.array([0.1, -0.2]),
}
# starting guess off by 30–40 % in every parameter
START = {"J1": 1.4 * TRUE["J1"], "J2": 0.65 * TRUE["J2"], "U21": TRUE["U21"] * np.array([1.3, 0.7] * 3 + [1.3])}
NOISE = 1e-4  # rad: weights only (the data below are noise-free)


def clean_record(with_torques: bool = True) -> Record:
    """A noise-free record generated inside the model class: the variator with a
    spline U21 on the fit's knots and the embedded record's torques (as `Sampled`
    inputs), integrated with the solver and tolerances the fit uses (`fit_solver`),
    so the model reproduces the data exactly at the true parameters."""
    emb = load_default()
    inputs = emb.inputs if with_torques else {k: np.zeros_like(v) for k, v in emb.inputs.items()}
    base = Record(emb.t, emb.channels, inputs, "clean")
    U = CubicSpline(ratio_knots(base), TRUE["U21"])
    p = params_for(base, TRUE["J1"], TRUE["J2"], U)
    qd0 = jnp.array([TRUE["w0"], TRUE["U21"][0] * TRUE["w0"]])
    q = np.asarray(
        nh.simulate(
            V.mechanism(), p, jnp.asarray(TRUE["phi0"]), qd0, jnp.asarray(emb.t), solver=fit_solver(None, p, 1e-8)
        ).q
    )
    return Record(emb.t, {"phi1": q[:, 0], "phi2": q[:, 1]}, inputs, "clean")


def fit_from_start(record, **kw):
    knots = ratio_knots(record)
    return fit_variator(record, J1=START["J1"], J2=START["J2"], U21=CubicSpline(knots, START["U21"]), noise=NOISE, **kw)


@pytest.fixture(scope="module")
def clean():
    return clean_record()


@pytest.fixture(scope="module")
def recovered(clean):
    return fit_from_start(clean)


def rel_err(result):
    e = result.estimates
    return np.concatenate(
        [
            [e["J1"]["value"] / TRUE["J1"] - 1, e["J2"]["value"] / TRUE["J2"] - 1],
            np.asarray(e["U21"]["value"]) / TRUE["U21"] - 1,
        ]
    )


# --- acceptance 1: noise-free data, start 30–40 % off ----------------------------------------


def test_noise_free_recovery_from_a_poor_start(recovered):
    r = recovered
    # the data are reproduced exactly at the truth, so only the optimiser's
    # termination limits the answer: 1e-6 relative is the acceptance criterion
    np.testing.assert_array_less(np.abs(rel_err(r)), 1e-6)
    assert r.converged and r.identifiable
    np.testing.assert_allclose(r.q0, TRUE["phi0"], atol=1e-8)
    np.testing.assert_allclose(r.qd0[0], TRUE["w0"], rtol=1e-7)
    assert r.rms_residual < 1e-8  # rad; the data have no noise
    assert set(r.estimates) == {"J1", "J2", "U21", "phi1(t0)", "phi2(t0)", "phi1'(t0)"}
    assert r.iterations < 40


def test_band_is_the_delta_method(recovered):
    # U21 is linear in its knot values: its variance at a knot is that knot's variance
    knots = np.asarray(recovered.params.U21.knots)
    val, std = recovered.profile_band("U21", knots)
    np.testing.assert_allclose(val, recovered.estimates["U21"]["value"], rtol=1e-12)
    np.testing.assert_allclose(std, recovered.estimates["U21"]["std"], rtol=1e-6)


# --- identifiability ---------------------------------------------------------------------------


def test_zero_torques_only_the_ratio_of_inertias_is_identifiable():
    rec = clean_record(with_torques=False)
    # the warning itself says what is wrong and names the ratio the data do determine
    with pytest.warns(
        UserWarning,
        match=r"NOT IDENTIFIABLE: scaling J[12] and J[12] by the same factor .*"
        r"only (J1/J2|J2/J1) is determined",
    ):
        r = fit_from_start(rec)
    assert not r.identifiable
    (entry,) = r.identifiability.undetermined
    assert set(entry["direction"]) == {"J1", "J2"}  # scaling both together changes nothing
    assert entry["identifiable"] in ("J1/J2", "J2/J1")
    assert "J1" in entry["message"] and "J2" in entry["message"]
    assert not np.isfinite(r.estimates["J1"]["std"]) and not np.isfinite(r.estimates["J2"]["std"])
    # what the data do determine is still estimated, with finite errors
    e = r.estimates
    np.testing.assert_allclose(e["J1"]["value"] / e["J2"]["value"], TRUE["J1"] / TRUE["J2"], rtol=1e-6)
    np.testing.assert_allclose(e["U21"]["value"], TRUE["U21"], rtol=1e-6)
    assert np.all(np.isfinite(e["U21"]["std"]))
    _, band = r.profile_band("U21", np.linspace(0, 6, 5))
    assert np.all(np.isfinite(band))
    assert not np.isfinite(r.band(lambda p, t: p.J1 + p.J2 * p.U21(t) ** 2, [1.0])[1][0])


def test_statistics_on_a_linear_problem():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(200, 3))
    r = rng.normal(size=200)
    st = jax.tree_util.tree_map(np.asarray, statistics(jnp.asarray(J), jnp.asarray(r)))
    s2 = r @ r / (200 - 3)
    np.testing.assert_allclose(st["cov"], s2 * np.linalg.inv(J.T @ J), rtol=1e-10)
    np.testing.assert_allclose(st["s2"], s2, rtol=1e-12)
    # two log-parameters whose effects cancel when both grow by the same factor:
    # the direction (+1, +1) is undetermined, the ratio Ja/Jb is determined
    for sign, determined in ((-1, "Ja/Jb"), (1, "Ja·Jb")):
        Jd = np.column_stack([J[:, 0], sign * J[:, 0], J[:, 2]])
        st = jax.tree_util.tree_map(np.asarray, statistics(jnp.asarray(Jd), jnp.asarray(r)))
        assert np.isinf(st["std"][:2]).all() and np.isfinite(st["std"][2])
        rep = analyse(st, ("Ja", "Jb", "c"), np.array([True, True, False]), 1e-8)
        assert not rep.identifiable and rep.undetermined[0]["identifiable"] == determined


# --- acceptance 4: the truth outside the model class ---------------------------------------------


class TanhRatio(Profile):
    """U21 = 1.1 + 0.3 tanh((t − 3 s)/0.35 s): a ratio change too quick for a natural spline on 1 s knots."""

    def __call__(self, t):
        return 1.1 + 0.3 * jnp.tanh((t - 3.0) / 0.35)


@pytest.fixture(scope="module")
def outside():
    """The embedded experiment (true J1, J2, torques, initial state) with the tanh ratio law, white
    Gaussian noise of the embedded encoders' standard deviations, fitted as `jaxnh fit` does."""
    emb = load_default()
    truth = json.loads((__import__("importlib").resources.files("jaxnh") / "data" / "variator_truth.json").read_text())
    U = TanhRatio()
    p = params_for(emb, truth["J1"], truth["J2"], U)
    qd0 = jnp.array([truth["w0"], float(U(0.0)) * truth["w0"]])
    q = np.asarray(nh.simulate(V.mechanism(), p, jnp.asarray(truth["phi0"]), qd0, jnp.asarray(emb.t)).q)
    y = q + np.asarray(truth["noise_std"]) * np.random.default_rng(5).normal(size=q.shape)
    rec = Record(emb.t, {"phi1": y[:, 0], "phi2": y[:, 1]}, emb.inputs, "tanh ratio")
    with pytest.warns(UserWarning, match=r"LACK OF FIT: the residuals are .* the noise level"):
        r = fit_variator(rec)
    return q, U, truth, r


def test_truth_outside_the_model_class_is_reported_with_its_size(outside):
    q, U, truth, r = outside
    lof = r.lack_of_fit
    # it still converges, to a well-determined answer ...
    assert r.converged and r.identifiable
    # ... and says that the misfit exceeds the noise, by how much, in the summary and the command-line table
    assert lof.significant and lof.s2 > lof.threshold and lof.model_error_over_noise > 10
    from jaxnh._cli.fit import estimate_table

    assert "LACK OF FIT" in estimate_table(r) and "LACK OF FIT" in r.summary()
    # The size it reports is the real model error: the rms of the fitted minus the noise-free motion.
    # σ·√(s² − 1) differs from it by the noise's sampling error, relative ~ 1/(√n · model error/noise)
    # plus 1/(model error/noise)² times the noise estimate's ≈ 5 %: far below 5 % here.
    actual = np.sqrt(np.mean((r.fitted - q) ** 2, axis=0))
    np.testing.assert_allclose([lof.model_error_rms[c] for c in ("phi1", "phi2")], actual, rtol=0.05)
    assert lof.autocorrelation["phi1"] > 0.9  # a smooth misfit, not noise
    # Graceful: the U21 estimate misses the true law by the order of the best the 7-knot spline can do (its
    # least-squares projection; the fit minimises the misfit of the motion, not of U21, so it need not reach
    # it), and the inertias are off by a few per cent, like the ratio law's best approximation (3 % rms).
    ts = np.linspace(0, 6, 601)
    u, _ = r.profile_band("U21", ts)
    u_true = np.asarray(jax.vmap(U)(jnp.asarray(ts)))
    knots = np.asarray(r.params.U21.knots)
    B = np.stack([np.asarray(jax.vmap(CubicSpline(knots, e))(jnp.asarray(ts))) for e in np.eye(len(knots))], axis=1)
    best = B @ np.linalg.lstsq(B, u_true, rcond=None)[0]
    rms_best = np.sqrt(np.mean((best - u_true) ** 2))
    assert 0.02 < rms_best / np.mean(u_true) < 0.05  # the law really is outside the class
    assert np.sqrt(np.mean((u - u_true) ** 2)) < 2 * rms_best
    e = r.estimates
    for k in ("J1", "J2"):
        assert abs(e[k]["value"] / truth[k] - 1) < 0.05, (k, e[k]["value"], truth[k])


# --- acceptance 2, the command line, the JSON --------------------------------------------------


def test_cli_on_the_embedded_record(tmp_path):
    from jaxnh._cli.main import fit_main

    out = tmp_path / "out"
    code = fit_main(["--json", str(tmp_path / "fit.json"), "--out", str(out), "--quiet"])
    assert code == 0
    rep = json.loads((tmp_path / "fit.json").read_text())
    for key in ("J1", "J2", "U21", "rms_residual", "iterations", "converged"):
        assert key in rep
    assert rep["converged"] and rep["identifiable"]
    assert len(rep["U21"]["t"]) == len(rep["U21"]["value"]) == len(rep["U21"]["std"])
    truth = json.loads((__import__("importlib").resources.files("jaxnh") / "data" / "variator_truth.json").read_text())
    for k in ("J1", "J2"):
        assert abs(rep[k]["value"] - truth[k]) <= 1.96 * rep[k]["std"], (k, rep[k], truth[k])
        assert rep[k]["std"] / rep[k]["value"] < 1e-3  # kg·m² known to better than 0.1 %
    v, s = np.asarray(rep["U21_knots"]["value"]), np.asarray(rep["U21_knots"]["std"])
    assert np.all(np.abs(v - truth["U21_values"]) <= 1.96 * s * 1.5)  # 7 knots: allow for multiplicity
    assert 0.5 < rep["chi2_dof"] < 2  # the noise levels estimated from the data are about right
    # the truth is inside the model class: no lack of fit is reported (a 1 % false-alarm test)
    assert not rep["lack_of_fit"]["significant"] and "fits to within the noise" in rep["lack_of_fit"]["message"]
    for png in ("fit_data.png", "fit_ratio.png"):
        assert (out / png).stat().st_size > 10_000


# --- options: multiple shooting, one encoder, optax ------------------------------------------------


def test_multiple_shooting_from_a_flat_ratio(clean):
    r = fit_variator(clean, J1=2 * TRUE["J1"], J2=0.5 * TRUE["J2"], U21=1.0, noise=NOISE, shooting=4)
    assert r.shooting == 4 and r.converged
    np.testing.assert_array_less(np.abs(rel_err(r)), 1e-6)


def test_one_encoder_is_enough_with_torques(clean, recovered):
    # with phi2 alone J1, J2 and U21 are still determined (the torques separate
    # them) but about 20x worse conditioned: the valley is long and curved, so
    # start 3 % off (10 % takes ~110 iterations). The unobserved phi1(0) is given
    # its true value so that the solver's step sequence — and with it the data —
    # is reproduced exactly at the truth.
    knots = ratio_knots(clean)
    r = fit_variator(
        clean,
        J1=1.03 * TRUE["J1"],
        J2=TRUE["J2"] / 1.03,
        U21=CubicSpline(knots, 1.03 * TRUE["U21"]),
        noise=NOISE,
        observe=("phi2",),
        q0=TRUE["phi0"],
        max_iterations=200,
    )
    assert r.observe == ("phi2",) and "phi1(t0)" not in r.estimates
    assert r.converged and r.identifiable
    assert r.identifiability.condition > 5 * recovered.identifiability.condition
    np.testing.assert_array_less(np.abs(rel_err(r)), 1e-6)


def test_optax_reports_honestly_when_not_converged(clean):
    adam = optax.adam(1e-2)
    start = fit_from_start(clean, optimizer=adam, max_iterations=1)  # the best point seen is the start
    r = fit_from_start(clean, optimizer=adam, max_iterations=15)
    assert r.optimizer == "optax" and r.iterations == 15 and r.differentiation == "forward"
    assert r.rms_residual < 0.5 * start.rms_residual  # it descends ...
    assert not r.converged and r.gn_step > GN_STEP_TOL  # ... but does not claim to have arrived
    assert "iteration limit" in r.message


# --- data and argument checks (no compilation) ---------------------------------------------------


def write(tmp_path, text):
    p = tmp_path / "d.csv"
    p.write_text(text)
    return p


def good_rows(n=25, t=None):
    t = np.arange(n) * 0.01 if t is None else t
    return "\n".join(f"{x},{0.1 * i},{0.2 * i},0.1,-0.1" for i, x in enumerate(t))


BAD_CSV = [
    ("t,phi1,M1,M2\n" + "\n".join(f"{0.01 * i},0,0,0" for i in range(25)), r"missing column\(s\) \['phi2'\]"),
    ("t,phi1,phi2,M1,M2\n" + good_rows(t=np.r_[np.arange(10) * 0.01, 0.09, np.arange(10, 24) * 0.01]), "repeated time"),
    (
        "t,phi1,phi2,M1,M2\n" + good_rows(t=np.r_[np.arange(10) * 0.01, 0.05, np.arange(11, 25) * 0.01]),
        "decreasing time",
    ),
    ("t,phi1,phi2,M1,M2\n" + good_rows().replace("0.1,-0.1", "nan,-0.1", 1), "non-finite values"),
    ("t,phi1,phi2,M1,M2\n" + good_rows(5), "too few samples: 5"),
    ("t,phi1,phi2,M1,M2\n" + good_rows().replace("0.1,-0.1", "abc,-0.1", 1), "'abc' is not a number"),
]


@pytest.mark.parametrize("text,match", BAD_CSV)
def test_read_csv_rejects_bad_records(tmp_path, text, match):
    with pytest.raises(ValueError, match=match):
        read_csv(write(tmp_path, text))


@pytest.mark.parametrize("text,match", BAD_CSV)
def test_cli_rejects_bad_records_with_exit_code_2(tmp_path, capsys, text, match):
    from jaxnh.cli import main

    path = write(tmp_path, text)
    assert main(["fit", str(path), "--quiet", "--json", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxnh fit: ") and str(path) in err
    assert re.search(match, err), err
    assert not (tmp_path / "o.json").exists()


def test_cli_exit_status_in_a_fresh_process(tmp_path):
    # the installed entry point's way: python -m jaxnh.cli (sys.exit(main())); a missing file too
    text, match = BAD_CSV[0]
    for path, what in ((write(tmp_path, text), match), (tmp_path / "no_such.csv", "No such file")):
        proc = subprocess.run(
            [sys.executable, "-m", "jaxnh.cli", "fit", str(path)], capture_output=True, text=True, timeout=120
        )
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.startswith("jaxnh fit: ") and "Traceback" not in proc.stderr
        assert re.search(what, proc.stderr), proc.stderr


def test_csv_round_trip_and_embedded_record(tmp_path):
    rec = load_default()
    assert rec.n == 1501 and set(rec.channels) == {"phi1", "phi2"} and set(rec.inputs) == {"M1", "M2"}
    write_csv(rec.head(50), tmp_path / "x.csv", comments=["a comment"])
    back = read_csv(tmp_path / "x.csv")
    np.testing.assert_allclose(back.t, rec.t[:50], rtol=1e-9)
    np.testing.assert_allclose(back.channels["phi2"], rec.channels["phi2"][:50], rtol=1e-9)
    one = read_csv(tmp_path / "x.csv", coordinates=("phi1",))
    assert set(one.channels) == {"phi1"}


def test_noise_level_of_white_noise_on_a_smooth_motion():
    t = np.linspace(0, 10, 20001)
    rng = np.random.default_rng(1)
    y = np.stack([3 * t + np.sin(2 * t), 0.5 * t**2], axis=1) + rng.normal(size=(t.size, 2)) * [2e-4, 7e-4]
    # 20000 third differences: the estimate's relative standard error is about 1.5 %
    np.testing.assert_allclose(noise_level(jnp.asarray(y)), [2e-4, 7e-4], rtol=0.06)
    # a quantised encoder (step 1e-3) with jitter 0.4 step: reading error sqrt(jitter² + step²/12)
    enc = np.floor((5 * t + 0.4e-3 * rng.normal(size=t.size)) / 1e-3) * 1e-3
    np.testing.assert_allclose(noise_level(jnp.asarray(enc)), np.sqrt(0.4e-3**2 + 1e-6 / 12), rtol=0.06)


def test_argument_errors_name_the_argument():
    rec = load_default()
    p = params_for(rec, 0.02, 0.05, CubicSpline(ratio_knots(rec), np.ones(7)))
    mech = V.mechanism()
    with pytest.raises(ValueError, match="no parameter 'J3'"):
        fit(mech, p, rec, free=("J1", "J3"))
    with pytest.raises(ValueError, match=r"positive=.*not among free"):
        fit(mech, p, rec, free=("J1",), positive=("J2",))
    with pytest.raises(ValueError, match="must be > 0 at the starting guess"):
        fit(mech, params_for(rec, -0.02, 0.05, p.U21), rec, free=FREE, positive=FREE)
    with pytest.raises(ValueError, match="observe: 'phi3' is not a coordinate"):
        fit(mech, p, rec, free=FREE, observe=("phi3",))
    with pytest.raises(ValueError, match="noise: standard deviations must be finite and > 0"):
        fit(mech, p, rec, free=FREE, noise=-1.0)
    with pytest.raises(ValueError, match="optimizer must be one of"):
        fit(mech, p, rec, free=FREE, optimizer="newton")
    with pytest.raises(ValueError, match="shooting=400: segments of"):
        fit(mech, p, rec, free=FREE, shooting=400)
    par = Parametrisation(p, FREE, FREE)
    assert par.labels[:3] == ("J1", "J2", "U21[0]") and par.size == 9
    back = par.unpack(par.pack())
    assert isinstance(p.U21, CubicSpline)
    np.testing.assert_allclose(back.U21.values, p.U21.values, rtol=1e-15)
    np.testing.assert_allclose(back.J2, p.J2, rtol=1e-15)


def test_savgol_derivative_matches_scipy():
    """The starting guess's own Savitzky–Golay derivative (no scipy.signal import) equals SciPy's
    savgol_filter(mode="interp") to rounding, inside and at both ends of the record."""
    from scipy.signal import savgol_filter

    from jaxnh.models.variator_fit import savgol_derivative

    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 6.0, 1501)
    y = np.sin(3 * t) + 0.01 * rng.normal(size=t.size)
    dt = t[1] - t[0]
    for deriv in (1, 2):
        for window in (7, 31, 61):
            ours = np.asarray(savgol_derivative(y, window, 3, deriv, dt))
            ref = np.asarray(savgol_filter(y, window, 3, deriv=deriv, delta=dt))
            np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10 * np.max(np.abs(ref)))


def test_host_arithmetic_in_numpy_matches_the_compiled_one():
    """The host fit runs the Levenberg–Marquardt update and the statistics in NumPy (nothing to
    compile); the compiled, vmappable path runs the same code in jax.numpy. Same numbers, to rounding,
    on a linear problem r(θ) = Aθ − b whose answer is known (least squares), with a rank-deficient
    Jacobian for the statistics (an undetermined direction: infinite standard errors)."""
    from jaxnh.identify.problem import _lm_limits, _lm_start, _lm_update, statistics_host

    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 4)) * np.array([1.0, 10.0, 0.1, 3.0])
    b = rng.normal(size=40)

    def run(xp):
        st = _lm_start(xp.asarray(np.zeros(4)), 40, xp=xp)
        lim = _lm_limits(1e-12, 1e-6, 1e-12, 50, np.float64, xp=xp)
        for _ in range(50):
            with np.errstate(invalid="ignore", divide="ignore"):
                st = _lm_update(st, A @ np.asarray(st.trial) - b, xp.asarray(A), lim, xp=xp)
            if bool(st.done):
                break
        return st

    s_np, s_j = run(np), run(jnp)
    assert int(s_np.code) == int(s_j.code) == 0 and int(s_np.k) == int(s_j.k)
    np.testing.assert_allclose(np.asarray(s_np.theta), np.asarray(s_j.theta), rtol=1e-12)
    # it stops when the remaining Gauss–Newton step is below gn_tol = 1e-6 standard errors
    exact = np.linalg.lstsq(A, b, rcond=None)[0]
    std = statistics_host(A, A @ exact - b)["std"]
    assert np.max(np.abs(np.asarray(s_np.theta) - exact) / std) < 1e-5

    J = np.concatenate([A, A[:, :1] * 2.0], axis=1)  # column 5 = 2 × column 1
    host, comp = statistics_host(J, b), statistics(jnp.asarray(J), jnp.asarray(b))
    assert int(host["rank"]) == int(comp["rank"]) == 4
    assert np.isinf(host["std"][0]) and np.isinf(host["std"][4]) and np.all(np.isfinite(host["std"][1:4]))
    for key in ("std", "s2", "gn_step", "cov", "sv"):
        h, c = np.asarray(host[key]), np.asarray(comp[key])
        fin = np.isfinite(h)
        assert np.array_equal(fin, np.isfinite(c)), key
        np.testing.assert_allclose(
            h[fin], c[fin], rtol=1e-9, atol=1e-12 * np.max(np.abs(h[fin]), initial=1.0), err_msg=key
        )


@pytest.mark.slow
def test_one_levenberg_marquardt_driver_compiled_and_on_the_host(tmp_path):
    """`solve_least_squares` (the compiled, vmappable loop) and `solve_least_squares_host` (the
    Python loop `fit` uses) are the same driver: same answer, steps and result on a small user's
    mechanism (tests/cli_model.py); the residual count comes from the shapes alone."""
    import cli_model

    from jaxnh.identify import prepare, solve_least_squares
    from jaxnh.identify.problem import solve_least_squares_host

    (tmp_path / "d.csv").write_text(cli_model.record_text(n=60))
    rec = read_csv(tmp_path / "d.csv", coordinates=("a", "b"), inputs=("F",))
    kw: dict[str, Any] = dict(free=("J1", "c"), positive=("J1", "c"), noise=2e-4, rtol=1e-8)
    for shooting in (2, 1):
        problem, theta0, obs, _ = prepare(cli_model.MECH, cli_model.params(rec), rec, shooting=shooting, **kw)
        n = jax.eval_shape(lambda: problem.raw_residuals(theta0, obs)).shape[0]
        assert problem.n_residuals(obs) == n
    host = solve_least_squares_host(problem, theta0, obs)
    loop = solve_least_squares(problem, theta0, obs)
    assert int(host["result"]) == int(loop["result"]) == 0 and int(host["steps"]) == int(loop["steps"])
    np.testing.assert_allclose(np.asarray(host["theta"]), np.asarray(loop["theta"]), rtol=1e-9, atol=1e-12)


def test_host_svd_of_a_non_finite_matrix_is_nan_like_the_compiled_one():
    """NumPy's SVD raises for NaN and can hang for inf; the host fit's `thin_svd` returns NaN
    (what jax.numpy gives), so a failed evaluation becomes a failure status, not a crash or a hang."""
    from jaxnh.identify.problem import statistics_host, thin_svd

    for bad in (np.nan, np.inf):
        M = np.ones((6, 3))
        M[2, 1] = bad
        U, s, Vt = thin_svd(M)
        assert U.shape == (6, 3) and s.shape == (3,) and Vt.shape == (3, 3)
        assert np.all(np.isnan(s)) and np.all(np.isnan(np.asarray(jnp.linalg.svd(M, full_matrices=False)[1])))
        st = statistics_host(M, np.ones(6))
        assert not np.any(np.isfinite(st["std"]))
