"""Experiment design before measuring: Fisher information against a closed form, the
identifiability diagnosis without data, predictions against a real fit, the design
criterion's gradient against central differences, `jaxnh design`'s input checks, and
the fit's ODE tolerance following the data (issue 18)."""

import importlib.util
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh  # noqa: F401  (64-bit mode)
from jaxnh._cli.design import main as design_main
from jaxnh.design import fd_gradient
from jaxnh.identify._experiment import (
    ChannelNoise,
    design_loss,
    encoder_noise,
    evaluate_design,
    experiment,
    input_spec,
    Limits,
    predict,
    StickLimit,
)
from jaxnh.models import variator as V
from jaxnh.models.variator_fit import embedded_truth, variator_experiment
from jaxnh.profiles import Bounded, Constant, Fourier


ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_encoder_noise_is_the_embedded_records_reading_error():
    T = embedded_truth()
    for counts, jitter, std in zip(T["counts_per_rev"], T["jitter_std"], T["noise_std"]):
        # quantisation step 2π/counts (uniform error, variance step²/12) plus Gaussian jitter
        assert encoder_noise(counts, jitter).total == pytest.approx(std, rel=1e-12)
    assert ChannelNoise(std=2e-4).total == 2e-4
    with pytest.raises(ValueError, match="both zero"):
        ChannelNoise()
    with pytest.raises(ValueError, match="counts_per_rev"):
        encoder_noise(0)


# --- Fisher information of a motion known in closed form ------------------------------------------------

J1, J2, U, M1, M2, W0 = 0.018, 0.045, 1.2, 0.15, -0.05, 4.0
SIG = (3e-4, 7e-4)


@pytest.fixture(scope="module")
def constant_ratio():
    """Constant ratio and torques: phi1 = phi1(0) + w t + a t²/2, phi2 = phi2(0) + U (w t + a t²/2),
    a = (M1 + U M2) / (J1 + J2 U²)."""
    p = V.VariatorParams(J1, J2, Constant(U), M1, M2)
    ts = np.linspace(0.0, 2.0, 101)
    exp = experiment(
        V.mechanism(),
        p,
        ts,
        free=("J1", "J2"),
        positive=("J1", "J2"),
        noise={"phi1": SIG[0], "phi2": SIG[1]},
        q0=[0.1, -0.2],
        qd0=[W0, U * W0],
        rtol=1e-10,
    )
    return exp, predict(exp), ts


def test_fisher_information_matches_closed_form(constant_ratio):
    exp, pred, t = constant_ratio
    I = J1 + J2 * U**2
    a = (M1 + U * M2) / I
    da = np.array([-a * J1 / I, -a * J2 * U**2 / I])  # ∂a/∂log J1, ∂a/∂log J2
    # columns: log J1, log J2, phi1(0), phi2(0), phi1'(0); rows: samples of phi1, then of phi2
    S1 = np.stack([0.5 * t**2 * da[0], 0.5 * t**2 * da[1], np.ones_like(t), np.zeros_like(t), t], axis=1)
    S2 = np.stack([U * 0.5 * t**2 * da[0], U * 0.5 * t**2 * da[1], np.zeros_like(t), np.ones_like(t), U * t], axis=1)
    F = S1.T @ S1 / SIG[0] ** 2 + S2.T @ S2 / SIG[1] ** 2
    assert exp.labels == ("J1", "J2", "phi1(t0)", "phi2(t0)", "phi1'(t0)")
    # the motion is a quadratic in t, which Runge–Kutta integrates to rounding
    np.testing.assert_allclose(pred.fisher, F, rtol=1e-8, atol=1e-8 * np.max(np.abs(F)))


def test_constant_ratio_determines_only_the_reduced_inertia(constant_ratio):
    """With U21 constant only J1 + J2 U² enters the motion: the diagnosis must say so before any data."""
    _, pred, _ = constant_ratio
    assert not pred.identifiable
    assert np.isinf(pred.std[:2]).all() and np.isfinite(pred.std[2:]).all()
    (u,) = pred.identifiability.undetermined
    d = u["direction"]  # direction in (log J1, log J2) along which J1 + J2 U² is constant
    expected = np.array([J2 * U**2, -J1]) / (J2 * U**2)
    np.testing.assert_allclose([d["J2"] / d["J1"]], [expected[1] / expected[0]], rtol=1e-6)


def test_stick_limit_is_the_friction_cone_of_the_contact_force(constant_ratio):
    """With U21, M1, M2 constant the roller's multiplier (eq. 8) is constant,
    λ = M2 − J2 U a with a = (M1 + U M2)/(J1 + J2 U²), N·m; its tangential force is λ/ρ with
    ρ = r/U, so the stick limit's utilisation is |λ| U / (r μs N), and the penalty is zero below
    99 % of the cone and positive above. The motion is quadratic in t, integrated to rounding at
    rtol 1e-10: the utilisation agrees to 1e-8."""
    exp, _, _ = constant_ratio
    p = V.VariatorParams(J1, J2, Constant(U), M1, M2)
    lam = M2 - J2 * U * (M1 + U * M2) / (J1 + J2 * U**2)
    r = 0.05
    need = abs(lam) * U / r  # the tangential force the roller needs, N
    for capacity in (2.0 * need, 0.5 * need):
        loss = design_loss(exp, "D", limits=Limits(stick=StickLimit(capacity=capacity, lever=V.ContactRadius(r))))
        ev = evaluate_design(loss, p)
        assert abs(ev["stick"] / (need / capacity) - 1) <= 1e-8
        penalties = loss.terms(p)[1]
        assert (float(penalties["stick"]) > 0) == (capacity < need)
    with pytest.raises(ValueError, match="limits.stick"):
        design_loss(exp, "D", limits=Limits(stick=StickLimit(capacity=-1.0, lever=V.ContactRadius(r))))


# --- the embedded record's experiment ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def embedded():
    exp, params = variator_experiment()
    return exp, params, predict(exp)


@pytest.mark.extended
def test_zero_torques_diagnosis_names_the_ratio_before_any_data(embedded):
    exp, params, _ = embedded
    zero = V.VariatorParams(params.J1, params.J2, params.U21, Constant(0.0), Constant(0.0))
    pred = predict(exp, zero)
    assert not pred.identifiable
    (u,) = pred.identifiability.undetermined
    assert u["identifiable"] == "J1/J2"
    assert "only J1/J2 is determined" in pred.identifiability.messages[0]
    assert math.isinf(pred.estimates["J1"]["std"]) and math.isinf(pred.estimates["J2"]["std"])
    assert np.all(np.isfinite(pred.estimates["U21"]["std"]))  # the ratio law is still determined


@pytest.mark.slow
def test_prediction_agrees_with_the_fit_of_the_embedded_record(embedded):
    """The fit reports std = prediction · s (residual scaling, noise estimated from the record):
    s² = 1 ± 0.04 and the noise estimates ± 3 % (n = 1501): agreement within 10 % is expected."""
    from jaxnh.identify import load_default
    from jaxnh.models.variator_fit import fit_variator

    _, _, pred = embedded
    res = fit_variator(load_default())
    assert res.converged
    ratio = res.std / pred.std
    assert np.all(np.abs(ratio - 1) < 0.10), dict(zip(res.labels, np.round(ratio, 3)))
    assert pred.identifiable and pred.max_multiplier is not None


# --- the design criterion's gradient ---------------------------------------------------------------------


@pytest.mark.extended
def test_design_gradient_matches_central_differences():
    """Forward-over-forward derivative of log var(J1) + penalties with respect to the Fourier
    coefficients of a bounded motor torque, at rtol 1e-12, against central differences."""
    T = embedded_truth()
    from jaxnh.profiles import CubicSpline

    Ux = CubicSpline(T["U21_knots"][:3], T["U21_values"][:3])
    M1x = Bounded(Fourier(0.1, cos=[0.4, -0.3], sin=[0.7, 0.2], period=2.0), -0.27, 0.27)
    p = V.VariatorParams(T["J1"], T["J2"], Ux, M1x, -0.08)
    ts = np.linspace(0.0, 2.0, 101)
    exp = experiment(
        V.mechanism(),
        p,
        ts,
        free=("J1", "J2", "U21"),
        positive=("J1", "J2", "U21"),
        noise={"phi1": encoder_noise(8192, 3e-4), "phi2": encoder_noise(4096, 6e-4)},
        qd0=[4.0, 3.2],
        rtol=1e-12,
        atol=1e-12,
    )
    loss = design_loss(exp, "A", of=("J1",), limits=Limits(multiplier=0.2, std={"J2": 1e-4}))
    spec = input_spec(p, ("M1",))
    import equinox as eqx

    from jaxnh.identify.design import _forward_value_and_grad

    theta, rest = eqx.partition(p, spec)
    value, g = jax.jit(lambda th: _forward_value_and_grad(lambda x: loss(eqx.combine(x, rest)), th))(theta)
    g_fd = fd_gradient(loss, p, h=1e-4, trainable=spec)
    ga = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(g)])
    gf = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(g_fd)])
    assert ga.shape == (5,) and np.all(np.isfinite(ga))
    np.testing.assert_allclose(ga, gf, rtol=1e-6, atol=1e-6 * np.max(np.abs(gf)))


# --- `jaxnh design`: bad input is refused before any work -------------------------------------------------


def test_design_cli_refuses_bad_input(tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    assert design_main(["--out", str(f)]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err
    (tmp_path / "o" / "design.json").mkdir(parents=True)
    assert design_main(["--out", str(tmp_path / "o")]) == 2
    assert "is a folder" in capsys.readouterr().err
    for bad, msg in (
        (["--harmonics", "0"], "--harmonics"),
        (["--lambda-max", "-1"], "--lambda-max"),
        (["--of", "J3"], "--of"),
        (["--energy-max", "nan"], "--energy-max"),
        (["--lambda-max", "1", "--normal-force", "50"], "choose one limit"),
        (["--mu-static", "0"], "--mu-static"),
    ):
        assert design_main(["--out", str(tmp_path / "ok"), *bad]) == 2
        assert msg in capsys.readouterr().err
    assert design_main(["--inputs", "M3"]) == 2  # argparse's own usage error
    assert design_main(["--help"]) == 0
    assert not (tmp_path / "ok" / "design.json").exists()


# --- fits keep up with informative data -----------------------------------------------------------------


def _maker():
    spec = importlib.util.spec_from_file_location("make_variator_data", ROOT / "examples" / "make_variator_data.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_fit_of_an_informative_record_converges_cleanly():
    """Issue 18's record: M1 = 0.27 sin(0.8πt), otherwise the embedded set-up."""
    import jaxnh as nh
    from jaxnh.identify.data import Record
    from jaxnh.models.variator_fit import fit_variator

    mk = _maker()
    truth = mk.truth()
    M1 = Fourier(0.0, cos=[0.0, 0.0], sin=[0.0, 0.27], period=5.0)  # harmonic 2 of 5 s: 0.27 sin(0.8π t)
    p = V.VariatorParams(truth.J1, truth.J2, truth.U21, M1, truth.M2)
    t = mk.sample_times()
    ts = jnp.asarray(t)
    sol = nh.simulate(V.mechanism(), p, jnp.zeros(2), jnp.array([4.0, 3.2]), ts, rtol=1e-12, atol=1e-12)
    y = np.asarray(mk.measure(sol.q, jax.random.PRNGKey(1)))
    rec = Record(
        t,
        {"phi1": y[:, 0], "phi2": y[:, 1]},
        {"M1": np.asarray(jax.vmap(M1)(ts)), "M2": np.asarray(jax.vmap(truth.M2)(ts))},
        "issue 18",
    )
    res = fit_variator(rec)
    assert res.converged and res.iterations <= 20, res.message
    assert res.gn_step < 0.05
    z = (np.asarray([res.estimates["J1"]["value"], res.estimates["J2"]["value"]]) - [truth.J1, truth.J2]) / np.asarray(
        [res.estimates["J1"]["std"], res.estimates["J2"]["std"]]
    )
    assert np.all(np.abs(z) < 3.5)


@pytest.mark.slow
def test_fit_tightens_the_ode_tolerance_for_a_very_precise_record():
    """Encoders 300× finer than the embedded record's (Gaussian 2 and 4 µrad): at rtol 1e-8 the solver's
    error is a sizeable fraction of the standard errors, so rtol="auto" must tighten it, converge, and
    say so; the result must contain the truth."""
    from jaxnh.identify import load_default
    from jaxnh.identify.data import Record
    from jaxnh.models.variator_fit import fit_variator

    mk = _maker()
    q = mk.clean_motion()
    y = q + np.array([2e-6, 4e-6]) * np.random.default_rng(3).standard_normal(q.shape)
    rec = Record(mk.sample_times(), {"phi1": y[:, 0], "phi2": y[:, 1]}, load_default().inputs, "precise")
    res = fit_variator(rec, rtol="auto")
    assert res.converged, res.message
    assert res.problem.rtol < 1e-9 and "ODE rtol tightened" in res.message
    for k in ("J1", "J2"):
        assert abs(res.estimates[k]["value"] - mk.TRUTH[k]) < 3.5 * res.estimates[k]["std"]


def test_multistart_keeps_the_best_acceptable_start_and_forward_gradients_agree():
    """Two minima of a double well, (x ∓ 1)², −0.5 deeper at x = +1; only x < 0 is acceptable."""
    import optax

    from jaxnh.design import multistart, optimize

    def loss(p):
        x = p["x"][0]
        return jnp.minimum((x - 1.0) ** 2 - 0.5, (x + 1.0) ** 2)

    starts = [{"x": jnp.array([0.8])}, {"x": jnp.array([-0.7])}, {"x": jnp.array([-1.3])}]
    best, runs, k = multistart(
        loss, starts, accept=lambda p: (float(p["x"][0]) < 0, {"value": float(loss(p))}), steps=200, learning_rate=0.05
    )
    assert [r["accepted"] for r in runs] == [False, True, True]
    assert k in (1, 2) and abs(float(best["x"][0]) + 1.0) < 1e-3
    # without the constraint the deeper well wins
    best, _, k = multistart(loss, starts, steps=200, learning_rate=0.05)
    assert k == 0 and abs(float(best["x"][0]) - 1.0) < 1e-3
    # forward- and reverse-mode gradients give the same optimisation
    a, ha = optimize(loss, starts[1], optimizer=optax.adam(0.05), steps=30, gradient="forward")
    b, hb = optimize(loss, starts[1], optimizer=optax.adam(0.05), steps=30, gradient="reverse")
    np.testing.assert_allclose(ha, hb, rtol=1e-12)
