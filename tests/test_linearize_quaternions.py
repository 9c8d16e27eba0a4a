"""`linearize` of a mechanism in a unit quaternion (issue 44), against the heavy symmetric top.

A body with a fixed point O, mass m, centre of mass at distance l on its symmetry axis, moments A
about the transverse axes through O and C about the axis, its orientation a unit quaternion e and
its speeds the angular velocity ω (body axes: T = ½ (A (ω1² + ω2²) + C ω3²); or space axes:
T = ½ Ωᵀ R I Rᵀ Ω), V = m g l × (the axis's height / l) = m g l R₃₃. Upright and spinning at
ω3 = n ("sleeping"), small nutations z = δθx + i δθy about the vertical, in axes that do not turn
with the body, obey

    A s² − i C n s − m g l = 0,    s = i [C n ± √(C² n² − 4 A m g l)] / (2A),

stable (s imaginary) iff C² n² > 4 A m g l (Goldstein, Classical Mechanics, 3rd ed., §5.7;
Arnold, Mathematical Methods of Classical Mechanics, §30). With δθ in space axes (`frame="space"`,
space-axes speeds) those are the eigenvalues ±s of the transverse mode; with δθ in body axes
(`frame="body"`, body-axes speeds) the transverse axes turn with the body at n, and the eigenvalues
are s − i n and their conjugates. The rotation about the axis (δθz, δωz) is the double zero
eigenvalue (a Jordan block: the spin angle drifts with δωz), left out of the comparisons.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

import jaxnh as nh
from jaxnh.rigid import quaternion_from_axis_angle, quaternion_rate, rotation_from_quaternion


EPS = float(jnp.finfo(jnp.float64).eps)
P = {"A": 0.02, "C": 0.01, "m": 1.0, "g": 9.81, "l": 0.1}  # kg·m², kg·m², kg, m/s², m
PARAMS = {k: jnp.asarray(v) for k, v in P.items()}
E_UP = jnp.array([1.0, 0.0, 0.0, 0.0])  # the axis (body z) vertical
N_CRITICAL = 2 * np.sqrt(P["A"] * P["m"] * P["g"] * P["l"]) / P["C"]  # rad/s, 28.0 here


def _potential(q, t, p):
    return p["m"] * p["g"] * p["l"] * rotation_from_quaternion(q)[2, 2]


def _kinetic_body(q, u, t, p):
    return 0.5 * (p["A"] * (u[0] ** 2 + u[1] ** 2) + p["C"] * u[2] ** 2)


def _kinetic_space(q, u, t, p):
    R = rotation_from_quaternion(q)
    inertia = jnp.diag(jnp.stack([p["A"], p["A"], p["C"]]))
    return 0.5 * u @ (R @ inertia @ R.T) @ u


TOP = {
    "body": nh.Mechanism(
        _kinetic_body,
        potential=_potential,
        kinematics=lambda q, u, t, p: quaternion_rate(q, u, frame="body"),
        quaternions=((0, 1, 2, 3),),
        names=("e0", "e1", "e2", "e3"),
    ),
    "space": nh.Mechanism(
        _kinetic_space,
        potential=_potential,
        kinematics=lambda q, u, t, p: quaternion_rate(q, u, frame="space"),
        quaternions=((0, 1, 2, 3),),
        names=("e0", "e1", "e2", "e3"),
    ),
}


def _closed_form(n, frame, p=P):
    """The four transverse eigenvalues (complex) at spin n (rad/s)."""
    mgl = p["m"] * p["g"] * p["l"]
    root = np.sqrt(complex(p["C"] ** 2 * n**2 - 4 * p["A"] * mgl))
    s = 1j * (p["C"] * n + np.array([root, -root])) / (2 * p["A"])
    if frame == "body":
        s = s - 1j * n
    return np.concatenate([s, np.conj(s)])


def _transverse(A):
    """The four eigenvalues of A largest in modulus (the transverse mode)
    and a tolerance for each: 100 eps ‖A‖_F κ(λ), with κ(λ) = ‖x‖ ‖y‖ / |yᴴ x| the condition number
    of the simple eigenvalue λ (x, y its right and left eigenvectors). A backward-stable
    eigensolver returns the eigenvalues of A + E, ‖E‖ ≈ a small multiple of eps ‖A‖, which moves a
    simple λ by κ(λ) ‖E‖ to first order; A itself is computed by forward-mode derivatives of a few
    dozen operations on numbers of ‖A‖'s size, which adds errors of the same order. 100 covers both."""
    A = np.asarray(A)
    w, vl, vr = scipy.linalg.eig(A, left=True, right=True)  # pyright: ignore[reportAssignmentType]
    kappa = np.linalg.norm(vl, axis=0) * np.linalg.norm(vr, axis=0) / np.abs(np.sum(np.conj(vl) * vr, axis=0))
    keep = np.argsort(-np.abs(w))[:4]
    return w[keep], 100 * EPS * np.linalg.norm(A) * kappa[keep]


def _errors(w, expected):
    """|w − expected| with the computed eigenvalues w matched one-to-one to the expected ones (the
    assignment of least total distance): no ordering of complex numbers to agree on."""
    rows, cols = scipy.optimize.linear_sum_assignment(np.abs(w[:, None] - expected[None, :]))
    return np.abs(w[rows] - expected[cols])


@pytest.mark.parametrize(("frame", "method"), [("body", "lagrange"), ("space", "appell")])
def test_sleeping_top_eigenvalues_closed_form(frame, method):
    n = 40.0  # rad/s, above N_CRITICAL: stable
    lin = nh.linearize(TOP[frame], PARAMS, E_UP, jnp.array([0.0, 0.0, n]), method=method, frame=frame)
    assert lin.A.shape == (6, 6)  # three entries δθ for the quaternion's four coordinates
    assert lin.states == tuple(f"θ{a}(e0,e1,e2,e3)" for a in "xyz") + ("u0", "u1", "u2")
    # the operating orientation turns at n about the vertical; the chart follows it, the rest is steady
    np.testing.assert_allclose(lin.rates, [0.0, 0.0, n, 0.0, 0.0, 0.0], atol=16 * EPS * n)
    np.testing.assert_array_equal(lin.state, [0.0, 0.0, 0.0, 0.0, 0.0, n])  # δθ = 0 at the operating point
    w, tol = _transverse(lin.A)
    expected = _closed_form(n, frame)
    np.testing.assert_array_less(_errors(w, expected), tol)
    # the spin block: δθ̇z = δωz, δω̇z = 0 (rows 2 and 5), nothing else
    np.testing.assert_allclose(lin.A[2], [0, 0, 0, 0, 0, 1], atol=16 * EPS)
    np.testing.assert_allclose(lin.A[5], np.zeros(6), atol=16 * EPS * float(jnp.max(jnp.abs(lin.A))))


@pytest.mark.parametrize("frame", ["body", "space"])
def test_sleeping_top_threshold(frame):
    """Just above the critical spin the transverse eigenvalues are imaginary (to their tolerance);
    just below, a pair has the positive real part √(4 A m g l − C² n²) / (2A) of the closed form."""
    for factor, stable in ((1 + 1e-4, True), (1 - 1e-4, False)):
        n = factor * N_CRITICAL
        lin = nh.linearize(TOP[frame], PARAMS, E_UP, jnp.array([0.0, 0.0, n]), frame=frame)
        w, tol = _transverse(lin.A)
        expected = _closed_form(n, frame)
        np.testing.assert_array_less(_errors(w, expected), tol)
        growth = np.sqrt(max(0.0, 4 * P["A"] * P["m"] * P["g"] * P["l"] - P["C"] ** 2 * n**2)) / (2 * P["A"])
        if stable:
            np.testing.assert_array_less(np.abs(np.real(w)), tol)
        else:
            assert growth > 1e3 * np.max(tol)  # the closed form's growth rate is far above the noise
            np.testing.assert_allclose(np.max(np.real(w)), growth, rtol=0, atol=np.max(tol))


def _fast_nutation(mass, n=40.0):
    """The fast nutation frequency (rad/s) of the top in space axes, α₊ = [C n + √(C² n² − 4 A m g l)]/(2A)."""
    p = dict(PARAMS, m=mass)
    lin = nh.linearize(TOP["space"], p, E_UP, jnp.array([0.0, 0.0, n]), frame="space", speeds=(0, 1, 2))
    return jnp.max(jnp.abs(jnp.imag(lin.eigenvalues())))


def test_sleeping_top_under_jit_and_grad():
    m = 1.0
    concrete = _fast_nutation(m)
    jitted, grad = jax.jit(jax.value_and_grad(_fast_nutation))(m)  # one program: value and gradient
    expected = np.max(np.abs(np.imag(_closed_form(40.0, "space"))))
    np.testing.assert_allclose(concrete, expected, rtol=1e3 * EPS)
    np.testing.assert_allclose(jitted, concrete, rtol=1e3 * EPS)
    grad = float(grad)
    # central difference: truncation h² |f'''| / 6 ≈ 1e-10 · O(10) and rounding of f (|f| ≈ 17, each
    # value to ≈ 1e3 eps relative, as above) / h ≈ 4e-9, at h = 1e-6 kg: both below 1e-7 of |f'| ≈ 3.4
    h = 1e-6
    fd = (float(_fast_nutation(m + h)) - float(_fast_nutation(m - h))) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-7)
    # and the closed form's dα₊/dm = −g l / √(C² n² − 4 A m g l)
    closed = -P["g"] * P["l"] / np.sqrt(P["C"] ** 2 * 40.0**2 - 4 * P["A"] * m * P["g"] * P["l"])
    np.testing.assert_allclose(grad, closed, rtol=1e3 * EPS * 100)


def test_tilted_operating_orientation_and_completion():
    """The chart at any orientation: a top at rest hanging down (the axis at π from the vertical, a
    stable equilibrium) has the transverse frequencies √(m g l / A) (pendulum), in either frame, and
    `complete` (here renormalising the quaternion) leaves the linearisation unchanged."""
    e_down = quaternion_from_axis_angle(jnp.array([0.6, 0.8, 0.0]), jnp.pi)
    w = np.sqrt(P["m"] * P["g"] * P["l"] / P["A"])
    for frame in ("body", "space"):
        lin = nh.linearize(TOP[frame], PARAMS, e_down, jnp.zeros(3), frame=frame)
        got, tol = _transverse(lin.A)
        # the two zero eigenvalues (spin) and ±i w twice: the four largest are ±i w
        np.testing.assert_array_less(_errors(got, np.array([-1j * w, -1j * w, 1j * w, 1j * w])), tol)
        completed = nh.linearize(
            TOP[frame], PARAMS, e_down, jnp.zeros(3), frame=frame, complete=lambda q, t, p: q / jnp.linalg.norm(q)
        )
        np.testing.assert_allclose(completed.A, lin.A, rtol=0, atol=64 * EPS * float(jnp.max(jnp.abs(lin.A))))


def test_refusals_name_the_argument():
    w0 = jnp.array([0.0, 0.0, 40.0])
    with pytest.raises(ValueError, match="`coordinates` keeps part of the unit quaternion"):
        nh.linearize(TOP["body"], PARAMS, E_UP, w0, coordinates=(1, 2))
    with pytest.raises(ValueError, match="frame must be one of"):
        nh.linearize(TOP["body"], PARAMS, E_UP, w0, frame="inertial")
    with pytest.raises(ValueError, match="off unit norm"):
        nh.linearize(TOP["body"], PARAMS, 1.01 * E_UP, w0)
    # traced values cannot be refused on the host: every output NaN, never a finite wrong answer
    A = jax.jit(lambda q: nh.linearize(TOP["body"], PARAMS, q, w0, speeds=(0, 1, 2)).A)(1.01 * E_UP)
    assert bool(jnp.all(jnp.isnan(A)))
    # speed names, and an ignorable orientation left out
    lin = nh.linearize(TOP["body"], PARAMS, E_UP, w0, coordinates=(), speed_names=("wx", "wy", "wz"))
    assert lin.states == ("wx", "wy", "wz") and lin.A.shape == (3, 3)
