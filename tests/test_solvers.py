"""Tests of jaxnh.solvers.DOP853: tableau, convergence orders, error estimate, dense
output, agreement with diffrax.Dopri8, and jit / vmap / grad / jvp / float32 / jumps.

Compiled functions are shared through module-scoped fixtures: the whole file should
run in well under a minute.
"""

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxnh._solve.rk import DOP853  # noqa: E402


ORDER = 8  # global order of DOP853
DENSE_LOCAL_ORDER = 8  # 7th-order continuous extension: local error O(h^8)
ERROR_ORDER = 8  # Hairer's combined 8(5,3) estimate behaves as O(h^8)


def slope(hs, errs):
    """Least-squares slope of log(err) against log(h)."""
    return float(np.polyfit(np.log(np.asarray(hs)), np.log(np.asarray(errs)), 1)[0])


# --- problems with known solutions ------------------------------------------------


def lin_vf(t, y, args):
    """y' = -y + sin t, applied to each component."""
    return -y + jnp.sin(t)


def lin_exact(t, t0, y0):
    particular = lambda s: 0.5 * (jnp.sin(s) - jnp.cos(s))
    return particular(t) + (y0 - particular(t0)) * jnp.exp(-(t - t0))


def rot_vf(t, y, args):
    """Rotation with time-dependent frequency w(t) = 1 + t/2, state as a dict."""
    w = 1.0 + 0.5 * t
    return {"x": -w * y["v"], "v": w * y["x"]}


def rot_exact(t):
    phi = t + 0.25 * t**2
    return {"x": jnp.cos(phi), "v": jnp.sin(phi)}


def lv_vf(t, y, args):
    a, b, c, d = 1.5, 1.0, 3.0, 1.0
    return jnp.stack([a * y[0] - b * y[0] * y[1], -c * y[1] + d * y[0] * y[1]])


def pend_vf(t, y, args):
    return jnp.stack([y[1], -args * jnp.sin(y[0])])


LIN_Y0 = jnp.array([1.0, 0.3])
LV_Y0 = jnp.array([1.0, 1.0])


# --- tableau ----------------------------------------------------------------------


def test_tableau_matches_scipy_and_is_consistent():
    from scipy.integrate._ivp import dop853_coefficients as ref

    from jaxnh._solve import rk as S

    A = np.zeros((16, 16))
    for i, row in S._A.items():
        for j, a in row.items():
            A[i - 1, j - 1] = a
    for j, b in S._B.items():
        A[12, j - 1] = b
    np.testing.assert_allclose(np.asarray(S._C), ref.C, rtol=0, atol=1e-15)
    np.testing.assert_allclose(A, ref.A, rtol=1e-15, atol=0)
    er = np.zeros(13)
    for j, e in S._ER.items():
        er[j - 1] = e
    np.testing.assert_allclose(er, ref.E5, rtol=1e-15, atol=0)
    e3 = np.zeros(13)
    for j, e in S._E3.items():
        e3[j - 1] = e
    np.testing.assert_allclose(e3, ref.E3, rtol=1e-14, atol=1e-16)
    D = np.zeros((4, 16))
    for k, row in S._D.items():
        for j, d in row.items():
            D[k - 4, j - 1] = d
    np.testing.assert_allclose(D, ref.D, rtol=1e-15, atol=0)
    # Row sums equal the nodes; weights sum to one; error weights sum to zero.
    np.testing.assert_allclose(A.sum(axis=1), ref.C, atol=1e-13)
    assert abs(sum(S._B.values()) - 1) < 1e-13
    assert abs(sum(S._ER.values())) < 1e-13
    assert abs(sum(S._E3.values())) < 1e-13


def test_solver_interface():
    s = DOP853()
    assert isinstance(s, diffrax.AbstractAdaptiveSolver)
    assert s.order(None) == ORDER
    assert s.error_order(None) == ERROR_ORDER


# --- (a) order of convergence with constant steps --------------------------------


@pytest.fixture(scope="module")
def fixed_solve_lin():
    """Constant-step solve of the linear problem; returns the values saved at `ts`
    (through the dense output) and `sol.evaluate` of the SaveAt(dense=True) output."""
    term = diffrax.ODETerm(lin_vf)
    ts = jnp.linspace(0.0, 4.0, 17)

    @jax.jit
    def solve(dt):
        sol = diffrax.diffeqsolve(
            term,
            DOP853(),
            0.0,
            4.0,
            dt,
            LIN_Y0,
            saveat=diffrax.SaveAt(ts=ts, dense=True),  # ts[-1] == t1
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=64,
        )
        return sol.ys, jax.vmap(sol.evaluate)(ts)

    return solve, ts


@pytest.fixture(scope="module")
def fixed_solve_rot():
    term = diffrax.ODETerm(rot_vf)

    @jax.jit
    def solve(dt):
        sol = diffrax.diffeqsolve(
            term,
            DOP853(),
            0.0,
            3.0,
            dt,
            rot_exact(0.0),
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=64,
        )
        return jax.tree_util.tree_map(lambda a: a[-1], sol.ys)

    return solve


def test_convergence_order_linear(fixed_solve_lin):
    solve, ts = fixed_solve_lin
    ns = [4, 6, 8, 11, 16]
    hs = [4.0 / n for n in ns]
    errs = []
    for h in hs:
        y1 = solve(h)[0][-1]
        errs.append(float(jnp.max(jnp.abs(y1 - lin_exact(4.0, 0.0, LIN_Y0)))))
    assert errs[-1] < 1e-11 < errs[0]
    assert abs(slope(hs, errs) - ORDER) < 0.5, (errs, slope(hs, errs))


def test_convergence_order_pytree_rotation(fixed_solve_rot):
    ns = [8, 11, 16, 22, 32]
    hs = [3.0 / n for n in ns]
    errs = []
    for h in hs:
        y = fixed_solve_rot(h)
        ex = rot_exact(3.0)
        errs.append(max(float(jnp.abs(y[k] - ex[k])) for k in ("x", "v")))
    assert errs[-1] < 1e-10
    assert abs(slope(hs, errs) - ORDER) < 0.5, (errs, slope(hs, errs))


# --- single steps: local error, error estimate, interpolant ----------------------


@pytest.fixture(scope="module")
def single_steps():
    """One step of size h from (t0, y0) of the linear problem, for several h."""
    term = diffrax.ODETerm(lin_vf)
    s = DOP853()
    t0 = 0.3
    theta = 0.37

    @jax.jit
    @jax.vmap
    def one(h):
        t1 = t0 + h
        state = s.init(term, t0, t1, LIN_Y0, None)
        y1, err, dense, _, _ = s.step(term, t0, t1, LIN_Y0, None, state, False)
        interp = s.interpolation_cls(t0=t0, t1=t1, **dense)
        ends = (interp.evaluate(t0), interp.evaluate(t1))
        return y1, err, interp.evaluate(t0 + theta * h), ends

    hs = jnp.array([0.6, 0.45, 0.3, 0.2])
    y1, err, ymid, ends = one(hs)
    exact1 = jax.vmap(lambda h: lin_exact(t0 + h, t0, LIN_Y0))(hs)
    exactm = jax.vmap(lambda h: lin_exact(t0 + theta * h, t0, LIN_Y0))(hs)
    return dict(hs=np.asarray(hs), y1=y1, err=err, ymid=ymid, ends=ends, exact1=exact1, exactm=exactm)


def test_local_error_order(single_steps):
    d = single_steps
    local = jnp.max(jnp.abs(d["y1"] - d["exact1"]), axis=1)
    assert abs(slope(d["hs"], local) - (ORDER + 1)) < 0.5, local


def test_error_estimate_order_and_size(single_steps):
    d = single_steps
    est = jnp.max(jnp.abs(d["err"]), axis=1)
    local = jnp.max(jnp.abs(d["y1"] - d["exact1"]), axis=1)
    assert abs(slope(d["hs"], est) - ERROR_ORDER) < 0.5, est
    # The estimate is conservative: it bounds the true local error.
    assert bool(jnp.all(est > local))


def test_interpolant_local_order_and_endpoints(single_steps):
    d = single_steps
    derr = jnp.max(jnp.abs(d["ymid"] - d["exactm"]), axis=1)
    assert abs(slope(d["hs"], derr) - DENSE_LOCAL_ORDER) < 0.5, derr
    y_start, y_end = d["ends"]
    np.testing.assert_allclose(y_start, jnp.broadcast_to(LIN_Y0, y_start.shape), atol=1e-15)
    np.testing.assert_allclose(y_end, d["y1"], atol=1e-14)


# --- (d) dense output through diffeqsolve ----------------------------------------


def test_dense_output_order_at_saveat_ts(fixed_solve_lin):
    solve, ts = fixed_solve_lin
    # Step sizes chosen so that most report times fall strictly inside a step.
    ns = [3, 5, 7, 10, 14]
    hs = [4.0 / n for n in ns]
    errs = []
    for h in hs:
        ys, ys_dense = solve(h)
        # SaveAt(dense=True) + sol.evaluate uses the same interpolant as SaveAt(ts).
        np.testing.assert_allclose(ys_dense, ys, rtol=0, atol=1e-14)
        errs.append(float(jnp.max(jnp.abs(ys - lin_exact(ts[:, None], 0.0, LIN_Y0)))))
    # Global error at interior points: interpolation O(h^8) + propagated O(h^8).
    assert abs(slope(hs, errs) - DENSE_LOCAL_ORDER) < 0.5, (errs, slope(hs, errs))
    assert errs[-1] < 3e-10


# --- (b) agreement with diffrax.Dopri8 and (c) tolerance proportionality ---------


def test_agrees_with_dopri8_tight_tolerance():
    term = diffrax.ODETerm(lv_vf)
    ts = jnp.linspace(0.0, 10.0, 41)

    def run(solver):
        return diffrax.diffeqsolve(
            term,
            solver,
            0.0,
            10.0,
            None,
            LV_Y0,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
            max_steps=20000,
        ).ys

    ours = jax.jit(lambda: run(DOP853()))()
    theirs = jax.jit(lambda: run(diffrax.Dopri8()))()
    assert float(jnp.max(jnp.abs(ours - theirs))) < 1e-10


def saved(sol):
    """The saved states of a diffrax solution (None only for a SaveAt that saves nothing)."""
    assert sol.ys is not None
    return sol.ys


def test_adaptive_solve_meets_tolerance():
    term = diffrax.ODETerm(lin_vf)
    t1 = 10.0

    @jax.jit
    def run(tol):
        sol = diffrax.diffeqsolve(
            term,
            DOP853(),
            0.0,
            t1,
            None,
            LIN_Y0,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            max_steps=4096,
        )
        return saved(sol)[-1], sol.stats["num_steps"]

    exact = lin_exact(t1, 0.0, LIN_Y0)
    prev_steps = 0
    for tol in (1e-6, 1e-8, 1e-10, 1e-12):
        y, n = run(tol)
        err = float(jnp.max(jnp.abs(y - exact)))
        assert err < 10 * tol, (tol, err)
        assert int(n) > prev_steps
        prev_steps = int(n)
    assert prev_steps < 200  # an 8th-order method: few steps even at 1e-12


# --- (e) gradients: reverse mode vs finite differences, forward mode -------------


@pytest.fixture(scope="module")
def pendulum_loss():
    term = diffrax.ODETerm(pend_vf)
    ts = jnp.linspace(0.0, 3.0, 7)
    y0 = jnp.array([1.2, 0.0])

    def loss(p, adjoint=diffrax.RecursiveCheckpointAdjoint()):
        g, th0 = p[0], p[1]
        sol = diffrax.diffeqsolve(
            term,
            DOP853(),
            0.0,
            3.0,
            None,
            y0.at[0].set(th0),
            args=g,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-11),
            max_steps=2048,
            adjoint=adjoint,
        )
        ys = saved(sol)
        return jnp.sum(ys[:, 0] ** 2) + jnp.sum(jnp.sin(ys[:, 1]))

    return loss


@pytest.fixture(scope="module")
def pendulum_grad(pendulum_loss):
    p = jnp.array([9.81 / 4.0, 1.2])
    return p, jax.jit(jax.grad(pendulum_loss))(p)


def test_grad_matches_finite_differences(pendulum_loss, pendulum_grad):
    p, grad = pendulum_grad
    eps = 1e-5
    shifts = jnp.concatenate([eps * jnp.eye(2), -eps * jnp.eye(2)])
    vals = jax.jit(jax.vmap(pendulum_loss))(p + shifts)
    fd = (vals[:2] - vals[2:]) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-7)


def test_forward_mode_matches_reverse(pendulum_loss, pendulum_grad):
    p, grad = pendulum_grad
    fwd = jax.jit(jax.jacfwd(lambda q: pendulum_loss(q, diffrax.ForwardMode())))(p)
    np.testing.assert_allclose(fwd, grad, rtol=1e-10, atol=1e-12)


# --- (f) vmap, float32, jumps -----------------------------------------------------


def test_vmap_matches_individual_solves():
    term = diffrax.ODETerm(pend_vf)

    def solve(y0):
        return saved(
            diffrax.diffeqsolve(
                term,
                DOP853(),
                0.0,
                5.0,
                None,
                y0,
                args=1.0,
                stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
                throw=False,
            )
        )[-1]

    y0s = jnp.stack([jnp.array([a, 0.1 * a]) for a in (0.1, 0.5, 1.0, 2.0, 3.0)])
    batched = jax.jit(jax.vmap(solve))(y0s)
    single = jax.jit(solve)
    for i in range(len(y0s)):
        # Batch members step together until the slowest finishes; each keeps its own
        # step sizes, so results agree to rounding.
        np.testing.assert_allclose(batched[i], single(y0s[i]), rtol=0, atol=1e-12)


def test_float32():
    term = diffrax.ODETerm(lin_vf)
    y0 = LIN_Y0.astype(jnp.float32)
    sol = jax.jit(
        lambda y: diffrax.diffeqsolve(
            term,
            DOP853(),
            jnp.float32(0.0),
            jnp.float32(4.0),
            None,
            y,
            stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
            saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 4.0, 9, dtype=jnp.float32)),
        )
    )(y0)
    assert sol.ys.dtype == jnp.float32
    exact = lin_exact(jnp.linspace(0.0, 4.0, 9)[:, None], 0.0, LIN_Y0)
    assert float(jnp.max(jnp.abs(sol.ys - exact))) < 1e-5


def test_jump_invalidates_fsal_stage():
    """After a jump in the vector field the stored f(t1, y1) is stale: DOP853 must
    re-evaluate the first stage, otherwise the step after the jump is wrong."""
    term = diffrax.ODETerm(lambda t, y, args: jnp.where(t < 1.0, 1.0, -1.0) * jnp.ones_like(y))
    ctrl = diffrax.ClipStepSizeController(diffrax.PIDController(rtol=1e-8, atol=1e-8), jump_ts=jnp.array([1.0]))
    solve = jax.jit(
        jax.vmap(lambda y0: saved(diffrax.diffeqsolve(term, DOP853(), 0.0, 2.0, 0.3, y0, stepsize_controller=ctrl))[-1])
    )
    y0s = jnp.array([[0.0], [1.0]])
    np.testing.assert_allclose(solve(y0s), y0s, atol=1e-12)  # up 1, then down 1
