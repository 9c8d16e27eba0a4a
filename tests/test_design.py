"""Design tools: bounded laws, the optax loop, and the optimal-ratio example's gradient."""

import importlib.util
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxnh.design import Bounded, Chebyshev, fd_gradient, optimize
from jaxnh.profiles import Fourier


ROOT = pathlib.Path(__file__).resolve().parents[1]


def load_example(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_chebyshev_matches_numpy_value_and_derivative():
    coef = np.array([0.3, -1.2, 0.5, 0.25, -0.1])
    law = Chebyshev(coef, 1.0, 5.0)
    t = np.linspace(1.0, 5.0, 17)
    x = (t - 1.0) / 2.0 - 1.0
    C = np.polynomial.chebyshev
    np.testing.assert_allclose(jax.vmap(law)(jnp.asarray(t)), C.chebval(x, coef), rtol=1e-14, atol=1e-14)
    # d/dt = d/dx · dx/dt with dx/dt = 2 / (t1 − t0) = 0.5
    np.testing.assert_allclose(
        jax.vmap(law.derivative)(jnp.asarray(t)), 0.5 * C.chebval(x, C.chebder(coef)), rtol=1e-13, atol=1e-13
    )
    with pytest.raises(ValueError, match="t1 > t0"):
        Chebyshev(coef, 2.0, 2.0)
    with pytest.raises(ValueError, match="non-empty 1-D"):
        Chebyshev(np.zeros((2, 2)))


def test_bounded_stays_inside_and_inverts():
    inner = Fourier(0.0, sin=[40.0], period=1.0)  # inner swings to ±40: the sigmoid saturates
    law = Bounded(inner, 0.4, 2.5)
    u = jax.vmap(law)(jnp.linspace(0.0, 1.0, 101))
    assert np.all(u >= 0.4) and np.all(u <= 2.5) and u.max() > 2.49 and u.min() < 0.41
    for U in (0.41, 1.0, 2.3):
        np.testing.assert_allclose(Bounded(Chebyshev([Bounded.inverse(U, 0.4, 2.5)]), 0.4, 2.5)(0.3), U, rtol=1e-14)
    with pytest.raises(ValueError, match="upper > lower"):
        Bounded(inner, 1.0, 1.0)
    with pytest.raises(TypeError, match="inner must be a jaxnh Profile"):
        Bounded(lambda t: t, 0.0, 1.0)  # pyright: ignore[reportArgumentType]  (wrong on purpose)


def test_optimize_holds_untrainable_leaves_and_returns_best():
    target = jnp.array([1.0, -2.0])
    params = {"x": jnp.zeros(2), "fixed": jnp.array(3.0), "name": "quadratic"}

    def loss(p):
        return jnp.sum((p["x"] - target) ** 2) + p["fixed"]

    trainable = {"x": True, "fixed": False, "name": False}
    best, hist = optimize(loss, params, optimizer=optax.adam(0.1), steps=300, trainable=trainable)
    np.testing.assert_allclose(best["x"], target, atol=1e-3)
    assert float(best["fixed"]) == 3.0 and best["name"] == "quadratic"
    assert hist.shape == (301,) and np.isclose(float(loss(best)), hist.min())
    with pytest.raises(ValueError, match="steps must be a non-negative integer"):
        optimize(loss, params, steps=-1)


def test_optimize_default_trains_coefficients_not_windows_or_bounds():
    """By default only a profile's trainable fields move (Chebyshev coefficients),
    never its time window or the bounds of a Bounded law."""
    law = Bounded(Chebyshev([0.0, 0.0], 0.0, 2.0), 0.4, 2.5)

    def loss(u):  # reach U21 = 2.0 at t = 0.5 s and U21 = 0.8 at t = 1.5 s
        return (u(0.5) - 2.0) ** 2 + (u(1.5) - 0.8) ** 2

    best, hist = optimize(loss, law, optimizer=optax.adam(0.1), steps=400)
    np.testing.assert_allclose([best(0.5), best(1.5)], [2.0, 0.8], atol=1e-3)
    assert (float(best.lower), float(best.upper), float(best.inner.t0), float(best.inner.t1)) == (0.4, 2.5, 0.0, 2.0)
    g = fd_gradient(loss, law)
    assert g.lower is None and g.inner.t0 is None and g.inner.coef.shape == (2,)


def test_fd_gradient_on_a_pytree():
    params = {"a": jnp.array([0.3, -0.7]), "b": jnp.array(1.5), "tag": "x"}

    def f(p):
        return jnp.sin(p["a"][0]) * p["b"] ** 2 + jnp.exp(p["a"][1] * p["b"])

    fd = fd_gradient(f, params, h=1e-5)
    g = eqx.filter_grad(f)(params)
    # central differences with h = 1e-5: truncation ~h² f''' ~ 1e-10, rounding ~ε/h ~ 1e-11
    np.testing.assert_allclose(fd["a"], g["a"], rtol=1e-8)
    np.testing.assert_allclose(fd["b"], g["b"], rtol=1e-8)
    assert fd["tag"] is None


@pytest.mark.slow
def test_optimal_ratio_gradient_matches_central_differences():
    """The gradient `optimize` follows (reverse mode through diffrax) for the
    example's objective, recovered from one SGD step, against central differences.

    The probe law varies and violates both the terminal-speed target and the
    contact-force limit, so every term of the objective contributes. The
    gradient is that of the discrete solution at rtol 1e-8; the reference is a
    central difference (h = 1e-4, truncation ~h² ≈ 1e-8) of the same objective
    solved at rtol 1e-12, since a central difference at rtol 1e-8 carries the
    solver's error divided by h (measured 1.6e-5 of max|g| with the default
    Dopri8, against 1.4e-8 for the autodiff gradient; 3.5e-7 and 1.2e-7 with
    Tsit5). Tolerance 1e-6 of max|g|.
    """
    O = load_example("optimal_ratio")
    probe = O.constant_law(1.1).at[1:].set(3.0 * jnp.array([0.8, -0.6, 1.2, 0.3, -0.4, 0.2, 0.1]))

    def f(c):
        return O.objective(c, 1e2, 5.0)

    lr, seen = 1e-4, []
    _, hist = optimize(f, probe, optimizer=optax.sgd(lr), steps=2, callback=lambda k, v, p: seen.append(p))
    g = (seen[0] - seen[1]) / lr
    g_fd = fd_gradient(lambda c: O.objective(c, 1e2, 5.0, rtol=1e-12), probe, h=1e-4)
    scale = np.max(np.abs(g_fd))
    assert scale > 0.1
    np.testing.assert_allclose(g, g_fd, atol=1e-6 * scale)
    assert hist[1] < hist[0] and hist[2] < hist[1]  # descending along −g
    m = {k: float(v) for k, v in jax.jit(O.metrics)(probe).items()}
    assert m["lam_max"] > O.LAMBDA_MAX and abs(m["w2"] - O.W_TARGET) > 1.0  # both penalties active
