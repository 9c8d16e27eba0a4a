"""Friction-held contacts (`jaxnh.FrictionContact`): stick, slip and the transitions between,
checked against closed forms, under jit, vmap and grad, for both formulations.

Closed forms used here (derived in the docstrings of each test's model):

* a cylinder (k = I/(mR²) = 1/2) or a ball (k = 2/5) sliding without spin on level ground
  with speed v0: the kinetic force −μk m g slows the centre (x'' = −μk g) and spins the body up
  (R θ'' = μk g / k), so the slip velocity w = x' − R θ' falls like v0 − μk g (1 + 1/k) t and
  rolling starts at t* = k v0 / ((1 + k) μk g) with speed v* = v0 / (1 + k); the energy lost,
  ½ m v0² k/(1+k), does not depend on μk;
* a cylinder on an incline of angle α: rolling needs the force k m g sin α/(1 + k), inside the
  cone μs m g cos α iff tan α ≤ μs (1 + 1/k); above, it slips from rest with the slip
  acceleration g [sin α − μk cos α (1 + 1/k)];
* the variator with no torques, rolling `r φ1' − ρ(t) φ2' = 0` (m/s, paper eq. 4): see
  `test_variator_slip_onset`.

Tolerances. The solves use RTOL = 1e-10 (ATOL = 1e-12). The level-ground and incline motions
are polynomial in t of degree ≤ 2, which every Runge–Kutta method integrates exactly, so only
the event's root finder (Newton to 1e3 eps on t and on the normalised guard) and rounding
remain: errors of a few 1e3 eps, well inside the required 1e-9 (values) and 1e-7 (derivatives).
The variator's motion is not polynomial: its onset time is accurate to about RTOL times the
time scale, inside the required 1e-8 s.
"""

from __future__ import annotations

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh


EPS = float(np.finfo(np.float64).eps)
RTOL, ATOL = 1e-10, 1e-12
G = 9.81  # m/s²
METHODS = ("lagrange", "appell")


def contacts(sol) -> nh.ContactDiagnostics:
    """The contact diagnostics of a friction solve (present: the mechanism has contacts)."""
    assert sol.contacts is not None
    return sol.contacts


def slipping(sol) -> jax.Array:
    """Which contacts slip at each report time (present: the mechanism has contacts)."""
    assert sol.slipping is not None
    return sol.slipping


def root(f, a: float, b: float) -> float:
    """The root of f in [a, b] (f(a), f(b) of opposite signs) by bisection, to a bracket of 4 eps |b|."""
    fa = f(a)
    assert fa * f(b) < 0
    while b - a > 4 * EPS * abs(b):
        mid = 0.5 * (a + b)
        if (f(mid) > 0) == (fa > 0):
            a = mid
        else:
            b = mid
    return 0.5 * (a + b)


def _p(name):
    """A contact value read from params (differentiable)."""
    return lambda q, qd, t, p: p[name]


# --- a cylinder (one-row contact) and a ball (two-row contact) on level ground or an incline ------


def cylinder_T(q, qd, t, p):
    """q = (x along the ground or down the slope, m; θ, rad)."""
    return 0.5 * p["m"] * qd[0] ** 2 + 0.5 * p["k"] * p["m"] * p["R"] ** 2 * qd[1] ** 2


def cylinder_slip(q, qd, t, p):
    """Slip velocity of the contact point, m/s."""
    return jnp.stack([qd[0] - p["R"] * qd[1]])


def cylinder_V(q, t, p):
    """Gravity along an incline of angle alpha (x down the slope), J."""
    return -p["m"] * G * jnp.sin(p["alpha"]) * q[0]


def cylinder_push(q, qd, t, p):
    """A push F0 exp(−t/tau) on the centre, N (F0 = 0 but in `test_push_from_rest`)."""
    return jnp.stack([p["F0"] * jnp.exp(-t / p["tau"]), 0.0 * t])


CYLINDER = nh.Mechanism(
    cylinder_T,
    constraints=cylinder_slip,
    potential=cylinder_V,
    forces=cylinder_push,
    contacts=(
        nh.FrictionContact(
            rows=(0,),
            normal_force=lambda q, qd, t, p: p["m"] * G * jnp.cos(p["alpha"]),
            mu_static=_p("mu_s"),
            mu_kinetic=_p("mu_k"),
            name="ground",
        ),
    ),
    names=("x", "theta"),
)
CYL = {"m": 2.0, "R": 0.1, "k": 0.5, "alpha": 0.0, "mu_s": 0.5, "mu_k": 0.3, "F0": 0.0, "tau": 1.0}


def ball_T(q, qd, t, p):
    """q = (x, y, a_x, a_y): the centre (m) and the integrals of the angular velocity about x and y
    (rad; the ball's orientation does not enter T or the contact, so these suffice)."""
    return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * p["k"] * p["m"] * p["R"] ** 2 * (qd[2] ** 2 + qd[3] ** 2)


def ball_slip(q, qd, t, p):
    """Slip velocity of the contact point (x, y), m/s: v + ω × (−R e_z)."""
    return jnp.stack([qd[0] - p["R"] * qd[3], qd[1] + p["R"] * qd[2]])


BALL = nh.Mechanism(
    ball_T,
    constraints=ball_slip,
    contacts=nh.FrictionContact((0, 1), lambda q, qd, t, p: p["m"] * G, _p("mu_s"), _p("mu_k"), name="ball"),
)
BAL = {"m": 1.5, "R": 0.05, "k": 0.4, "mu_s": 0.5, "mu_k": 0.2}


def level_ground_closed_form(v0, mu_k, k, m, T):
    """(t*, v*, x(T), energy lost) for sliding without spin from x = 0, T > t*."""
    t_star = k * v0 / ((1 + k) * mu_k * G)
    v_star = v0 / (1 + k)
    x_star = v0 * t_star - 0.5 * mu_k * G * t_star**2
    return t_star, v_star, x_star + v_star * (T - t_star), 0.5 * m * v0**2 * k / (1 + k)


TS = jnp.linspace(0.0, 1.0, 11)


def _cyl(p, qd0, method, **kw):
    """Every cylinder solve of this module: one compiled program per method."""
    return nh.simulate(
        CYLINDER,
        p,
        jnp.zeros(2),
        qd0,
        TS,
        method=method,
        rtol=RTOL,
        atol=ATOL,
        max_transitions=4,
        record=("multipliers", "residual"),
        **kw,
    )


def _cylinder(mu_k, method, v0=3.0, **kw):
    return _cyl({**CYL, "mu_k": mu_k}, jnp.array([v0, 0.0]), method, **kw)


@pytest.mark.parametrize("method", METHODS)
def test_cylinder_slides_then_rolls(method):
    v0, mu_k = 3.0, 0.3
    sol = _cylinder(mu_k, method)
    t_star, v_star, x_T, lost = level_ground_closed_form(v0, mu_k, CYL["k"], CYL["m"], 1.0)
    assert sol.message == "success"
    ((t, kind),) = contacts(sol).transitions(0)  # one transition: it locks
    assert kind == "slip→stick"
    # the initial state violates the friction row (w = v0): it starts slipping, not refused
    assert bool(slipping(sol)[0, 0]) and contacts(sol).slip_intervals(0) == [(0.0, t)]
    assert abs(t / t_star - 1) <= 1e-9
    assert abs(float(sol.qd[-1, 0]) / v_star - 1) <= 1e-9
    assert abs(float(sol.q[-1, 0]) / x_T - 1) <= 1e-9
    assert abs(float(contacts(sol).dissipated_energy[0]) / lost - 1) <= 1e-9
    assert abs(float(contacts(sol).slip_time[0]) / t_star - 1) <= 1e-9
    # slip distance: ∫ w dt = v0 t* / 2 (w falls linearly to 0)
    assert abs(float(contacts(sol).slip_distance[0]) / (0.5 * v0 * t_star) - 1) <= 1e-9
    # while slipping the multiplier is the kinetic force −μk m g, N; while rolling freely 0
    slips = np.asarray(slipping(sol)[:, 0])
    np.testing.assert_allclose(np.asarray(sol.multipliers)[slips, 0], -mu_k * CYL["m"] * G, rtol=1e3 * EPS)
    np.testing.assert_allclose(np.asarray(sol.multipliers)[~slips, 0], 0.0, atol=1e3 * EPS * CYL["m"] * G)
    # the residual of the friction row is the slip velocity: v0 − μk g (1 + 1/k) t while slipping
    w = v0 - mu_k * G * (1 + 1 / CYL["k"]) * np.asarray(TS)
    np.testing.assert_allclose(np.asarray(sol.residual)[slips, 0], w[slips], rtol=1e-9)
    assert float(np.max(np.abs(np.asarray(sol.residual)[~slips, 0]))) <= 1e-9 * v0


@pytest.mark.slow
def test_cylinder_derivatives_through_the_transition():
    """dt*/dμk and dx(T)/dμk against the closed form, and the μk-derivative of the energy lost
    (which does not depend on μk) vanishing: the transition time is differentiated through the
    restart (a restart at a frozen time would give dx(T)/dμk = 0 − ... wrong by the saltation term)."""
    v0 = 3.0

    def outputs(mu_k):
        sol = _cylinder(mu_k, "lagrange", v0=v0)
        return jnp.stack([contacts(sol).transition_times[0, 0], sol.q[-1, 0], contacts(sol).dissipated_energy[0]])

    def exact(mu_k):
        t_star, _, x_T, lost = level_ground_closed_form(v0, mu_k, CYL["k"], CYL["m"], 1.0)
        return jnp.stack([t_star, x_T, lost + 0 * mu_k])

    mu = jnp.asarray(0.3)
    J, Je = jax.jit(jax.jacrev(outputs))(mu), jax.jacfwd(exact)(mu)
    assert abs(float(J[0] / Je[0]) - 1) <= 1e-7, (J, Je)
    assert abs(float(J[1] / Je[1]) - 1) <= 1e-7, (J, Je)
    lost = level_ground_closed_form(v0, 0.3, CYL["k"], CYL["m"], 1.0)[3]
    assert abs(float(J[2])) <= 1e-9 * lost, J
    # and central differences agree (away from grazing: t* is well inside (0, T))
    h = 1e-5
    fd = (outputs(mu + h) - outputs(mu - h)) / (2 * h)
    np.testing.assert_allclose(np.asarray(J[:2]), np.asarray(fd[:2]), rtol=1e-6)


@pytest.mark.slow
def test_forward_mode_derivatives_and_reverse_mode_refused():
    """With contacts, adjoint=ForwardSensitivity() is served by diffrax.ForwardMode(): jax.jacfwd
    gives dt*/dμk and dx(T)/dμk of the closed form (the bound of the reverse-mode test above), and
    jax.grad, which would have to transpose ForwardMode's while loop, is refused naming the adjoint
    and the fix (JAX's own message names neither)."""
    v0 = 3.0

    def outputs(mu_k):
        sol = _cylinder(mu_k, "lagrange", v0=v0, adjoint=nh.ForwardSensitivity())
        return jnp.stack([contacts(sol).transition_times[0, 0], sol.q[-1, 0]])

    def exact(mu_k):
        t_star, _, x_T, _ = level_ground_closed_form(v0, mu_k, CYL["k"], CYL["m"], 1.0)
        return jnp.stack([t_star, x_T])

    mu = jnp.asarray(0.3)
    J, Je = jax.jacfwd(outputs)(mu), jax.jacfwd(exact)(mu)
    np.testing.assert_allclose(np.asarray(J), np.asarray(Je), rtol=1e-7)
    with pytest.raises(TypeError, match=r"ForwardSensitivity\(\).*forward mode only.*RecursiveCheckpointAdjoint"):
        jax.grad(lambda m: outputs(m)[1])(mu)


@pytest.mark.parametrize("method", METHODS)
def test_ball_two_row_contact(method):
    """A ball sliding without spin, obliquely (both rows of its contact slip): the kinetic force is
    −μk m g along the slip velocity, which keeps its direction; the closed form is the cylinder's
    with k = 2/5."""
    v0, beta = 2.0, 0.6
    qd0 = jnp.array([v0 * math.cos(beta), v0 * math.sin(beta), 0.0, 0.0])
    sol = nh.simulate(BALL, BAL, jnp.zeros(4), qd0, TS, method=method, rtol=RTOL, atol=ATOL, record=("multipliers",))
    t_star, v_star, x_T, lost = level_ground_closed_form(v0, BAL["mu_k"], BAL["k"], BAL["m"], 1.0)
    ((t, kind),) = contacts(sol).transitions(0)
    assert kind == "slip→stick" and abs(t / t_star - 1) <= 1e-9
    assert abs(float(jnp.hypot(sol.qd[-1, 0], sol.qd[-1, 1])) / v_star - 1) <= 1e-9
    assert abs(float(jnp.hypot(sol.q[-1, 0], sol.q[-1, 1])) / x_T - 1) <= 1e-9
    assert abs(float(contacts(sol).dissipated_energy[0]) / lost - 1) <= 1e-9
    lam = np.asarray(sol.multipliers)[np.asarray(slipping(sol)[:, 0])]
    want = -BAL["mu_k"] * BAL["m"] * G * np.array([math.cos(beta), math.sin(beta)])
    np.testing.assert_allclose(lam, np.broadcast_to(want, lam.shape), rtol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_incline_threshold(method):
    """Just below tan α = μs (1 + 1/k) the cylinder rolls from rest with the friction force
    k m g sin α/(1 + k); just above, it slips from rest with slip acceleration
    g [sin α − μk cos α (1 + 1/k)], and its slip never stops."""
    k, mu_s, mu_k = CYL["k"], CYL["mu_s"], CYL["mu_k"]
    threshold = math.atan(mu_s * (1 + 1 / k))
    for factor, slips in ((0.99, False), (1.01, True)):
        alpha = threshold * factor
        p = {**CYL, "alpha": alpha}
        sol = _cyl(p, jnp.zeros(2), method)
        assert sol.message == "success"
        assert contacts(sol).transitions(0) == []
        assert np.all(np.asarray(slipping(sol)[:, 0]) == slips)
        w = np.asarray(sol.qd[:, 0] - CYL["R"] * sol.qd[:, 1])
        if slips:
            a_slip = G * (math.sin(alpha) - mu_k * math.cos(alpha) * (1 + 1 / k))
            np.testing.assert_allclose(w[1:] / np.asarray(TS)[1:], a_slip, rtol=1e-9)
            assert math.isnan(float(contacts(sol).peak_utilisation[0]))
        else:
            scale = CYL["m"] * G
            assert float(np.max(np.abs(w))) <= 1e-9
            F = -k * CYL["m"] * G * math.sin(alpha) / (1 + k)
            np.testing.assert_allclose(np.asarray(sol.multipliers)[:, 0], F, atol=1e-9 * scale)
            u = abs(F) / (mu_s * CYL["m"] * G * math.cos(alpha))  # = tan α / (μs (1 + 1/k))
            assert abs(float(contacts(sol).peak_utilisation[0]) - u) <= 1e-9


def test_slip_from_rest_does_not_fire_at_its_own_start():
    """A contact that starts slipping from rest has a guard (its slip speed) exactly 0 at the start:
    it must not be taken for a stop (no transition, one segment, slipping to the end)."""
    alpha = 1.2 * math.atan(CYL["mu_s"] * (1 + 1 / CYL["k"]))
    for method in METHODS:
        sol = _cyl({**CYL, "alpha": alpha}, jnp.zeros(2), method)
        assert int(contacts(sol).transitions_used) == 0 and int(sol.stats["segments"]) == 1
        assert bool(jnp.all(slipping(sol)))


@pytest.mark.parametrize("method", METHODS)
def test_push_from_rest(method):
    """A cylinder at rest pushed by F0 exp(−t/τ) with k F0/(1 + k) > μs m g slips from the start
    (its velocity scale is 0 there) and locks where the slip velocity
    w = (F0 τ/m)(1 − e^(−t/τ)) − μk g (1 + 1/k) t returns to 0 (then rolling needs
    k F/(1 + k) < μs m g: it stays locked)."""
    m, k, mu_k, mu_s = CYL["m"], CYL["k"], CYL["mu_k"], CYL["mu_s"]
    F0, tau = 40.0, 0.2
    assert k * F0 / (1 + k) > mu_s * m * G
    sol = _cyl({**CYL, "F0": F0, "tau": tau}, jnp.zeros(2), method)

    def w(t):
        return F0 * tau / m * (1 - math.exp(-t / tau)) - mu_k * G * (1 + 1 / k) * t

    t_lock = root(w, 0.05, 1.0)
    assert k * F0 * math.exp(-t_lock / tau) / (1 + k) < mu_s * m * G
    ((t, kind),) = contacts(sol).transitions(0)
    assert kind == "slip→stick"
    # not polynomial: the event's error is the solve's, ~RTOL on the time scale 1 s
    assert abs(t - t_lock) <= 1e-8
    assert bool(slipping(sol)[0, 0]) and not bool(slipping(sol)[-1, 0])


# --- the variator ---------------------------------------------------------------------------------


def rho(t, p):
    """Contact radius on shaft 2, m: a cosine ramp from rho0 to rho1 over [0, Tr], then constant."""
    s = jnp.clip(t / p["Tr"], 0.0, 1.0)
    return p["rho0"] + (p["rho1"] - p["rho0"]) * 0.5 * (1 - jnp.cos(jnp.pi * s))


def variator_T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def variator_rolling(q, qd, t, p):
    """Slip velocity of the roller, m/s (paper eq. 4 times ρ): r φ1' − ρ(t) φ2'."""
    return jnp.stack([p["r"] * qd[0] - rho(t, p) * qd[1]])


VARIATOR = nh.Mechanism(
    variator_T,
    constraints=variator_rolling,
    contacts=(nh.FrictionContact(0, _p("N"), _p("mu_s"), lambda q, qd, t, p: 0.8 * p["mu_s"], name="roller"),),
    names=("phi1", "phi2"),
)
VAR = {"J1": 0.02, "J2": 0.05, "r": 0.05, "rho0": 0.05, "rho1": 0.025, "Tr": 0.5, "N": 150.0, "mu_s": 0.3}
W0 = 100.0  # rad/s
VTS = jnp.linspace(0.0, 1.0, 21)


def _variator(p, method="lagrange", **kw):
    qd0 = jnp.array([W0, W0 * p["r"] / p["rho0"]])
    kw = {"rtol": RTOL, "atol": ATOL, "step_ts": [VAR["Tr"]], "record": ("energy",), **kw}
    return nh.simulate(VARIATOR, p, jnp.zeros(2), qd0, VTS, method=method, **kw)


def variator_onset(p) -> float:
    """The slip onset from the closed form.

    While rolling, U = U21 = r/ρ, and J1 φ1'' = r λ, J2 φ2'' = −ρ λ (λ the tangential force, N).
    Differentiating the constraint, r φ1'' − ρ' φ2' − ρ φ2'' = 0, gives
    λ (r²/J1 + ρ²/J2) = ρ' φ2' = ρ' U φ1', and with ρ'/ρ² = −U'/r:

        λ = −J1 J2 U U' φ1' / (r (J1 + J2 U²)),

    so |λ| = μs N where J1 J2 |U'| |φ1'| = μs N ρ (J1 + J2 U²). With no torques, eq. (9),
    (J1 + J2 U²) φ1'' + J2 U U' φ1' = 0, integrates to φ1' = w0 √(I(0)/I(t)), I = J1 + J2 U²:
    the onset is the first root of the difference, found here by bisection to a few eps.
    """
    pn = {key: float(v) for key, v in p.items()}

    def f(t):
        rh = float(rho(t, pn))
        drho = float(jax.grad(lambda s: rho(s, pn))(t))
        U, dU = pn["r"] / rh, -pn["r"] * drho / rh**2
        inertia = pn["J1"] + pn["J2"] * U**2
        w = W0 * math.sqrt((pn["J1"] + pn["J2"] * (pn["r"] / pn["rho0"]) ** 2) / inertia)
        return pn["J1"] * pn["J2"] * abs(dU) * w - pn["mu_s"] * pn["N"] * rh * inertia

    grid = np.linspace(1e-9, pn["Tr"], 2001)
    first = int(np.argmax([f(t) > 0 for t in grid]))
    return root(f, float(grid[first - 1]), float(grid[first]))


@pytest.mark.parametrize("method", METHODS)
def test_variator_slip_onset(method):
    sol = _variator(VAR, method)
    (t_on, k1), (t_lock, k2) = contacts(sol).transitions("roller")
    assert (k1, k2) == ("stick→slip", "slip→stick")
    assert abs(t_on - variator_onset(VAR)) <= 1e-8
    # the slip guard was 0 at the restart at t_on and did not fire there: the lock is much later
    assert t_lock - t_on > 0.1
    assert int(contacts(sol).transitions_used) == 2 and int(sol.stats["segments"]) == 3
    # at the onset the needed force reached the cone: peak utilisation 1, smallest margin 0
    assert abs(float(contacts(sol).peak_utilisation[0]) - 1) <= 1e-9
    assert abs(float(contacts(sol).min_margin[0])) <= 1e-9 * VAR["mu_s"] * VAR["N"]
    # the constraint is homogeneous in the velocities, so its force does no work: the energy lost
    # is exactly the energy dissipated by slip
    energy = np.asarray(sol.energy)
    lost = float(energy[0] - energy[-1])
    assert abs(float(contacts(sol).dissipated_energy[0]) / lost - 1) <= 1e-8


def test_lagrange_and_appell_agree_on_the_variator():
    a, b = _variator(VAR, "lagrange"), _variator(VAR, "appell")
    np.testing.assert_allclose(np.asarray(a.q), np.asarray(b.q), rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(contacts(a).transition_times), np.asarray(contacts(b).transition_times), rtol=1e-8
    )


@pytest.mark.slow
def test_vmap_over_mu_s_members_with_different_transitions():
    """One batch: never slips (μs = 0.5), slips and locks again (0.3), slips to the end (0.02)."""
    mus = jnp.array([0.5, 0.3, 0.02])
    sols = jax.vmap(lambda m: _variator({**VAR, "mu_s": m}, throw=False))(mus)
    assert np.all(np.asarray(sols.status == nh.STATUS.successful))
    counts = np.sum(np.asarray(contacts(sols).transition_kinds) != 0, axis=(1, 2))
    np.testing.assert_array_equal(counts, [0, 2, 1])
    for i, m in enumerate(np.asarray(mus)):
        one = _variator({**VAR, "mu_s": jnp.asarray(m)})
        np.testing.assert_allclose(np.asarray(sols.q[i]), np.asarray(one.q), rtol=1e-10, atol=1e-10)
        np.testing.assert_array_equal(np.asarray(slipping(sols)[i]), np.asarray(slipping(one)))
    assert abs(float(contacts(sols).transition_times[1, 0, 0]) - variator_onset({**VAR, "mu_s": 0.3})) <= 1e-8
    assert abs(float(contacts(sols).transition_times[2, 0, 0]) - variator_onset({**VAR, "mu_s": 0.02})) <= 1e-8


@pytest.mark.extended
def test_variator_gradients_agree_with_central_differences():
    """Derivatives of the slip time, the energy dissipated and φ1(T) with respect to the pressing
    force N, through two transitions; N is far from grazing (the slip lasts 0.36 s)."""

    def outputs(N):
        sol = _variator({**VAR, "N": N}, "appell")
        return jnp.stack([contacts(sol).slip_time[0], contacts(sol).dissipated_energy[0], sol.q[-1, 0]])

    N = jnp.asarray(VAR["N"])
    J = jax.jit(jax.jacrev(outputs))(N)
    h = 1e-3 * VAR["N"]
    fd = (outputs(N + h) - outputs(N - h)) / (2 * h)
    # central differences: truncation ~ h² f'''/6 and the solves' own error RTOL/h; both ≤ 1e-6 here
    np.testing.assert_allclose(np.asarray(J), np.asarray(fd), rtol=1e-5)


def test_float32():
    """In float32 (rtol = 1e-5, above the 10 eps that simulate allows), the onset is found to the
    solve's accuracy: within 10 rtol × the time scale of 1 s."""
    p32 = {key: jnp.asarray(v, jnp.float32) for key, v in VAR.items()}
    qd0 = jnp.array([W0, W0 * VAR["r"] / VAR["rho0"]], jnp.float32)
    ts = jnp.linspace(0.0, 1.0, 21, dtype=jnp.float32)
    sol = nh.simulate(VARIATOR, p32, jnp.zeros(2, jnp.float32), qd0, ts, method="lagrange", rtol=1e-5, atol=1e-6)
    assert sol.q.dtype == jnp.float32 and sol.message == "success"
    (t_on, k1), (_, k2) = contacts(sol).transitions(0)
    assert (k1, k2) == ("stick→slip", "slip→stick")
    assert abs(t_on - variator_onset(VAR)) <= 10 * 1e-5


def test_under_jit():
    f = jax.jit(lambda m: contacts(_variator({**VAR, "mu_s": m})).slip_time[0])
    eager = float(contacts(_variator(VAR)).slip_time[0])
    assert abs(float(f(jnp.asarray(VAR["mu_s"]))) - eager) <= 1e-12
    # every input closed over: nothing traced goes in, but the outputs are traced
    closed = jax.jit(lambda: contacts(_variator(VAR)).slip_time[0])
    assert abs(float(closed()) - eager) <= 1e-12


def two_T(q, qd, t, p):
    """Two cylinders side by side on level ground, q = (x1, θ1, x2, θ2)."""
    return cylinder_T(q[:2], qd[:2], t, p) + cylinder_T(q[2:], qd[2:], t, p)


def two_slip(q, qd, t, p):
    return jnp.concatenate([cylinder_slip(q[:2], qd[:2], t, p), cylinder_slip(q[2:], qd[2:], t, p)])


TWO = nh.Mechanism(
    two_T,
    constraints=two_slip,
    contacts=(
        nh.FrictionContact(0, lambda q, qd, t, p: p["m"] * G, 0.5, _p("mu_k1"), name="first"),
        nh.FrictionContact(1, lambda q, qd, t, p: p["m"] * G, 0.5, _p("mu_k2"), name="second"),
    ),
)


def test_two_contacts_lock_at_their_own_times():
    """Each contact's transitions are located and recorded on its own (the event is the first
    zero of the smallest guard; the contact that fired is the one whose guard is 0)."""
    p = {**CYL, "mu_k1": 0.3, "mu_k2": 0.1}
    qd0 = jnp.array([3.0, 0.0, -2.0, 0.0])
    sol = nh.simulate(TWO, p, jnp.zeros(4), qd0, TS, method="lagrange", rtol=RTOL, atol=ATOL)
    for j, (v0, mu_k) in enumerate(((3.0, 0.3), (-2.0, 0.1))):
        t_star, v_star, x_T, lost = level_ground_closed_form(abs(v0), mu_k, CYL["k"], CYL["m"], 1.0)
        ((t, kind),) = contacts(sol).transitions(j)
        assert kind == "slip→stick" and abs(t / t_star - 1) <= 1e-9
        assert abs(abs(float(sol.q[-1, 2 * j])) / x_T - 1) <= 1e-9
        assert abs(float(contacts(sol).dissipated_energy[j]) / lost - 1) <= 1e-9
    assert int(contacts(sol).transitions_used) == 2


def test_design_smallest_pressing_force():
    """While rolling, the force the roller needs does not depend on N: the smallest N that keeps
    the drive rolling is N × the largest utilisation of the rolling motion (`stick_margin`),
    and the friction solve slips 1 % below it and rolls 1 % above it."""
    qd0 = jnp.array([W0, W0 * VAR["r"] / VAR["rho0"]])
    fine = jnp.linspace(0.0, 1.0, 401)  # the margin is sampled at the report times
    margin = nh.stick_margin(VARIATOR, VAR, jnp.zeros(2), qd0, fine, rtol=RTOL, atol=ATOL, step_ts=[VAR["Tr"]])
    assert float(margin.minimum[0]) < 0 and float(margin.soft_minimum[0]) <= float(margin.minimum[0])
    N_min = VAR["N"] * float(jnp.max(margin.utilisation))
    assert len(contacts(_variator({**VAR, "N": 0.99 * N_min})).transitions(0)) == 2
    assert contacts(_variator({**VAR, "N": 1.01 * N_min})).transitions(0) == []
    # the smooth objective has a derivative: d(minimum)/dN = (1 − minimum)/N (utilisation ∝ 1/N)
    dm = jax.grad(
        lambda N: nh.stick_margin(
            VARIATOR, {**VAR, "N": N}, jnp.zeros(2), qd0, fine, rtol=RTOL, atol=ATOL, step_ts=[VAR["Tr"]]
        ).minimum[0]
    )(jnp.asarray(VAR["N"]))
    assert abs(float(dm) / ((1 - float(margin.minimum[0])) / VAR["N"]) - 1) <= 1e-9


# --- caps, status, validation, and no cost without contacts ---------------------------------------


def test_transition_cap_stops_with_a_status_naming_time_and_contact():
    sol = _variator(VAR, max_transitions=1, throw=False)
    assert bool(sol.status == nh.STATUS.friction_transitions_exceeded)
    t_lock = contacts(_variator(VAR)).transitions(0)[1][0]
    assert abs(float(contacts(sol).stopped_at) - t_lock) <= 1e-9
    assert int(contacts(sol).stopped_contact) == 0
    assert "max_transitions" in sol.message and "roller" in sol.message and f"{t_lock:.6f}"[:6] in sol.message
    after = np.asarray(VTS) > t_lock
    assert np.all(np.isnan(np.asarray(sol.q)[after])) and np.all(np.isfinite(np.asarray(sol.q)[~after]))
    with pytest.raises(nh.SimulationError, match="roller"):
        _variator(VAR, max_transitions=1)


def test_friction_values_are_checked():
    bad = {**CYL, "mu_s": 0.1, "mu_k": 0.3}  # μs < μk
    sol = _cyl(bad, jnp.array([1.0, 0.0]), "lagrange", throw=False)
    assert bool(sol.status == nh.STATUS.friction_values_invalid)
    with pytest.raises(ValueError, match="mu_static"):
        nh.FrictionContact(0, 1.0, mu_static=0.1, mu_kinetic=0.3)
    with pytest.raises(ValueError, match="one or two"):
        nh.FrictionContact((0, 1, 2), 1.0, 0.5, 0.3)
    with pytest.raises(ValueError, match="row 0"):
        nh.Mechanism(cylinder_T, constraints=cylinder_slip, contacts=[nh.FrictionContact(0, 1, 1, 1)] * 2)
    mech = nh.Mechanism(cylinder_T, constraints=cylinder_slip, contacts=nh.FrictionContact(1, 1.0, 0.5, 0.3))
    with pytest.raises(ValueError, match="returns 1 rows"):
        nh.simulate(mech, CYL, jnp.zeros(2), jnp.zeros(2), TS)
    with pytest.raises(TypeError, match="params"):
        jax.jit(lambda mu: nh.FrictionContact(0, 1.0, mu, 0.1))(0.5)
    # a change of mode is an event located on the solver's interpolant: Kvaerno5's is a third-order
    # Hermite between long implicit steps, refused (before anything is compiled) with the fix named
    with pytest.raises(ValueError, match=r"solver=Kvaerno5\(\).*Kvaerno3"):
        _cylinder(0.3, "lagrange", solver=diffrax.Kvaerno5())


def test_no_contacts_no_friction_fields():
    mech = nh.Mechanism(cylinder_T, constraints=cylinder_slip)
    assert mech.contacts == ()
    sol = nh.simulate(mech, CYL, jnp.zeros(2), jnp.array([1.0, 10.0]), TS)
    assert sol.slipping is None and sol.contacts is None


def test_shipped_friction_variator_force_is_the_papers_multiplier_over_rho():
    """`jaxnh.models.variator.friction_mechanism` while rolling: its multiplier is the tangential
    force F (N), and ρ F is the paper's contact multiplier λ = M2 − J2 (U21' φ1' + U21 φ1''), N·m
    (eq. 8, with φ1'' from eq. 9), ρ = r / U21. The solve's tolerance is RTOL, so F agrees to a few
    RTOL relative to its scale."""
    from jaxnh.models import variator as V

    p = V.default_params()
    drive = V.DriveParams(p, 0.05, 1e4, 0.3, 0.25)  # pressed hard: it never slips
    ts = jnp.linspace(0.0, 2.0, 21)
    qd0 = jnp.array([2.0, p.U21(0.0) * 2.0])
    sol = nh.simulate(V.friction_mechanism(), drive, jnp.zeros(2), qd0, ts, rtol=RTOL, atol=ATOL,
                      record=("multipliers",))  # fmt: skip
    assert contacts(sol).transitions(0) == [] and not bool(jnp.any(slipping(sol)))
    phi1d = sol.qd[:, 0]
    lam = jax.vmap(lambda w, t: V.paper_multiplier(w, V.paper_eq9(w, t, p), t, p))(phi1d, ts)
    rho = 0.05 / jax.vmap(p.U21)(ts)
    F = np.asarray(sol.multipliers)[:, 0]
    scale = float(np.max(np.abs(F)))
    np.testing.assert_allclose(F, np.asarray(lam / rho), atol=100 * RTOL * scale)


# --- values along the motion, and transitions inside a step --------------------------------------

# A cylinder thrown without spin (the level-ground closed form above) whose normal force is
# N = m g (1 − a t) and whose μk turns NaN after t_nan: one mechanism, two failures by parameters.
VARYING = nh.Mechanism(
    cylinder_T,
    constraints=cylinder_slip,
    potential=cylinder_V,
    forces=cylinder_push,
    contacts=nh.FrictionContact(
        0,
        normal_force=lambda q, qd, t, p: p["m"] * G * (1 - p["a"] * t),
        mu_static=_p("mu_s"),
        mu_kinetic=lambda q, qd, t, p: jnp.where(t > p["t_nan"], jnp.nan, p["mu_k"]),
        name="ground",
    ),
)


def _varying(a, t_nan):
    p = {**CYL, "a": a, "t_nan": t_nan}
    return nh.simulate(VARYING, p, jnp.zeros(2), jnp.array([3.0, 0.0]), TS, rtol=RTOL, atol=ATOL,
                       max_transitions=4, record=("energy",), throw=False)  # fmt: skip


def test_a_normal_force_that_falls_to_zero_stops_the_solve_there():
    """N = m g (1 − 4t) reaches 0 at t = 0.25 s while the cylinder still slides (t* = 0.34 s at
    μk = 0.3): friction would push it after that. The solve stops at the zero, located by the
    event's root finder to 1e3 eps of the time (so 1e-12 s holds), with the status, the contact, the
    cause and the time in the message; the reports before it are right (the kinetic energy falls),
    those after are NaN."""
    sol = _varying(4.0, 10.0)
    c = contacts(sol)
    assert bool(sol.status == nh.STATUS.contact_normal_force_lost), sol.message
    assert abs(float(c.stopped_at) - 0.25) <= 1e-12
    assert int(c.stopped_contact) == 0 and nh.ContactDiagnostics.STOP_CAUSES[int(c.stop_cause)] == (
        "normal force reached zero"
    )
    assert "normal force reached zero" in sol.message and "'ground'" in sol.message and "t = 0.25" in sol.message
    e = np.asarray(sol.energy)
    before = np.asarray(TS) < 0.25
    assert np.all(np.isfinite(e[before])) and np.all(np.diff(e[before]) < 0) and np.all(np.isnan(e[~before]))
    with pytest.raises(nh.SimulationError, match="normal force reached zero"):
        nh.simulate(VARYING, {**CYL, "a": 4.0, "t_nan": 10.0}, jnp.zeros(2), jnp.array([3.0, 0.0]), TS,
                    rtol=RTOL, atol=ATOL, max_transitions=4, record=("energy",))  # fmt: skip


def test_a_contact_value_that_becomes_nan_stops_the_solve_naming_it():
    """μk = NaN from t = 0.05 s: the solve stops there (located to the root finder's 1e3 eps), naming
    the contact and μk, instead of shrinking its steps to max_steps and blaming stiffness."""
    sol = _varying(0.0, 0.05)
    c = contacts(sol)
    assert bool(sol.status == nh.STATUS.contact_value_invalid), sol.message
    assert abs(float(c.stopped_at) - 0.05) <= 1e-12
    assert nh.ContactDiagnostics.STOP_CAUSES[int(c.stop_cause)] == "μk not finite or negative"
    assert "μk" in sol.message and "stiff" not in sol.message
    # the same mechanism with good values is the closed form: nothing of the checks changes a motion
    good = _varying(0.0, 10.0)
    t_star, _, x_T, _ = level_ground_closed_form(3.0, CYL["mu_k"], CYL["k"], CYL["m"], 1.0)
    assert abs(float(contacts(good).transition_times[0, 0]) - t_star) <= 1e-9
    assert abs(float(good.q[-1, 0]) - x_T) <= 1e-9


def _belt(k, cap, method):
    """A block (1 kg) on a spring (k, N/m, anchored) on a belt moving at vb = 0.1 m/s, pressed by
    N = 10 N, μs = 0.5, μk = 0.3; x in m, the slip w = x' − vb. One coordinate and one row held by
    friction: while it sticks it has no independent velocity (Appell's form: none but the slip)."""
    m, vb, N = 1.0, 0.1, 10.0
    mech = nh.Mechanism(
        lambda q, qd, t, p: 0.5 * m * qd[0] ** 2,
        constraints=lambda q, qd, t, p: jnp.stack([qd[0] - vb]),
        potential=lambda q, t, p: 0.5 * p["k"] * q[0] ** 2,
        contacts=nh.FrictionContact(0, N, 0.5, 0.3, name="belt"),
    )
    ts = jnp.linspace(0.0, 1.0, 201)
    return nh.simulate(mech, {"k": jnp.asarray(k)}, jnp.zeros(1), jnp.array([vb]), ts, rtol=RTOL, atol=ATOL,
                       max_transitions=cap, throw=False, method=method)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_stick_slip_on_a_stiff_belt_finds_every_transition(method):
    """Stick–slip closed form. Stuck, x grows at vb until k x = μs N; then it slips, oscillating about
    x_e = μk N / k at ω = √(k/m) from (x − x_e, x') = (X, vb), X = (μs − μk) N / k, and the slip
    w = x' − vb returns to zero (it locks) at (−X, vb), after (2π − 2 atan(ω X / vb)) / ω; stuck
    again at x = x_e − X, the belt carries it back to x_e + X in 2 X / vb. Near the lock the slip
    rises to zero over a window far shorter than a step (k = 1e6: 40 µs in a cycle of 6.3 ms),
    which a step must not carry it across: every lock is found, at the closed-form times (each
    located to the root finder's tolerance and the solve's rtol, 1e-8 s over 160 cycles)."""
    k, m, vb, N = 1e6, 1.0, 0.1, 10.0
    omega, X = math.sqrt(k / m), 0.2 * N / k
    slip, stick = (2 * math.pi - 2 * math.atan(omega * X / vb)) / omega, 2 * X / vb
    onset0 = 0.5 * N / k / vb
    expected = [onset0]
    while expected[-1] + slip < 1.0:
        expected.append(expected[-1] + slip)  # lock
        if expected[-1] + stick < 1.0:
            expected.append(expected[-1] + stick)  # onset
    sol = _belt(k, 400, method)
    assert bool(sol.status == nh.STATUS.successful), sol.message
    times = [t for t, _ in contacts(sol).transitions(0)]
    assert len(times) == len(expected) == 319
    np.testing.assert_allclose(times, expected, rtol=0, atol=1e-8)
    x = np.asarray(sol.q[:, 0])
    amplitude = math.hypot(X, vb / omega)
    assert np.all(x <= 0.3 * N / k + amplitude * (1 + 1e-6)) and np.all(x >= 0.3 * N / k - amplitude * (1 + 1e-6))
    # with the default cap the transitions come too fast: the cap's status, never success
    capped = _belt(k, 32, method)  # (simulate's default max_transitions)
    assert bool(capped.status == nh.STATUS.friction_transitions_exceeded), capped.message


@pytest.mark.extended
@pytest.mark.parametrize("method", METHODS)
def test_vmap_of_grad_agrees_with_a_loop_of_grad(method):
    """`jax.vmap(jax.grad(f))` through the restarts equals `jax.grad` member by member (rounding of
    the same operations in a batch: 1e-12), and the closed form dx(T)/dμk = −g t*²/2 to the
    derivative tolerance of this module (1e-7).

    Under vmap every segment runs for every member, and in the segments in which no member has an
    event (after the lock, or at rest with no transition at all) the reverse pass must not run
    diffrax's event root find on stand-in residuals: it used to, and lineax raised on the
    non-finite cotangent of the event time. The batch holds two identical members."""

    def x_end(mu_k, v0):
        return _cylinder(mu_k, method, v0=v0).q[-1, 0]

    mus = jnp.array([0.3, 0.3, 0.2])
    looped = np.array([float(jax.grad(x_end)(m, 3.0)) for m in mus])
    batched = np.asarray(jax.vmap(jax.grad(x_end), in_axes=(0, None))(mus, 3.0))
    np.testing.assert_allclose(batched, looped, rtol=0, atol=1e-12)
    for m, d in zip(np.asarray(mus), looped):
        t_star = level_ground_closed_form(3.0, float(m), CYL["k"], CYL["m"], 1.0)[0]
        assert abs(d - (-0.5 * G * t_star**2)) < 1e-7
    still = jax.vmap(jax.grad(x_end), in_axes=(0, None))(mus, 0.0)  # at rest: no event anywhere
    assert np.all(np.asarray(still) == 0.0)
