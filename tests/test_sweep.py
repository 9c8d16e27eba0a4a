"""`nh.sweep`: chunked, sharded batches equal a loop of single simulations, in order.

Tolerances: a member of a vmapped adaptive solve takes exactly the steps a
single solve takes (the PID controller acts per member); only the order of
floating-point operations in fused kernels may differ, by a few ulps per step.
Over the ~100 steps of these runs that accumulates to ~1e-14 relative, so
`rtol=1e-12` (≈ 5000 ε) separates rounding from any real difference (a wrong
member or a wrong order changes results by O(1)).
"""

import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh._analysis.sweep import default_mesh, sweep
from jaxnh.models import variator as V
from jaxnh.profiles import Fourier


ROOT = pathlib.Path(__file__).resolve().parents[1]
MECH = V.mechanism()
TS = jnp.linspace(0.0, 2.0, 11)
RTOL = 1e-12


def make_params(J2, amp):
    return V.VariatorParams(J1=0.02, J2=J2, U21=Fourier(1.0, sin=[amp], period=2.0), M1=0.3, M2=-0.1)


def run(p, w0):
    """One member: final speeds, peak |λ| (N·m), status."""
    qd0 = jnp.stack([w0, p.U21(0.0) * w0])
    sol = nh.simulate(MECH, p, jnp.zeros(2), qd0, TS, record=("multipliers",), throw=False)
    assert sol.multipliers is not None
    return {"q": sol.q[-1], "qd": sol.qd[-1], "lam": jnp.max(jnp.abs(sol.multipliers)), "status": sol.status}


run_single = jax.jit(run)


def batch(n):
    J2 = np.linspace(0.03, 0.08, n)
    amp = np.linspace(0.0, 0.5, n)[::-1].copy()
    w0 = np.linspace(1.0, 3.0, n)
    return J2, amp, w0, jax.vmap(make_params)(J2, amp)


def loop(J2, amp, w0):
    outs = [run_single(make_params(J2[i], amp[i]), w0[i]) for i in range(len(J2))]
    return {k: np.stack([np.asarray(o[k]) for o in outs]) for k in ("q", "qd", "lam")}


@pytest.mark.parametrize("n", [5, 8])
def test_sweep_equals_loop_in_order(n):
    """Batch sizes that do (8) and do not (5) divide the chunk size of 4, over
    several chunks (one compiled chunk shape serves both)."""
    chunk = 4
    J2, amp, w0, ps = batch(n)
    out = sweep(run, ps, w0, chunk_size=chunk)
    ref = loop(J2, amp, w0)
    for k in ("q", "qd", "lam"):
        assert out[k].shape == ref[k].shape
        np.testing.assert_allclose(out[k], ref[k], rtol=RTOL, err_msg=k)
    assert np.all(out["status"] == nh.STATUS.successful)


def _generic(x, cfg, scale, offset):
    return {"y": x["a"] * scale + jnp.sum(x["b"]) + offset, "tag": cfg}


@pytest.mark.parametrize("n, chunk", [(1, 4), (3, 4), (11, 4), (12, 4), (12, 5), (7, 1), (7, None)])
def test_generic_function_pytrees_and_static_outputs(n, chunk):
    """Any function of a batch: dict inputs, shared static values and a shared
    array (in_axes=None), a non-array output; one member, fewer members than a
    chunk, (non-)dividing chunks."""
    a = np.arange(float(n))
    b = np.arange(3.0 * n).reshape(n, 3)
    offset = jnp.array([0.5, -1.0])
    out = sweep(_generic, {"a": a, "b": b}, "label", 2.0, offset, in_axes=(0, None, None, None), chunk_size=chunk)
    assert out["y"].shape == (n, 2)
    np.testing.assert_array_equal(out["y"], (a * 2.0 + b.sum(1))[:, None] + np.asarray(offset))
    assert out["tag"] == "label"


def test_failed_member_reports_its_own_status():
    """A member with a non-finite inertia fails alone; the others are unaffected."""
    J2, amp, w0, _ = batch(5)
    J2 = J2.copy()
    J2[2] = np.nan
    ps = jax.vmap(make_params)(J2, amp)
    out = sweep(run, ps, w0, chunk_size=4)
    ok = np.asarray(out["status"] == nh.STATUS.successful)
    np.testing.assert_array_equal(ok, [True, True, False, True, True])
    assert bool(np.asarray(out["status"] == nh.STATUS.non_finite_input)[2])
    good = [0, 1, 3, 4]
    ref = loop(J2[good], amp[good], w0[good])
    np.testing.assert_allclose(out["qd"][good], ref["qd"], rtol=RTOL)


def test_progress_callback_and_printed_lines(capsys):
    seen = []
    x = np.arange(10.0)
    sweep(lambda v: v * 2, x, chunk_size=3, progress=lambda d, t, e: seen.append((d, t, e)))
    assert [s[0] for s in seen] == [3, 6, 9, 10] and all(s[1] == 10 for s in seen)
    assert all(s[2] >= 0 for s in seen)
    sweep(lambda v: v * 2, x, chunk_size=5, progress=True)
    err = capsys.readouterr().err
    assert err.count("sweep: ") == 2 and "10/10 members (100%)" in err


@pytest.mark.parametrize(
    "kwargs, args, match",
    [
        ({}, (np.zeros(3), np.zeros(4)), r"args\[1\] has shape \(4,\)"),
        ({"chunk_size": 0}, (np.zeros(3),), "chunk_size must be a positive integer"),
        ({"in_axes": 1}, (np.zeros(3),), "must be 0 .batched. or None"),
        ({"in_axes": (0, 0)}, (np.zeros(3),), "in_axes has 2 entries but 1 arguments"),
        ({"in_axes": None}, (np.zeros(3),), "marks no array argument as batched"),
        ({}, (np.float64(1.0),), r"batched leaf args\[0\] is a scalar"),
        ({}, (np.zeros((0, 2)),), "the batch is empty"),
        ({"progress": "yes"}, (np.zeros(3),), "progress must be"),
    ],
)
def test_errors_name_the_argument(kwargs, args, match):
    with pytest.raises((ValueError, TypeError), match=match):
        sweep(lambda *a: a[0], *args, **kwargs)


TWO_DEVICE_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    import jax
    sys.path.insert(0, {tests!r})
    from test_sweep import batch, run
    import jaxnh
    from jaxnh._analysis.sweep import sweep
    assert jax.device_count() == 2, jax.devices()
    J2, amp, w0, ps = batch(7)
    out = sweep(run, ps, w0, chunk_size=4)
    np.savez({out!r}, q=out["q"], qd=out["qd"], lam=out["lam"],
             ok=np.asarray(out["status"] == jaxnh.STATUS.successful))
    """
)


def test_two_devices_equal_one_device(tmp_path):
    """7 members, chunks of 4 over 2 devices (2 per device, last chunk padded):
    the same numbers as the single-device sweep and the loop."""
    script = tmp_path / "two.py"
    result = tmp_path / "two.npz"
    script.write_text(TWO_DEVICE_SCRIPT.format(tests=str(ROOT / "tests"), out=str(result)))
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    two = np.load(result)
    J2, amp, w0, ps = batch(7)
    one = sweep(run, ps, w0, chunk_size=4)
    ref = loop(J2, amp, w0)
    assert two["ok"].all()
    # Two devices run batches of 2 where one device runs batches of 4: XLA vectorises them
    # differently, so they round differently. The step-size controller's error estimate is a
    # difference of nearly equal stage values, known only to about eps·|y| / (rtol·|y|) = 2e-8
    # relative at rtol 1e-8: the two runs may choose steps that differ at that level, and their
    # results then differ by up to the local error of those steps, a fraction of rtol. Bound:
    # the requested rtol, 1e-8; a wrong member or a wrong order differs by O(1).
    for k in ("q", "qd", "lam"):
        np.testing.assert_allclose(two[k], one[k], rtol=1e-8, err_msg=k)
        np.testing.assert_allclose(two[k], ref[k], rtol=1e-8, err_msg=k)


def test_default_mesh_uses_all_devices():
    mesh = default_mesh()
    assert mesh.size == jax.device_count() and mesh.axis_names == ("batch",)
    with pytest.raises(ValueError, match="devices is empty"):
        default_mesh([])


def test_in_axes_as_a_pytree_prefix():
    """in_axes={"x": 0, "k": None} batches one entry of a dict and shares the other."""
    data = {"x": np.arange(5.0), "k": np.array([1.0, 10.0])}
    out = sweep(lambda d: d["x"] * d["k"], data, in_axes=({"x": 0, "k": None},), chunk_size=2)
    np.testing.assert_array_equal(out, np.arange(5.0)[:, None] * np.array([1.0, 10.0]))
    with pytest.raises(ValueError, match="pytree prefix"):
        sweep(lambda d: d["x"], data, in_axes=({"y": 0},))


def test_callables_inside_batched_arguments_are_static():
    """A law (callable) travelling with batched data is passed through, not batched."""
    batch = {"x": np.linspace(0.0, 1.0, 6), "law": jnp.cos}
    out = sweep(lambda b: b["law"](b["x"]), batch, chunk_size=4)
    np.testing.assert_allclose(out, np.cos(np.linspace(0.0, 1.0, 6)), rtol=1e-15)


def test_explicit_mesh_argument():
    mesh = default_mesh(jax.devices()[:1])
    out = sweep(lambda v: v**2, np.arange(5.0), mesh=mesh, chunk_size=2)
    np.testing.assert_array_equal(out, np.arange(5.0) ** 2)
    with pytest.raises(TypeError, match="mesh must be a jax.sharding.Mesh"):
        sweep(lambda v: v, np.arange(3.0), mesh="cpu")  # pyright: ignore[reportArgumentType]  (wrong on purpose)


MULTI_PROCESS_SCRIPT = textwrap.dedent(
    """
    import sys
    pid, port, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=2, process_id=pid)
    import numpy as np
    import jax.numpy as jnp
    from jaxnh._analysis.sweep import sweep
    assert jax.process_count() == 2 and jax.device_count() == 4, (jax.process_count(), jax.devices())
    x = np.arange(11.0)
    res = sweep(lambda v, w: {"a": v * w, "b": jnp.sin(v)}, x, jnp.asarray(3.0), in_axes=(0, None), chunk_size=4)
    np.savez(out, a=res["a"], b=res["b"])
    jax.distributed.shutdown()
    """
)


def test_two_processes_two_devices_each(tmp_path):
    """Multi-controller run (jax.distributed on localhost, 2 processes × 2 CPU
    devices, gloo collectives): every process gets the whole result, in order."""
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    script = tmp_path / "mp.py"
    script.write_text(MULTI_PROCESS_SCRIPT)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(i), str(port), str(tmp_path / f"r{i}.npz")],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    for p in procs:
        try:
            _, err = p.communicate(timeout=240)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            raise
        assert p.returncode == 0, err[-3000:]
    x = np.arange(11.0)
    for i in range(2):
        r = np.load(tmp_path / f"r{i}.npz")
        np.testing.assert_array_equal(r["a"], 3.0 * x)
        np.testing.assert_allclose(r["b"], np.sin(x), rtol=1e-15)
