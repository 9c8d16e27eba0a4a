"""The consistency check of qd0 judges each constraint on its own velocity scale, and the
checks neither underflow nor overflow at extreme (but representable) scales.

Three shafts, the first two coupled by 1.2 phi1' − phi2' = 0, the third free: a large phi3'
must not hide a violation of the coupling, and velocities whose squares underflow
(< 1e-154) are judged like any others. Each case eagerly, under jit and under vmap.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh


def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2 + p["J3"] * qd[2] ** 2)


def coupling(q, qd, t, p):
    return jnp.stack([1.2 * qd[0] - qd[1]])


MECH = nh.Mechanism(T, constraints=coupling)
P = {"J1": 0.02, "J2": 0.05, "J3": 1.0}
TS = jnp.linspace(0.0, 1.0, 3)
# (qd0, consistent): a violation of 0.4 % of the coupled speeds, a consistent state
CASES = [
    ([1.0, 1.205, 1e7], False),  # the large free speed used to hide the violation
    ([1.0, 1.2, 1e7], True),
    ([1e-160, 1.205e-160, 0.0], False),  # squares underflow: the check used to refuse or pass blindly
    ([1e-160, 1.2e-160, 0.0], True),
    ([1e-291, 1.2e-291, 0.0], True),
    ([1e-291, 1.205e-291, 0.0], False),
]
QD0S = jnp.array([c[0] for c in CASES])


def status(qd0, method):
    return nh.simulate(MECH, P, jnp.zeros(3), qd0, TS, method, throw=False).status._value


@pytest.fixture(scope="module", params=["appell", "lagrange"])
def outcomes(request):
    m = request.param
    eager = [nh.simulate(MECH, P, jnp.zeros(3), x, TS, m, throw=False) for x in QD0S]
    jitted = jax.jit(lambda x: status(x, m))
    return m, eager, [int(jitted(x)) for x in QD0S], np.asarray(jax.vmap(lambda x: status(x, m))(QD0S))


def test_each_constraint_is_judged_on_its_own_velocities(outcomes):
    m, eager, jitted, batched = outcomes
    bad = int(nh.STATUS.inconsistent_velocities._value)
    for (qd0, consistent), sol, j, v in zip(CASES, eager, jitted, batched):
        want = 0 if consistent else bad
        assert int(sol.status._value) == j == int(v) == want, (m, qd0, sol.message)
        if consistent:  # free motion: the velocities stay as they started (no torques)
            np.testing.assert_allclose(np.asarray(sol.qd[-1]), np.asarray(qd0), rtol=1e-12, atol=0)


@pytest.mark.parametrize("scale", [1e300, 1e-300])
def test_mass_matrix_check_at_extreme_inertias(scale):
    """Inertias near 1e±300 are a valid (if odd) choice of units: the Jacobi scaling of the
    positive-definiteness test must not over- or underflow (it used to, refusing them)."""
    p = {k: v * scale for k, v in P.items()}
    sol = nh.simulate(MECH, p, jnp.zeros(3), jnp.array([1.0, 1.2, 0.0]), TS, throw=False)
    assert sol.message == "success"
    np.testing.assert_allclose(np.asarray(sol.q[-1]), [1.0, 1.2, 0.0], rtol=1e-12)


# --- nearly dependent rows, and the distance to the constraint manifold ------------------------
#
# Three shafts, two constraints: phi1' − phi2' = 0 and (1 + d) phi1' − phi2' + e phi3' = 0.
# d = 0, e = 0: the second row repeats the first (redundant: 'lagrange' accepts it).
# e = 1e-9: rows apart by 1e-9 of their length, neither repeated to rounding nor independent
# enough to enforce (which motions are locked is decided by rounding): refused.
# e = 1e-3: independent, but ill-conditioned (σ_min/σ_max ≈ 7e-4): a qd0 whose second residual
# is 1e-9 of its scale (within √eps per row) needs a correction of ≈ 1e-6 of the speeds along
# phi3' to meet both: refused as inconsistent, while the exactly consistent state runs.


def two_rows(q, qd, t, p):
    return jnp.stack([qd[0] - qd[1], (1.0 + p["d"]) * qd[0] - qd[1] + p["e"] * qd[2]])


MECH2 = nh.Mechanism(T, constraints=two_rows)
ROW_CASES = [
    # (d, e, qd0, expected status name)
    (0.0, 0.0, [1.0, 1.0, 0.3], "successful"),
    (0.0, 1e-9, [1.0, 1.0, 0.0], "constraints_nearly_dependent"),
    (0.0, 1e-3, [1.0, 1.0, 0.0], "successful"),
    (0.0, 1e-3, [1.0, 1.0, 1e-6], "inconsistent_velocities"),
]


def row_status(d, e, qd0):
    p = dict(P, d=d, e=e)
    return nh.simulate(MECH2, p, jnp.zeros(3), qd0, TS, "lagrange", throw=False).status._value


@pytest.mark.slow
def test_nearly_dependent_rows_refused_and_distance_judged():
    args = [(jnp.asarray(d), jnp.asarray(e), jnp.asarray(qd0, dtype=float)) for d, e, qd0, _ in ROW_CASES]
    want = [int(nh.STATUS._name_to_item[name]._value) for *_, name in ROW_CASES]
    eager = [int(row_status(*a)) for a in args]
    jitted = jax.jit(row_status)
    batched = jax.vmap(row_status)(*(jnp.stack(x) for x in zip(*args)))
    assert eager == [int(jitted(*a)) for a in args] == list(np.asarray(batched)) == want
    # the per-row residual of the refused state is within the per-row tolerance: only the
    # distance test catches it (c2 = 1e-9, scale ≈ 1.4, √eps × scale ≈ 2e-8)
    c = two_rows(None, jnp.asarray(ROW_CASES[3][2]), 0.0, dict(d=0.0, e=1e-3))
    assert abs(float(c[1])) < 2e-8
    # the eager check of a concrete call raises naming the constraints
    with pytest.raises(ValueError, match="nearly dependent"):
        nh.simulate(MECH2, dict(P, d=0.0, e=1e-9), jnp.zeros(3), jnp.array([1.0, 1.0, 0.0]), TS, "lagrange")


def test_nearly_dependent_band_follows_the_dtype():
    """Rows 1 % apart (σ ratio ≈ 0.007) are independent in float64 but nearly dependent in float32,
    where 'lagrange' would drop one (its multiplier pivot ≈ 2e-4 < 1e4 eps); rows repeated exactly
    are dependent in both; rows 1e-9 apart are nearly dependent in float64, repeated in float32."""
    from jaxnh._model.checks import nearly_dependent

    def rows(d, dtype):
        return jnp.asarray([[1.0, -1.0, 0.0], [1.0 + d, -1.0, 0.0]], dtype=dtype)

    assert not bool(nearly_dependent(rows(0.01, jnp.float64)))
    assert bool(nearly_dependent(rows(0.01, jnp.float32)))
    assert not bool(nearly_dependent(rows(0.0, jnp.float64))) and not bool(nearly_dependent(rows(0.0, jnp.float32)))
    assert bool(nearly_dependent(rows(1e-9, jnp.float64)))
    assert not bool(nearly_dependent(rows(1e-9, jnp.float32)))


# --- a user's acceleration energy S is checked against T ------------------------------------------------


def _polar_T(q, qd, t, p):
    """A unit point mass in polar coordinates (r, θ): T = ½ (r'² + r² θ'²), J."""
    return 0.5 * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)


def _polar_S(q, qd, a, t, p):
    """Its acceleration energy ½ |acceleration|²: radial r'' − r θ'², transverse r θ'' + 2 r' θ'."""
    return 0.5 * ((a[0] - q[0] * qd[1] ** 2) ** 2 + (q[0] * a[1] + 2 * qd[0] * qd[1]) ** 2)


def _polar_S_no_centripetal(q, qd, a, t, p):
    return 0.5 * (a[0] ** 2 + (q[0] * a[1] + 2 * qd[0] * qd[1]) ** 2)


def _polar_S_mass_twice(q, qd, a, t, p):
    return 2.0 * _polar_S(q, qd, a, t, p)


def _polar_S_wrong_sign(q, qd, a, t, p):
    return -_polar_S(q, qd, a, t, p)


@pytest.mark.parametrize(
    "S, agrees",
    [(_polar_S, True), (_polar_S_no_centripetal, False), (_polar_S_mass_twice, False), (_polar_S_wrong_sign, False)],
)
def test_acceleration_energy_is_checked_against_the_kinetic_energy(S, agrees):
    """Appell's theorem ∂S/∂qdd = M qdd + h is an identity of exact derivatives, so a right S passes
    (to rounding) and a wrong one is refused, even from rest, where the forgotten centripetal term
    vanishes (the check also looks at a second velocity): eagerly with InvalidInitialState naming
    `acceleration_energy`, under jit with its status."""
    mech = nh.Mechanism(_polar_T, acceleration_energy=S)
    q0, qd0, ts = jnp.array([1.0, 0.0]), jnp.zeros(2), jnp.linspace(0.0, 1.0, 5)
    if agrees:
        assert nh.simulate(mech, {}, q0, qd0, ts, method="appell").message == "success"
        return
    with pytest.raises(nh.InvalidInitialState, match="acceleration_energy"):
        nh.simulate(mech, {}, q0, qd0, ts, method="appell")
    sol = jax.jit(lambda q: nh.simulate(mech, {}, q, qd0, ts, method="appell", throw=False))(q0)
    assert bool(sol.status == nh.STATUS.acceleration_energy_mismatch)
    assert bool(jnp.all(jnp.isnan(sol.q)))


def test_singular_rows_flags_a_fold_and_no_consistent_linear_row():
    """`singular_rows`: a row of ∂c/∂qd that vanishes to within √eps of the constraint's scale.
    c = nl y² + R y + d at its double root y = −R/(2 nl) (d = R²/(4 nl)) has A = 2 nl y + R = 0
    to rounding: its velocity part (eps·R·|y|) is eps-level against |d|, far below √eps."""
    from jaxnh._model.checks import singular_rows

    nl, R = 0.7, 1.3
    y = jnp.asarray([-R / (2 * nl)])
    A = jnp.asarray([[2 * nl * y[0] + R]])  # 0, or a rounding-level remainder
    d = jnp.asarray([R * R / (4 * nl)])
    assert bool(singular_rows(A + 1e-16, y, d)) and bool(singular_rows(A, y, d))
    # away from the fold (y at the simple root of nl y² + R y = 0 shifted): a regular row
    assert not bool(singular_rows(jnp.asarray([[R]]), jnp.asarray([0.5]), jnp.asarray([-0.65])))
    # linear rows met by qd (A qd = −a) never qualify, however large a is against A
    A2 = jnp.asarray([[1e-9, 0.0], [1.0, -1.0]])
    qd = jnp.asarray([1e9, 1e9])
    assert not bool(singular_rows(A2, qd, -(A2 @ qd)))
    # at rest with a = 0: nothing to judge, not flagged
    assert not bool(singular_rows(A2, jnp.zeros(2), jnp.zeros(2)))


def test_a_driven_mechanism_started_at_rest_is_inconsistent_not_singular():
    """A drive c = qd[0] − v met by no qd0 at rest has a velocity part of 0 against |v|: the
    start is reported as inconsistent (the row is not met), not as a fold of the constraint."""
    mech = nh.Mechanism(
        lambda q, qd, t, p: 0.5 * jnp.sum(qd**2), constraints=lambda q, qd, t, p: jnp.stack([qd[0] - p["v"]])
    )
    sol = nh.simulate(mech, {"v": 2.0}, jnp.zeros(2), jnp.zeros(2), jnp.linspace(0.0, 1.0, 3), throw=False)
    assert sol.status == nh.STATUS.inconsistent_velocities


def test_shared_row_checks_agree_with_the_separate_checks():
    """`constraint_row_checks` evaluates ∂c/∂qd once, c once (batched over qd = 0 and the
    affinity probe's two points) and one SVD for `nearly_dependent` and `consistent`: each verdict
    must be the one the separate check gives. Cases: independent rows met by qd, a violated row,
    nearly dependent rows (1e-9 apart), more rows than coordinates (the fourth a sum of two), a
    constraint declared linear that is not, and a subset of held rows whose violation is ignored."""
    from jaxnh._model.checks import consistent, constraint_row_checks, constraints_affine, nearly_dependent

    def c_lin(q, qd, t, p):
        return p["A"] @ qd + p["a"]

    def c_quad(q, qd, t, p):
        return p["A"] @ qd + p["a"] + jnp.stack([qd[0] ** 2] + [0.0 * qd[0]] * (p["A"].shape[0] - 1))

    T = lambda q, qd, t, p: 0.5 * jnp.sum(qd**2)  # noqa: E731
    qd = jnp.array([1.0, 2.0, -0.5])
    A3 = jnp.array([[1.0, 0.0, 2.0], [0.0, 1.0, -1.0]])
    near = jnp.array([[1.0, -1.0, 0.0], [1.0 + 1e-9, -1.0, 0.0]])
    four = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0]])
    cases = [
        (c_lin, A3, -(A3 @ qd), None),  # met
        (c_lin, A3, -(A3 @ qd) + jnp.array([0.0, 1e-3]), None),  # row 1 violated
        (c_lin, near, -(near @ qd), None),  # nearly dependent
        (c_lin, four, -(four @ qd), None),  # m > s, dependent to rounding
        (c_quad, A3, -(A3 @ qd) - jnp.array([1.0, 0.0]), None),  # declared linear, is not
        (c_lin, A3, -(A3 @ qd) + jnp.array([0.0, 1e-3]), (0,)),  # the violated row is not held
    ]
    for c, A, a, held in cases:
        mech = nh.Mechanism(T, constraints=c)
        p = {"A": A, "a": a}
        q = jnp.zeros(3)
        rows = constraint_row_checks(mech, q, qd, 0.0, p, held)
        got = [bool(g) for g, _ in (*rows.leading, *rows.trailing)]
        c0 = c(q, qd, 0.0, p)
        a0 = c(q, jnp.zeros(3), 0.0, p)
        Ah = rows.A if held is None else rows.A[jnp.asarray(held)]
        want_consistent = consistent(
            Ah, c0 if held is None else c0[jnp.asarray(held)], qd, a0 if held is None else a0[jnp.asarray(held)]
        )
        assert np.allclose(rows.A, jax.jacfwd(lambda v: c(q, v, 0.0, p))(qd), rtol=0, atol=1e-15)
        assert got[2] == bool(constraints_affine(mech, q, qd, 0.0, p))
        assert got[3] == (not bool(nearly_dependent(rows.A)))
        assert got[4] == bool(want_consistent)
    # the verdicts themselves: met, violated, nearly dependent, m > s, nonlinear, unheld violation
    verdicts = []
    for c, A, a, held in cases:
        rows = constraint_row_checks(nh.Mechanism(T, constraints=c), jnp.zeros(3), qd, 0.0, {"A": A, "a": a}, held)
        verdicts.append(next((s for g, s in (*rows.leading, *rows.trailing) if not bool(g)), None))
    S = nh.STATUS
    want = [None, S.inconsistent_velocities, S.constraints_nearly_dependent, None, S.constraints_nonlinear, None]
    assert [v is None for v in verdicts] == [w is None for w in want]
    assert all(bool(v == w) for v, w in zip(verdicts, want) if w is not None)


def test_split_regularity_is_judged_by_the_smallest_singular_value_not_the_volume():
    """`split_regular`, the one test of Appell's split in simulate's and the friction solve's
    initial checks. A car pulling 32 trailers (benchmarks/mechanisms/chain.py: 33 knife edges) has
    a best dependent block of volume 1.2e-18, below 1e3 eps, while every singular value of it is
    above 0.08: the friction solve judged by the volume and refused it as `singular_split`. A knife
    edge (ẏ cos θ − ẋ sin θ = 0 at θ = 0) with x among the dependent velocities has a singular
    block (its column of A is 0) whatever the scale: refused when fixed, avoided when automatic."""
    from benchmarks.mechanisms import chain as CH
    from jaxnh._equations.split import best_partition, split_regular

    N = 32
    p = CH.params(N)
    q, qd = CH.initial_state(N, p)
    assert float(best_partition(CH.mechanism(N), q, qd, 0.0, p, N + 3, N + 1)[1]) < 1e3 * np.finfo(np.float64).eps
    assert bool(split_regular(CH.mechanism(N), q, qd, 0.0, p, N + 3, N + 1))

    def knife(q, qd, t, p):
        return jnp.stack([qd[1] * jnp.cos(q[2]) - qd[0] * jnp.sin(q[2])])

    def T_knife(q, qd, t, p):
        return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * p["I"] * qd[2] ** 2

    for scale in (1e-6, 1.0, 1e6):  # (units: the mass scaling makes the verdicts scale-free)
        mech, pk = nh.Mechanism(T_knife, constraints=knife), {"m": scale, "I": 1e-3 * scale}
        q0, qd0 = jnp.zeros(3), jnp.array([1.0, 0.0, 0.5])
        assert bool(split_regular(mech, q0, qd0, 0.0, pk, 3, 1))
        assert bool(split_regular(mech, q0, qd0, 0.0, pk, 3, 1, independent=(0, 2)))
        assert not bool(split_regular(mech, q0, qd0, 0.0, pk, 3, 1, independent=(1, 2)))


# --- a mass matrix singular to rounding, written in speeds -------------------------------------
#
# Two shafts coupled by K² = J1 J2 (T is then a perfect square in q̇1, q̇2: ∂²T/∂q̇² singular), and a
# third shaft, written in speeds u = S(q) q̇ with S(q) invertible and state-dependent (diagonal
# 1 + a_i sin² q_i, skew coupling e). ∂²T/∂u² = S⁻ᵀ M S⁻¹ is then singular too; computed through
# S⁻¹ its smallest eigenvalue is rounding noise (~1e-16 of its largest, of either sign). The check
# used to pass such a matrix when its Jacobi-scaled Cholesky pivots were 1, 1e-4, 8.5e-13 (> 1e3
# eps: the last pivot is rounding noise amplified by the second), and the solve stalled at
# max_steps. The threshold, the smallest eigenvalue of the Jacobi-scaled matrix > 1e3 eps, lies far
# above rounding noise (~eps) and far below δ = 1e-6, the nearly singular but valid case.


def _S(q, p):
    s0, s1, s2 = jnp.sin(q[0]), jnp.sin(q[1]), jnp.sin(q[2])
    e = p["e"]
    return jnp.array(
        [
            [1.0 + p["a1"] * s0**2, e * s2, 0.0 * s0],
            [-e * s2, 1.0 + p["a2"] * s1**2, e * s0],
            [0.0 * s0, -e * s0, 1.0 + p["a3"] * s2**2],
        ]
    )


def _T_speeds(q, u, t, p):
    qd = jnp.linalg.solve(_S(q, p), u)
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2 + p["J3"] * qd[2] ** 2) + p["K"] * qd[0] * qd[1]


MECH_SPEEDS = nh.Mechanism(_T_speeds, kinematics=lambda q, u, t, p: jnp.linalg.solve(_S(q, p), u))


def _speeds_draws(delta, n=64, seed=0):
    rng = np.random.default_rng(seed)
    J = 10.0 ** rng.uniform(-3, 1, size=(n, 3))
    sign = rng.choice([-1.0, 1.0], size=n)
    p = dict(
        J1=J[:, 0],
        J2=J[:, 1],
        J3=J[:, 2],
        K=sign * np.sqrt(J[:, 0] * J[:, 1] * (1 - delta)),
        a1=rng.uniform(0, 1, n),
        a2=rng.uniform(0, 1, n),
        a3=rng.uniform(0, 1, n),
        e=rng.choice([-1.0, 1.0], size=n) * rng.uniform(0.1, 0.5, n),
    )
    q = rng.uniform(-np.pi, np.pi, size=(n, 3))
    u = rng.normal(size=(n, 3))
    return {k: jnp.asarray(v) for k, v in p.items()}, jnp.asarray(q), jnp.asarray(u)


@pytest.mark.parametrize("delta,positive", [(0.0, False), (1e-6, True)])
def test_mass_matrix_singular_to_rounding_in_speeds_is_refused(delta, positive):
    """64 random draws: K² = J1 J2 exactly is refused in every one, δ = 1e-6 passes in every one;
    through simulate, the first draw stops at once with the status that names the mass matrix."""
    from jaxnh._model.checks import mass_matrix_check

    p, q, u = _speeds_draws(delta)
    ok, _ = jax.jit(jax.vmap(lambda q, u, p: mass_matrix_check(MECH_SPEEDS, q, u, 0.0, p)))(q, u, p)
    assert np.all(np.asarray(ok) == positive)
    if not positive:
        p0 = {k: v[0] for k, v in p.items()}
        sol = nh.simulate(MECH_SPEEDS, p0, q[0], u[0], TS, throw=False)
        assert bool(sol.status == nh.STATUS.mass_matrix_not_positive_definite), sol.message
