"""The batch and design jobs with a friction contact (issue 43): `jaxnh.sweep` and
`jaxnh.design.optimize` through a stick→slip transition, against the closed form.

The scene: a block of mass m on a rough floor (N = m g given), its one coordinate x (m) held by a
friction row ẋ = 0 while it sticks, pushed along x by a force c·t (N, c in N/s). It sticks while
c t ≤ μs m g and starts to slip at t_s = μs m g / c; the located transition time is
differentiable, d t_s / d c = −μs m g / c².

Tolerances. float64, rtol 1e-10, atol 1e-12. The transition is located by Newton's method on the
solve's interpolant to a residual of the stick margin's scale times 1e3 eps; the margin
μs m g − c t has slope c, so t_s is found to about (1e3 eps · μs m g)/c + rtol · t_s. The bound
below, 1e2 rtol · t_s, holds that with room (t_s ≤ 1 s, μs m g ≈ 5 N, c ≥ 5 N/s).
"""

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402
import pytest  # noqa: E402

import jaxnh as nh  # noqa: E402


RTOL, ATOL = 1e-10, 1e-12
G = 9.81
BASE = {"m": 1.0, "mus": 0.5, "muk": 0.3, "c": 10.0}
TS = jnp.linspace(0.0, 1.2, 7)


def _T(q, qd, t, p):
    return 0.5 * p["m"] * qd[0] ** 2


MECH = nh.Mechanism(
    _T,
    constraints=lambda q, qd, t, p: jnp.stack([qd[0]]),  # the block's slip velocity, m/s
    forces=lambda q, qd, t, p: jnp.stack([p["c"] * t]),  # the push, N
    contacts=nh.FrictionContact(
        0,
        normal_force=lambda q, qd, t, p: p["m"] * G,
        mu_static=lambda q, qd, t, p: p["mus"],
        mu_kinetic=lambda q, qd, t, p: p["muk"],
        name="floor",
    ),
)


def onset(p):
    """The located stick→slip time, s, and the solve's status."""
    sol = nh.simulate(MECH, p, jnp.zeros(1), jnp.zeros(1), TS, rtol=RTOL, atol=ATOL, throw=False)
    return sol.contacts.transition_times[0, 0], sol.status


def exact_onset(c):
    return BASE["mus"] * BASE["m"] * G / c


def test_sweep_with_contacts_matches_the_closed_form_and_a_loop():
    cs = np.array([5.0, 6.0, 7.5, 10.0, 12.0, 20.0])
    t_s, status = nh.sweep(onset, {**BASE, "c": cs}, in_axes=({"m": None, "mus": None, "muk": None, "c": 0},))
    assert np.all(np.asarray(status == nh.STATUS.successful))  # a batch's status (docs/faq.md)
    np.testing.assert_allclose(t_s, exact_onset(cs), rtol=1e2 * RTOL)
    # every member follows the arithmetic of a single call (sweep's contract): to rounding
    one = np.array([float(onset({**BASE, "c": c})[0]) for c in cs[:2]])
    np.testing.assert_allclose(np.asarray(t_s)[:2], one, rtol=1e3 * np.finfo(np.float64).eps)


@pytest.mark.slow
def test_design_with_contacts_reaches_the_push_that_slips_at_the_target_time():
    target = 0.5  # s
    c_star = BASE["mus"] * BASE["m"] * G / target

    def loss(p):
        return (onset(p)[0] - target) ** 2

    # sgd at a step near 1/curvature: the loss's curvature at c* is 2 (d t_s/dc)² = 2 (t_s/c*)²
    lr = 0.8 / (2 * (target / c_star) ** 2)
    best, history = nh.design.optimize(
        loss,
        {**BASE, "c": jnp.asarray(12.0)},
        optimizer=optax.sgd(lr),
        steps=25,
        trainable={"m": False, "mus": False, "muk": False, "c": True},
    )
    assert history[-1] < 1e-3 * history[0]
    # the design's c makes the block slip at the target: |t_s − target| within the located time's
    # error (1e2 rtol t_s), so |c − c*| ≤ c* × that / target
    np.testing.assert_allclose(float(best["c"]), c_star, rtol=1e2 * RTOL + np.sqrt(history[-1]) / target)
    np.testing.assert_allclose(float(onset(best)[0]), target, atol=1e2 * RTOL * target + np.sqrt(history[-1]))
