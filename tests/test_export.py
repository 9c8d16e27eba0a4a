"""Traced programs kept on disk (`jaxnh._export`): the same answer as the ordinary path, one file
per program structure, a damaged file rebuilt, and nothing kept for what the key cannot see
(functions from outside jaxnh, closures, traced calls, the cache turned off)."""

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh  # 64-bit mode
from jaxnh import _cache, _export
from jaxnh.linalg import mm, solve_spd


@pytest.fixture
def folder(tmp_path, monkeypatch):
    base = tmp_path / "cache"
    base.mkdir(mode=0o700)
    monkeypatch.setattr(_cache, "_active", str(base))
    monkeypatch.setattr(_export, "_MEMO", {})
    monkeypatch.setattr(_export, "_REFUSED", set())
    monkeypatch.setattr(_export, "_KEYS", {})
    monkeypatch.setattr(_export, "_FAST", {})
    return base / "exported"


def spd(n, seed=0):
    a = np.random.default_rng(seed).normal(size=(n, n))
    return jnp.asarray(a @ a.T + n * np.eye(n)), jnp.arange(1.0, n + 1.0)


def test_round_trip_and_one_file_per_structure(folder, monkeypatch):
    M, b = spd(4)
    out = _export.exported_call(solve_spd, (M, b), name="spd")
    np.testing.assert_allclose(np.asarray(out), np.asarray(solve_spd(M, b)), rtol=1e-14)
    files = sorted(os.listdir(folder))
    assert len(files) == 1 and files[0].startswith("spd-")
    assert oct(os.stat(folder).st_mode & 0o777) == "0o700"
    # a new process: loaded from the file (no new file), other values through the same program
    monkeypatch.setattr(_export, "_MEMO", {})
    M2, b2 = spd(4, seed=1)
    out2 = _export.exported_call(solve_spd, (M2, b2), name="spd")
    np.testing.assert_allclose(np.asarray(out2), np.asarray(solve_spd(M2, b2)), rtol=1e-14)
    assert sorted(os.listdir(folder)) == files
    # another shape is another program
    M3, b3 = spd(3)
    out3 = _export.exported_call(solve_spd, (M3, b3), name="spd")
    np.testing.assert_allclose(np.asarray(out3), np.asarray(solve_spd(M3, b3)), rtol=1e-14)
    assert len(os.listdir(folder)) == 2


def test_damaged_file_is_rebuilt(folder, monkeypatch):
    M, b = spd(4)
    _export.exported_call(solve_spd, (M, b), name="spd")
    (path,) = [folder / f for f in os.listdir(folder)]
    path.write_bytes(b"not a program")
    monkeypatch.setattr(_export, "_MEMO", {})
    out = _export.exported_call(solve_spd, (M, b), name="spd")
    np.testing.assert_allclose(np.asarray(out), np.asarray(solve_spd(M, b)), rtol=1e-14)
    assert path.read_bytes() != b"not a program"


def users_function(M, b):
    return jnp.linalg.solve(M, b)


def test_not_kept_when_the_key_cannot_see_the_program(folder, monkeypatch):
    M, b = spd(3)
    scale = 2.0

    def closure(M, b):
        return solve_spd(M, b) * scale

    assert _export.exported_call(users_function, (M, b), name="u") is None  # code outside jaxnh
    assert _export.exported_call(closure, (M, b), name="c") is None  # captured values
    assert _export.exported_call(solve_spd, (M, users_function), name="f") is None  # a foreign leaf
    seen = []
    jax.jit(lambda M, b: seen.append(_export.exported_call(solve_spd, (M, b), name="t")) or b)(M, b)
    assert seen == [None]  # traced: the caller's program
    assert not folder.exists() or os.listdir(folder) == []
    monkeypatch.setattr(_cache, "_active", None)  # JAXNH_CACHE_DIR=off
    monkeypatch.setenv("JAXNH_CACHE_DIR", "off")
    assert _export.exported_call(solve_spd, (M, b), name="spd") is None


def test_shipped_program_is_found_and_right(folder, tmp_path, monkeypatch):
    """A program built into the shipped folder is used by a later process whose own folder is
    empty (nothing is traced or written there), gives the same answer, and is not read when the
    cache is turned off."""
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    monkeypatch.setattr(_export, "SHIPPED", str(shipped))
    M, b = spd(4)
    monkeypatch.setattr(_export, "_BUILDING", True)
    _export.exported_call(solve_spd, (M, b), {}, name="spd")
    monkeypatch.setattr(_export, "_BUILDING", False)
    (built,) = os.listdir(shipped)
    assert not folder.exists() or os.listdir(folder) == []  # building writes only the shipped folder
    monkeypatch.setattr(_export, "_MEMO", {})
    traced = []
    monkeypatch.setattr(jax.export, "export", lambda *a, **k: traced.append(1) or pytest.fail("traced again"))
    M2, b2 = spd(4, seed=3)
    out = _export.exported_call(solve_spd, (M2, b2), {}, name="spd")
    np.testing.assert_allclose(np.asarray(out), np.asarray(solve_spd(M2, b2)), rtol=1e-14)
    assert traced == [] and (not folder.exists() or os.listdir(folder) == [])
    assert os.listdir(shipped) == [built]
    monkeypatch.setattr(_export, "_MEMO", {})
    monkeypatch.setattr(_cache, "_active", None)
    monkeypatch.setenv("JAXNH_CACHE_DIR", "off")
    assert _export.exported_call(solve_spd, (M2, b2), {}, name="spd") is None


def test_shipped_programs_match_the_sources():
    """The programs in jaxnh/programs/ were built from these sources (`make programs` after a
    change); with other versions of the JAX stack they are never used (the key differs), and
    must still be readable files."""
    info = _export.manifest()
    assert info, "jaxnh/programs/MANIFEST.json is missing: run `make programs`"
    on_disk = sorted(f for f in os.listdir(_export.SHIPPED) if f.endswith(".bin"))
    assert on_disk == info["files"] and len(on_disk) >= 2
    assert set(info["jobs"]) == set(_export.SHIPPED_JOBS)
    if info["versions"] == _export._versions() and info["backend"] == jax.default_backend():
        assert info["source_digest"] == _export._source_digest(), (
            "jaxnh's sources changed since the shipped programs were built: run `make programs`"
        )
    for f in on_disk:
        assert _export._load(os.path.join(_export.SHIPPED, f)) is not None, f


def test_one_shot_jit_under_transformations(folder):
    """A one-shot program (kept as an exported program when called eagerly) gives the same
    values and derivatives eagerly, under jit, vmap and grad."""
    M, b = spd(3)
    f = _export.one_shot_jit(solve_spd)
    x = f(M, b)
    assert os.listdir(folder)  # kept
    np.testing.assert_allclose(np.asarray(x), np.linalg.solve(np.asarray(M), np.asarray(b)), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(jax.jit(f)(M, b)), np.asarray(x), rtol=1e-14)
    bs = jnp.stack([b, 2 * b])
    np.testing.assert_allclose(np.asarray(jax.vmap(f, in_axes=(None, 0))(M, bs))[1], 2 * np.asarray(x), rtol=1e-13)
    g = jax.grad(lambda b: f(M, b).sum())(b)
    np.testing.assert_allclose(np.asarray(g), np.linalg.solve(np.asarray(M).T, np.ones(3)), rtol=1e-12)


# --- users' own mechanisms: kept under the jaxprs of their functions --------------------------

HALF = 0.5


def half():
    return HALF


def kinetic(q, qd, t, p):
    return half() * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def rolling(q, qd, t, p):
    return jnp.stack([(1.0 + 0.4 * jnp.sin(jnp.pi * t)) * qd[0] - qd[1]])


def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


P = {"J1": jnp.asarray(0.02), "J2": jnp.asarray(0.05), "M1": jnp.asarray(0.3), "M2": jnp.asarray(-0.1)}
TS = jnp.linspace(0.0, 2.0, 5)


def run(mech, exported=True, monkeypatch=None):
    from jaxnh import _simulate

    if not exported:
        assert monkeypatch is not None
        with monkeypatch.context() as m:
            m.setattr(_simulate, "_run_exported", lambda *a: None)
            return nh.simulate(mech, P, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, record=("energy",))
    return nh.simulate(mech, P, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, record=("energy",))


def new_process(monkeypatch):
    """What a new process starts without: jaxnh's loaded programs and keys, and JAX's caches of
    traces (within one process JAX, like jaxnh, reuses a trace of the same function)."""
    monkeypatch.setattr(_export, "_MEMO", {})
    monkeypatch.setattr(_export, "_KEYS", {})
    monkeypatch.setattr(_export, "_FAST", {})
    jax.clear_caches()


@pytest.mark.slow
def test_users_mechanism_kept_under_what_its_functions_compute(folder, monkeypatch):
    """A simulation of a user's mechanism is kept (no second trace in a later process, the same
    answer), and any change in what its functions compute is another program: a helper it calls,
    a global it reads, an array it captures. Functions holding Python code that JAX does not
    trace (a custom derivative rule) are not kept; their simulations run as before."""
    mech = nh.Mechanism(kinetic, constraints=rolling, forces=torques)
    first = run(mech)
    assert len(os.listdir(folder)) == 1
    new_process(monkeypatch)
    with monkeypatch.context() as m:
        m.setattr(jax.export, "export", lambda *a, **k: pytest.fail("traced again"))
        again = run(mech)
    np.testing.assert_array_equal(np.asarray(again.q), np.asarray(first.q))
    assert again.success and len(os.listdir(folder)) == 1
    reference = run(mech, exported=False, monkeypatch=monkeypatch)
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(reference)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    # the same functions, but a global their helper reads has changed: another program, another answer
    new_process(monkeypatch)
    monkeypatch.setattr(sys.modules[__name__], "HALF", 0.25)
    changed = run(mech)
    assert len(os.listdir(folder)) == 2
    ref = run(mech, exported=False, monkeypatch=monkeypatch)
    np.testing.assert_array_equal(np.asarray(changed.q), np.asarray(ref.q))
    assert not np.allclose(np.asarray(changed.q), np.asarray(first.q))  # half the inertia: faster
    monkeypatch.setattr(sys.modules[__name__], "HALF", 0.5)

    # an array captured by a closure: its values are part of the key
    for torque in (0.3, 0.6):
        M = jnp.asarray([torque, -0.1])
        new_process(monkeypatch)
        out = run(nh.Mechanism(kinetic, constraints=rolling, forces=lambda q, qd, t, p, M=M: M))
        ref = run(nh.Mechanism(kinetic, constraints=rolling, forces=lambda q, qd, t, p, M=M: M), False, monkeypatch)
        np.testing.assert_array_equal(np.asarray(out.q), np.asarray(ref.q))
    assert len(os.listdir(folder)) == 4

    @jax.custom_jvp
    def square(x):
        return x**2

    square.defjvp(lambda x, dx: (square(x[0]), 2 * x[0] * dx[0]))

    def kinetic_rule(q, qd, t, p):
        return 0.5 * (p["J1"] * square(qd[0]) + p["J2"] * square(qd[1]))

    new_process(monkeypatch)
    out = run(nh.Mechanism(kinetic_rule, constraints=rolling, forces=torques))
    assert len(os.listdir(folder)) == 4  # not kept
    np.testing.assert_allclose(np.asarray(out.q), np.asarray(first.q), rtol=1e-12)


def test_memoised_calls_take_numpy_scalars_as_inputs(folder):
    """With `memo` (a caller's own static key), a later call with another NumPy scalar is another
    input to the same program, not a stale baked-in constant."""
    b = jnp.arange(1.0, 4.0)
    for scale in (np.float64(1.0), np.float64(3.0)):
        out = _export.exported_call(mm, (scale, b), name="mm", memo="the same options")
        assert out is not None
        np.testing.assert_allclose(float(out), 6.0 * float(scale), rtol=1e-15)
    assert len(os.listdir(folder)) == 1


def test_exported_call_skips_linear_algebra_setup_only_when_unused():
    """The first call of an exported program that calls no LAPACK kernel skips JAX's LAPACK
    set-up (a SciPy import); one that calls LAPACK is recognised, and the hook is restored.
    (The test's name avoids the word LAPACK in lower case: source locations, function names
    included, are part of the serialized module, and the check errs on the side of set-up.)"""
    from jax._src.export import _export as internal

    from jaxnh._export import _calls_no_lapack, _lapack_left_alone

    S = jax.ShapeDtypeStruct((20, 20), jnp.float64)
    plain = jax.export.export(jax.jit(lambda a: jnp.sin(a) @ a))(S)
    factor = jax.export.export(jax.jit(jnp.linalg.cholesky))(S)
    assert _calls_no_lapack(plain)
    assert not _calls_no_lapack(factor)
    hook = internal._ensure_backends_initialized
    with _lapack_left_alone():
        assert internal._ensure_backends_initialized is not hook
    assert internal._ensure_backends_initialized is hook
    # a LAPACK program exported and called afterwards is right
    a = np.random.default_rng(1).normal(size=(20, 20))
    spd = a @ a.T + 20 * np.eye(20)
    L = np.asarray(jax.jit(factor.call)(jnp.asarray(spd)))
    np.testing.assert_allclose(L @ L.T, spd, rtol=0, atol=1e-12)
