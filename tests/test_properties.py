"""Property-based tests: random mechanisms, for which the formulations must agree and
the mechanics must hold.

A random mechanism of a fixed shape (s coordinates, m nonholonomic constraints) is
a set of coefficient ARRAYS drawn by hypothesis and passed as `params` (traced), so
each shape compiles once and every example reuses the compiled code. It has

* kinetic energy `T = ½ qdᵀ M(q) qd + qd·g(q, t) + T0(q, t)`: a configuration-
  dependent mass matrix `M(q) = R(q)ᵀ R(q) + diag(d)`, d ≥ 0.2 (positive definite
  by construction), a rheonomic gyroscopic term and a rheonomic T0;
* a time-dependent potential `V(q, t)`;
* non-potential forces `Q(q, qd, t)`: non-symmetric damping and position-dependent
  (circulatory) forces and a time-varying push;
* rheonomic linear constraints `c = A(q, t) qd + a0(q, t) = 0` whose dependent block
  (the last m columns) is strictly diagonally dominant for every q and t, so the
  split used by "appell" is valid along any motion.

The identity tested for the power balance (derived from Lagrange's equations
`d/dt ∂T/∂qd − ∂T/∂q = Q − ∂V/∂q + Aᵀλ`, contracted with qd): with the
generalized momentum `p = ∂T/∂qd` and the energy function (Jacobi integral)
`h = p·qd − T + V`,

    dh/dt = Q·qd + λᵀ A qd − ∂T/∂t + ∂V/∂t
          = Q·qd − λᵀ a0 − ∂T/∂t + ∂V/∂t        (A qd = −a0 on the constraints),

where the partial time derivatives are taken at fixed (q, qd). For a scleronomic T
(T quadratic in qd) h = T + V, and for homogeneous constraints (a0 = 0) the
constraint forces do no work: d(T + V)/dt = Q·qd + ∂V/∂t.
"""

from typing import Any

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, HealthCheck, settings, strategies as st

import jaxnh as nh


# Fixed, reproducible profile: derandomized (same examples every run, no database),
# no deadline (the first example of each shape includes compilation).
settings.register_profile(
    "jaxnh-properties",
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
PROFILE = settings.get_profile("jaxnh-properties")

SHAPES = [(2, 1), (4, 2)]  # (s, m): the variator's shape and a 2-constraint one
N_STATES = 8  # random states per example for the pointwise identities
N_REPORT = 101  # report times of the trajectory (even number of Simpson intervals)
HORIZON = 1.0  # s


def coefficient_shapes(s, m):
    """Shapes of the coefficient arrays of a random (s, m) mechanism."""
    return dict(
        R0=(s, s),
        R1=(s, s),
        ph=(s, s),
        d=(s,),
        g=(s,),
        gw=(),
        e0=(),
        A0=(m, s - m),
        E=(m, m),
        A1=(m, s),
        wa=(m, s),
        b=(m,),
        wb=(),
        C=(s, s),
        F=(s,),
        wf=(),
        K=(s, s),
        kv=(s,),
        kt=(),
    )


# --- the random mechanism (coefficients in [-1, 1] mapped to physical ranges) --------


def mass_matrix(q, c):
    R = c["R0"] + 0.5 * c["R1"] * jnp.sin(q[None, :] + 3.0 * c["ph"])
    return R.T @ R + jnp.diag(0.6 + 0.4 * c["d"])  # eigenvalues ≥ 0.2


def kinetic(q, qd, t, c):
    g = 0.5 * c["g"] * jnp.cos((1.0 + 0.5 * c["gw"]) * t + q)
    T0 = 0.3 * c["e0"] * (1.0 + 0.5 * jnp.sin(t)) * jnp.sum(jnp.cos(q))
    return 0.5 * qd @ mass_matrix(q, c) @ qd + qd @ g + T0


def constraint_matrix(q, t, c):
    m = c["E"].shape[0]
    base = jnp.concatenate([c["A0"], 2.0 * jnp.eye(m) + 0.35 * c["E"]], axis=1)
    # |0.35 E| + |0.3 A1| ≤ 0.65 < 2 − 0.65: the dependent block stays diagonally dominant (m ≤ 2)
    return base + 0.3 * c["A1"] * jnp.sin(q[None, :] + (1.0 + 0.5 * c["wa"]) * t)


def free_term(q, t, c):
    return 0.5 * c["b"] * jnp.sin((1.0 + 0.5 * c["wb"]) * t + q[0])


def constraints(q, qd, t, c):
    return constraint_matrix(q, t, c) @ qd + free_term(q, t, c)


def forces(q, qd, t, c):
    return -0.5 * c["C"] @ qd + 0.5 * c["F"] * jnp.sin((1.0 + 0.5 * c["wf"]) * t) - 0.5 * c["K"] @ q


def potential(q, t, c):
    return 0.5 * (1.0 + 0.3 * c["kt"] * jnp.sin(t)) * jnp.sum((1.0 + 0.5 * c["kv"]) * q**2)


MECH = nh.Mechanism(kinetic, constraints=constraints, forces=forces, potential=potential)


# --- the checks, compiled once per shape --------------------------------------------


def energy_function(q, qd, t, c):
    """h = p·qd − T + V (the Jacobi integral), J."""
    p = jax.grad(kinetic, argnums=1)(q, qd, t, c)
    return p @ qd - kinetic(q, qd, t, c) + potential(q, t, c)


def power(q, qd, t, lam, c):
    """Q·qd − λᵀ a0 − ∂T/∂t + ∂V/∂t, W, and a scale of its terms (for tolerances)."""
    terms = jnp.stack(
        [
            forces(q, qd, t, c) @ qd,
            -lam @ free_term(q, t, c),
            -jax.grad(kinetic, argnums=2)(q, qd, t, c),
            jax.grad(potential, argnums=1)(q, t, c),
        ]
    )
    return jnp.sum(terms), jnp.sum(jnp.abs(terms))


def pointwise(c, q, qd_guess, t, independent):
    """At random states: consistent velocities, both formulations, the power identity."""
    qd = nh.consistent_velocities(MECH, q, qd_guess, t, c)
    a_l, lam_l = nh.accelerations(MECH, q, qd, t, c, method="lagrange")
    a_a, lam_a = nh.accelerations(MECH, q, qd, t, c, method="appell", independent=independent)
    assert lam_l is not None and lam_a is not None  # both forms return multipliers
    # differentiated constraint A qdd + b, evaluated from the user's c by a jvp
    cdot = jax.jvp(lambda a, b, s: constraints(a, b, s, c), (q, qd, t), (qd, a_l, jnp.ones_like(t)))[1]
    dh = jax.jvp(lambda a, b, s: energy_function(a, b, s, c), (q, qd, t), (qd, a_l, jnp.ones_like(t)))[1]
    P, P_scale = power(q, qd, t, lam_l, c)
    scale_a = 1.0 + jnp.max(jnp.abs(a_l))
    scale_P = 1.0 + P_scale + jnp.abs(dh)
    return dict(
        residual=jnp.max(jnp.abs(constraints(q, qd, t, c))),
        accel_diff=jnp.max(jnp.abs(a_a - a_l)) / scale_a,
        lam_diff=jnp.max(jnp.abs(lam_a - lam_l)) / (1.0 + jnp.max(jnp.abs(lam_l))),
        cdot=jnp.max(jnp.abs(cdot)) / scale_a,
        power_gap=jnp.abs(dh - P) / scale_P,
        # the same balance without the constraint power −λᵀa0 (must fail: see below)
        gap_without_constraint_power=jnp.abs(dh - P - lam_l @ free_term(q, t, c)) / scale_P,
    )


def trajectories(c, q0, qd_guess, t0, independent):
    """Both formulations from one consistent state over HORIZON; integrated power balance."""
    qd0 = nh.consistent_velocities(MECH, q0, qd_guess, t0, c)
    ts = t0 + jnp.linspace(0.0, HORIZON, N_REPORT)
    kw: dict[str, Any] = dict(rtol=1e-10, atol=1e-12, max_steps=4096, throw=False)
    lag = nh.simulate(MECH, c, q0, qd0, ts, method="lagrange", record=("multipliers", "residual"), **kw)
    app = nh.simulate(MECH, c, q0, qd0, ts, method="appell", independent=independent, record=("residual",), **kw)
    h = jax.vmap(lambda a, b, s: energy_function(a, b, s, c))(lag.q, lag.qd, ts)
    P, P_scale = jax.vmap(lambda a, b, s, l: power(a, b, s, l, c))(lag.q, lag.qd, ts, lag.multipliers)
    dt = HORIZON / (N_REPORT - 1)
    work = dt / 3 * (P[0] + P[-1] + 4 * jnp.sum(P[1:-1:2]) + 2 * jnp.sum(P[2:-1:2]))  # Simpson
    scale_q = 1.0 + jnp.max(jnp.abs(lag.q)) + jnp.max(jnp.abs(lag.qd))
    assert app.residual is not None and lag.residual is not None
    return dict(
        success=lag.success & app.success,
        traj_diff=jnp.maximum(jnp.max(jnp.abs(app.q - lag.q)), jnp.max(jnp.abs(app.qd - lag.qd))) / scale_q,
        res_appell=jnp.max(jnp.abs(app.residual)) / scale_q,
        res_lagrange=jnp.max(jnp.abs(lag.residual)) / scale_q,
        balance_gap=jnp.abs(h[-1] - h[0] - work) / (1.0 + jnp.max(jnp.abs(h)) + dt * jnp.sum(P_scale)),
    )


@pytest.fixture(scope="module")
def checkers():
    """One compiled (pointwise, trajectories) pair per shape, built lazily."""
    cache = {}

    def get(s, m):
        if (s, m) not in cache:
            ind = tuple(range(s - m))
            cache[(s, m)] = (
                jax.jit(jax.vmap(lambda c, q, v, t: pointwise(c, q, v, t, ind), in_axes=(None, 0, 0, 0))),
                jax.jit(lambda c, q, v, t: trajectories(c, q, v, t, ind)),
            )
        return cache[(s, m)]

    return get


def unit_arrays(shape):
    return hnp.arrays(np.float64, shape, elements=st.floats(-1.0, 1.0, allow_nan=False, width=64))


@st.composite
def random_case(draw, s, m):
    coeffs = {k: draw(unit_arrays(v)) for k, v in coefficient_shapes(s, m).items()}
    q = 2.0 * draw(unit_arrays((N_STATES, s)))
    qd = 2.0 * draw(unit_arrays((N_STATES, s)))
    t = 1.5 + 1.5 * draw(unit_arrays((N_STATES,)))
    return coeffs, q, qd, t


def check_case(checkers, s, m, case):
    coeffs, q, qd, t = case
    pw, tr = checkers(s, m)
    c = {k: jnp.asarray(v) for k, v in coeffs.items()}
    p = {k: float(jnp.max(v)) for k, v in pw(c, jnp.asarray(q), jnp.asarray(qd), jnp.asarray(t)).items()}
    p.pop("gap_without_constraint_power")
    # Pointwise quantities are exact up to rounding in small, well-conditioned
    # solves (mass matrix eigenvalues ≥ 0.2, dominant constraint block): 1e-9 of
    # the scale leaves ~1e5 × eps of room.
    assert p["residual"] < 1e-10, p
    assert p["accel_diff"] < 1e-9, p
    assert p["lam_diff"] < 1e-9, p
    assert p["cdot"] < 1e-9, p
    assert p["power_gap"] < 1e-9, p
    r = {k: float(v) for k, v in tr(c, jnp.asarray(q[0]), jnp.asarray(qd[0]), jnp.asarray(t[0])).items()}
    assert r["success"], r
    # rtol 1e-10 over 1 s: global errors of a few 1e-10 relative; 1e-7 is loose
    # enough for the least smooth draws, far below any formulation error (O(1)).
    assert r["traj_diff"] < 1e-7, r
    # Appell keeps the constraints by construction (rounding only); Lagrange keeps
    # their derivative, so its residual is the integration drift (≈ tolerance).
    assert r["res_appell"] < 1e-12, r
    assert r["res_lagrange"] < 1e-7, r
    # Simpson's rule on 100 intervals of 0.01 s: error ≈ h⁴/180 max|P''''| ≲ 1e-8 of the
    # scale for these bounded coefficients; a missing power term would be O(1).
    assert r["balance_gap"] < 1e-6, r
    return p, r


@pytest.mark.slow
@pytest.mark.parametrize("s,m", SHAPES)
def test_random_mechanisms(checkers, s, m):
    """Lagrange = Appell, constraints hold, and the power balance holds, for random mechanisms."""

    @settings(PROFILE, max_examples=12)
    @given(random_case(s, m))
    def run(case):
        check_case(checkers, s, m, case)

    run()


def test_power_identity_detects_a_missing_term(checkers):
    """The check is sharp: without the constraint power −λᵀa0 the balance fails."""
    s, m = 2, 1
    rng = np.random.default_rng(0)
    c = {k: jnp.asarray(rng.uniform(-1, 1, v)) for k, v in coefficient_shapes(s, m).items()}
    q, qd, t = (jnp.asarray(rng.uniform(-1, 1, shape)) for shape in [(N_STATES, s), (N_STATES, s), (N_STATES,)])
    out = checkers(s, m)[0](c, q, qd, 1.5 + t)
    assert float(jnp.max(out["power_gap"])) < 1e-9
    assert float(jnp.min(out["gap_without_constraint_power"])) > 1e-3
