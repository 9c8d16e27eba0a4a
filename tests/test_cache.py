"""The persistent compilation cache (opt-in): where it is, that it is private, what is refused, and
that importing jaxnh changes no JAX setting but 64-bit mode.

Everything here is file-system checks and JAX config flags, no compilation,
except one fresh process that compiles `sin` to see an entry written.
"""

import json
import os
import stat
import subprocess
import sys
import warnings

import jax
import pytest
from jax.experimental.compilation_cache.compilation_cache import reset_cache

from jaxnh._base import cache as _cache
from jaxnh._base.cache import (
    cache_dir,
    check_cache_dir,
    enable_compilation_cache,
    MIN_COMPILE_TIME_SECS,
    UnsafeCacheDirWarning,
)


def flag(name):
    """The value of one of JAX's flags (attributes jax.config creates at run time, unknown to type checkers)."""
    return getattr(jax.config, name)


@pytest.fixture
def clean_jax_cache_config():
    """Run a test that may call enable_compilation_cache and put JAX's flags back afterwards."""
    before = (
        flag("jax_compilation_cache_dir"),
        flag("jax_persistent_cache_min_compile_time_secs"),
        _cache._active,
    )
    # start from JAX's defaults, whatever `import jaxnh` configured for this session
    jax.config.update("jax_compilation_cache_dir", None)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    _cache._active = None
    yield
    jax.config.update("jax_compilation_cache_dir", before[0])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])
    _cache._active = before[2]
    # JAX builds its cache object once, from the directory set at the first compilation after it
    # was enabled, and keeps it when the flag changes back: without a reset, every later test of
    # this worker would read and write the test's temporary cache (a worker crashed in XLA
    # reading an entry from it, in test_variator)
    reset_cache()


def mode(path):
    return stat.S_IMODE(os.lstat(path).st_mode)


def test_folder_from_environment(tmp_path):
    assert cache_dir({"JAXNH_CACHE_DIR": str(tmp_path / "c")}) == str(tmp_path / "c")
    assert cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == str(tmp_path / "jaxnh")
    assert cache_dir({}) == os.path.join(os.path.expanduser("~"), ".cache", "jaxnh")
    for off in ("off", "OFF", "0", "none", "", " false "):
        assert cache_dir({"JAXNH_CACHE_DIR": off, "XDG_CACHE_HOME": str(tmp_path)}) is None


def test_created_private_even_under_umask_000(tmp_path, clean_jax_cache_config):
    old = os.umask(0)
    try:
        path = enable_compilation_cache({"JAXNH_CACHE_DIR": str(tmp_path / "deep" / "c")})
    finally:
        os.umask(old)
    assert path == str(tmp_path / "deep" / "c")
    assert mode(path) == 0o700 and mode(tmp_path / "deep") == 0o700  # missing ancestors too (XDG: 0700)
    assert flag("jax_compilation_cache_dir") == path
    # small programs are cached too: the write threshold is lowered from JAX's 1 s
    assert flag("jax_persistent_cache_min_compile_time_secs") == MIN_COMPILE_TIME_SECS
    # a second call keeps the same folder (the CLI calls it again after `import jaxnh` did)
    assert enable_compilation_cache({"JAXNH_CACHE_DIR": str(tmp_path / "other")}) == path


def test_off_changes_nothing(tmp_path, clean_jax_cache_config):
    assert enable_compilation_cache({"JAXNH_CACHE_DIR": "off", "XDG_CACHE_HOME": str(tmp_path)}) is None
    assert flag("jax_compilation_cache_dir") is None
    assert not (tmp_path / "jaxnh").exists()


def test_a_user_configured_cache_is_respected(tmp_path, clean_jax_cache_config):
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 2.5)
    assert enable_compilation_cache({"JAXNH_CACHE_DIR": str(tmp_path / "c")}) is None
    assert flag("jax_compilation_cache_dir") == str(tmp_path / "mine")
    assert flag("jax_persistent_cache_min_compile_time_secs") == 2.5
    assert not (tmp_path / "c").exists()


def test_user_threshold_kept(tmp_path, clean_jax_cache_config):
    env = {"JAXNH_CACHE_DIR": str(tmp_path / "c"), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1.0"}
    assert enable_compilation_cache(env) == str(tmp_path / "c")
    assert flag("jax_persistent_cache_min_compile_time_secs") == 1.0


def refused(tmp_path, path, match):
    """enable_compilation_cache warns (naming the problem), returns None and leaves JAX's setting alone."""
    with pytest.warns(UnsafeCacheDirWarning, match=match):
        assert enable_compilation_cache({"JAXNH_CACHE_DIR": str(path)}) is None
    assert flag("jax_compilation_cache_dir") is None


@pytest.mark.parametrize(
    "perm,match", [(0o777, "writable by others"), (0o770, "writable by its group"), (0o702, "writable by others")]
)
def test_writable_by_others_is_refused(tmp_path, clean_jax_cache_config, perm, match):
    d = tmp_path / "c"
    d.mkdir()
    os.chmod(d, perm)
    refused(tmp_path, d, match)
    assert mode(d) == perm  # not "repaired" behind the user's back: they decide


def test_foreign_owner_is_refused(tmp_path, clean_jax_cache_config, monkeypatch):
    d = tmp_path / "c"
    d.mkdir(mode=0o700)
    os.chmod(d, 0o700)
    monkeypatch.setattr(_cache, "_uid", lambda: os.lstat(d).st_uid + 1)  # as if another user owned it
    refused(tmp_path, d, "owned by another user")


def test_symlink_is_refused(tmp_path, clean_jax_cache_config):
    real = tmp_path / "real"
    real.mkdir(mode=0o700)
    os.chmod(real, 0o700)
    link = tmp_path / "c"
    link.symlink_to(real)
    refused(tmp_path, link, "symbolic link")


@pytest.mark.parametrize("sticky", [False, True])
def test_parent_writable_by_others(tmp_path, clean_jax_cache_config, sticky):
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o777 | (stat.S_ISVTX if sticky else 0))
    if sticky:  # like /tmp: others cannot rename our folder away
        assert enable_compilation_cache({"JAXNH_CACHE_DIR": str(shared / "c")}) == str(shared / "c")
        assert mode(shared / "c") == 0o700
    else:
        refused(tmp_path, shared / "c", "which others can write")
        assert not (shared / "c").exists()


def test_a_file_is_refused_and_an_uncreatable_folder_warns(tmp_path, clean_jax_cache_config):
    f = tmp_path / "c"
    f.write_text("x")
    refused(tmp_path, f, "not a directory")
    if os.geteuid() != 0:  # root can write anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        os.chmod(ro, 0o500)
        refused(tmp_path, ro / "c", "cannot be created")


def test_existing_private_folder_is_used(tmp_path, clean_jax_cache_config):
    d = tmp_path / "c"
    d.mkdir()
    os.chmod(d, 0o755)  # readable by others is fine: only writing is a risk
    assert check_cache_dir(str(d)) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert enable_compilation_cache({"JAXNH_CACHE_DIR": str(d)}) == str(d)


def test_programs_are_written_and_an_unsafe_folder_is_not_read(tmp_path):
    # fresh processes, so the global JAX setting does not leak into the test session
    code = (
        "import warnings, jax, jax.numpy as jnp\n"
        "from jaxnh._base.cache import enable_compilation_cache\n"
        "p = enable_compilation_cache()\n"
        "jax.jit(lambda x: jnp.sin(x) * 2)(1.0).block_until_ready()\n"
        "print(p, jax.config.jax_compilation_cache_dir)\n"
    )
    env = dict(os.environ, JAXNH_CACHE_DIR=str(tmp_path / "c"), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str(tmp_path / "c")] * 2
    entries = os.listdir(tmp_path / "c")
    assert entries, "the compiled program was not written to the cache folder"
    # the same folder made world-writable: refused with a warning, nothing read or written
    os.chmod(tmp_path / "c", 0o777)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["None", "None"]
    assert "UnsafeCacheDirWarning" in out.stderr and "writable by others" in out.stderr
    assert sorted(os.listdir(tmp_path / "c")) == sorted(entries)


def test_importing_jaxnh_changes_no_jax_setting_but_x64():
    """A fresh process: every value of `jax.config` is read before and after `import jaxnh`."""
    code = (
        "import json, jax\n"
        "def settings():\n"
        "    return {k: repr(v) for k, v in jax.config.values.items()}\n"
        "before = settings()\n"
        "import jaxnh\n"
        "after = settings()\n"
        "print(json.dumps({k: [before.get(k), after.get(k)] for k in set(before) | set(after) "
        "if before.get(k) != after.get(k)}))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "JAXNH_"))}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    changed = json.loads(out.stdout.strip().splitlines()[-1])
    assert changed == {"jax_enable_x64": ["False", "True"]}, changed
