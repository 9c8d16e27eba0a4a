"""`jaxnh.design.fd_gradient` against exact derivatives, for entries from 1e-12 to 1e12.

Central differences with step s have a truncation error c s² and a rounding error δ |f| / s
(δ the relative noise of f, the machine epsilon here). With the step relative to the function's
own length scale L (|x| for powers and 1/x, 1 for exp x), s = eps^(1/3) L, both are of order
eps^(2/3) of |f'| + |f| / L: that is the tolerance below, times 8 for the constants (the
truncation left by the step-halving test is at most a third of eps^(2/3) |f'|, the rounding of
each of the two values of f up to a few eps of the terms computed). Measured: at most 4
eps^(2/3) in float64 and 6 in float32 over every case here.

The reported failures of the former step h·max(1, |x|) with h = 1e-6 (absolute below |x| = 1) are
of the first two kinds below: f = 1/x at x = 1e-5 gave −1.0101e10 for −1e10 (a step of a tenth of x),
f = log x at x = 1e-8 gave NaN for 1e8 (the step crossed 0). The third, −1.490 for −1.515, is a
large f differenced over the absolute step 1e-6: the quotient can only take multiples of
ulp(f) / 2e-6, and −1.490 is exactly −200 × 2⁻²⁶ / 2e-6 (ulp(f) = 2⁻²⁶ for |f| in [6.7e7, 1.3e8]);
the function itself was not reported, so the case here is of that kind (1e10 + a x, whose rounding
1e10 eps / 2e-6 ≈ 1 is of the order of the derivative), not a reproduction.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh  # noqa: F401  (64-bit mode)
from jaxnh.design import fd_gradient


XS = [1e-12, 1e-8, 1e-5, 1e-3, 0.5, 1.0, 3.0, 1e3, 1e8, 1e12]

# (name, f, f', the length scale L of f at x, the x it is defined for)
CASES = [
    ("a x^2", lambda x: 3.0 * x**2, lambda x: 6.0 * x, lambda x: x, XS),
    ("1/x", lambda x: 1 / x, lambda x: -1 / x**2, lambda x: x, XS),
    ("log x", jnp.log, lambda x: 1 / x, lambda x: x, XS),
    ("sqrt x", jnp.sqrt, lambda x: 0.5 / np.sqrt(x), lambda x: x, XS),
    ("exp x", jnp.exp, np.exp, lambda x: 1.0, [x for x in XS if x < 700]),
    ("exp(x / 1e6)", lambda x: jnp.exp(x / 1e6), lambda x: np.exp(x / 1e6) / 1e6, lambda x: 1e6, XS[:-2]),
    ("1e10 exp x", lambda x: 1e10 * jnp.exp(x), lambda x: 1e10 * np.exp(x), lambda x: 1.0, XS[:7]),
    ("1e10 + 1.515 x", lambda x: 1e10 + 1.515 * x, lambda x: 1.515 + 0 * x, lambda x: 1e10, XS[:-1]),
    ("1e-10 / x", lambda x: 1e-10 / x, lambda x: -1e-10 / x**2, lambda x: x, XS),
    ("cos x", jnp.cos, lambda x: -np.sin(x), lambda x: 1.0, XS[:-1]),
]


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("name, f, df, length, xs", CASES, ids=[c[0] for c in CASES])
def test_fd_gradient_matches_exact_derivatives_at_every_scale(dtype, name, f, df, length, xs):
    eps = float(jnp.finfo(dtype).eps)
    for x in xs:
        x = np.asarray(x, dtype)
        if dtype == jnp.float32 and not np.isfinite(np.asarray(f(jnp.asarray(x, dtype)))):
            continue  # 1e10 exp x overflows float32's range beyond x ≈ 65
        x64 = float(x)
        if np.spacing(x) > eps ** (1 / 3) * length(x64):  # x too coarse in its dtype to follow f: refused
            with pytest.raises(ValueError, match="resolution"):
                fd_gradient(lambda p: f(p["x"]), {"x": jnp.asarray(x, dtype)})
            continue
        g = fd_gradient(lambda p: f(p["x"]), {"x": jnp.asarray(x, dtype)})["x"]
        assert g.dtype == dtype
        exact = float(df(x64))
        fx = float(f(jnp.asarray(x64)))
        tol = 8 * eps ** (2 / 3) * (abs(exact) + abs(fx) / max(x64, length(x64)))
        assert abs(float(g) - exact) <= tol, (name, x64, float(g), exact, tol)


def test_fd_gradient_reported_cases_are_right():
    """The three reported cases' kinds, exactly: each was wrong with the former step."""
    eps = float(np.finfo(np.float64).eps)
    for f, x, exact, length in (
        (lambda x: 1 / x, 1e-5, -1e10, 1e-5),
        (jnp.log, 1e-8, 1e8, 1e-8),
        (lambda x: 1e10 - 1.515 * x, 0.3, -1.515, 1e10),
    ):
        g = float(fd_gradient(lambda p: f(p["x"]), {"x": jnp.asarray(x)})["x"])
        tol = 8 * eps ** (2 / 3) * (abs(exact) + abs(float(f(x))) / length)
        assert abs(g - exact) <= tol, (x, g, exact, tol)


def test_fd_gradient_entries_at_zero_and_several_leaves():
    """An entry at exactly 0 takes the step h·scale (1 by default); entries of one leaf and of
    several leaves are differenced one at a time."""
    eps = float(np.finfo(np.float64).eps)
    p = {"a": jnp.array([0.0, 2e-9, -3e7]), "b": jnp.array(0.0)}

    def f(q):
        return jnp.sum(jnp.exp(q["a"] / 1e7)) + 5.0 * q["b"] + q["b"] ** 2

    g = fd_gradient(f, p)
    exact = np.exp(np.asarray(p["a"]) / 1e7) / 1e7
    np.testing.assert_allclose(g["a"], exact, rtol=8 * eps ** (2 / 3) * 2)  # |f| / L = |f'| here
    assert abs(float(g["b"]) - 5.0) <= 8 * eps ** (2 / 3) * 5.0


def test_fd_gradient_refuses_bad_arguments_and_a_function_it_cannot_difference():
    p = {"x": jnp.asarray(1.0)}
    with pytest.raises(ValueError, match="h"):
        fd_gradient(lambda q: q["x"] ** 2, p, h=0.0)
    with pytest.raises(ValueError, match="scale"):
        fd_gradient(lambda q: q["x"] ** 2, p, scale=-1.0)
    with pytest.raises(ValueError, match="f\\(params\\)"):
        fd_gradient(lambda q: jnp.log(q["x"] - 2.0), p)

    # f with a ripple of 1e-6 of its size on a scale of 1e-9 (a loose solve's error), differenced with
    # the step meant for rounding: the quotients do not settle, and the error names h
    def rippled(q):
        return q["x"] ** 2 * (1 + 1e-6 * jnp.sin(1e9 * q["x"]))

    with pytest.raises(ValueError, match="h ≈"):
        fd_gradient(rippled, p)
    # with h for that noise, (1e-6)^(1/3) = 1e-2, the smooth derivative 2x to the order h² of it
    # (ripple 1e-6 over a step 1e-2, plus truncation): within 4 h²
    g = float(fd_gradient(rippled, p, h=1e-2)["x"])
    assert abs(g - 2.0) <= 4 * 1e-4 * 2.0, g
