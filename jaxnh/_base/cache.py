"""JAX's persistent compilation cache, in a folder only the user can write, when asked for.

Compiling jaxnh's programs (a simulation, a fit's Jacobian) takes seconds;
JAX can keep the compiled programs on disk and load them in later processes.
Importing jaxnh leaves JAX's settings alone (apart from 64-bit mode). JAX's
cache is a setting of the whole process, so it is the program's decision:
`jaxnh.enable_compilation_cache()` turns it on (the `jaxnh` command line does
so), called before the first compilation of the process. It points JAX's
cache at

* `$JAXNH_CACHE_DIR` when set (`JAXNH_CACHE_DIR=off`, `0`, `none` or empty
  disables the cache),
* else `$XDG_CACHE_HOME/jaxnh`,
* else `~/.cache/jaxnh`,

unless the user has configured JAX's cache themselves
(`jax_compilation_cache_dir`, e.g. through `JAX_COMPILATION_CACHE_DIR`, or
`jax_enable_compilation_cache=False`): then nothing is changed.

Safety. A compilation cache holds native code that JAX loads and runs, so
anyone who can write into the folder can run code as the user (JAX's own
documentation says so for `set_cache_dir`). The folder is therefore created
with mode 0700, and an existing one is used only when it is a real directory
(not a symbolic link), owned by the current user, not writable by group or
others, in a parent folder that others cannot write (unless it has the
sticky bit, like /tmp); otherwise a `warnings.warn` names the problem and the fix, and no
cache is used (nothing is read from it).

Every compiled program is written (`MIN_COMPILE_TIME_SECS` = 0; JAX's default
threshold of 1 s leaves out most of a small simulation's programs and the
warm first call was 50 % slower with it). Programs containing host callbacks
(e.g. equinox's `error_if`) are never cached by JAX: they are compiled again
in every process.
"""

from __future__ import annotations

import os
import stat
import warnings
from typing import Mapping

import jax


__all__ = ["enable_compilation_cache", "cache_dir", "check_cache_dir", "MIN_COMPILE_TIME_SECS", "OFF_VALUES"]

OFF_VALUES = ("", "0", "off", "none", "false", "no")
MIN_COMPILE_TIME_SECS = 0.0
"""Programs compiled faster than this (s) are not written to the cache. 0: every
program is written. Measured once, by a script since removed (a fresh process
importing jaxnh and running the README's variator, programs without host
callbacks; medians of 3, 2 loaded cores): the first call after the import took
2.1 s from a warm cache with JAX's default threshold of 1 s (1 entry written),
1.9 s with 0.1 s (2 entries) and 1.4 s with 0 (17 entries), against 5.4–6.6 s cold.
benchmarks/first_answer.py measures first answers cold and from a warm cache
at this setting (not the other thresholds)."""

JAX_DEFAULT_MIN_COMPILE_TIME = 1.0
_active: str | None = None  # the folder this module gave JAX


class UnsafeCacheDirWarning(UserWarning):
    """The compilation-cache folder could be written by someone else; it is not used."""


def cache_dir(environ: Mapping[str, str] | None = None) -> str | None:
    """The folder jaxnh would use for compiled programs, or None when disabled.

    `$JAXNH_CACHE_DIR` (off/0/none/empty: disabled), else `$XDG_CACHE_HOME/jaxnh`,
    else `~/.cache/jaxnh`. Nothing is created or checked here.
    """
    env = os.environ if environ is None else environ
    path = env.get("JAXNH_CACHE_DIR")
    if path is not None:
        if path.strip().lower() in OFF_VALUES:
            return None
        return os.path.abspath(os.path.expanduser(path))
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.abspath(os.path.join(base, "jaxnh"))


def _uid():
    getuid = getattr(os, "getuid", None)
    return None if getuid is None else getuid()


def check_cache_dir(path: str) -> str | None:
    """Why `path` must not hold compiled programs, or None when it is safe.

    Safe: a directory (not a symbolic link to one), owned by the current user,
    not writable by group or others, whose parent others cannot write (or has
    the sticky bit). A path that does not exist is "missing"
    (the caller creates it).
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return "missing"
    except OSError as e:
        return f"cannot be inspected ({e.strerror})"
    if stat.S_ISLNK(st.st_mode):
        return "is a symbolic link (it could be redirected to a folder others can write)"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    uid = _uid()
    if uid is not None and st.st_uid != uid:
        return f"is owned by another user (uid {st.st_uid}; you are uid {uid})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        who = "others" if st.st_mode & stat.S_IWOTH else "its group"
        return f"is writable by {who} (mode {stat.S_IMODE(st.st_mode):04o})"
    return _check_parent(path)


def _check_parent(path: str) -> str | None:
    """A folder whose parent others can write (without the sticky bit, as /tmp has) can be
    renamed away and replaced by theirs after it was checked."""
    parent = os.path.dirname(os.path.abspath(path))
    try:
        st = os.stat(parent)
    except OSError:
        return None
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not st.st_mode & stat.S_ISVTX:
        return (
            f"is in {parent}, which others can write (mode {stat.S_IMODE(st.st_mode):04o}, no sticky bit), "
            "so it could be replaced by theirs"
        )
    return None


def _prepare(path: str) -> str | None:
    """Create `path` with mode 0700 if missing; return why it is unsafe, or None."""
    why = check_cache_dir(path)
    if why != "missing":
        return why
    missing = []  # the folder and its missing ancestors, created 0700 (as the XDG spec asks for ~/.cache)
    p = path
    while not os.path.exists(p):
        missing.append(p)
        up = os.path.dirname(p)
        if up == p:
            break
        p = up
    why = _check_parent(missing[-1])  # the existing folder we create into
    if why is not None:
        return why
    try:
        for p in reversed(missing):
            try:
                os.mkdir(p, 0o700)
                os.chmod(p, 0o700)  # the mode given to mkdir is masked by the umask; make it exact
            except FileExistsError:
                pass  # created concurrently (another process): judged below
    except OSError as e:
        return f"cannot be created ({e.strerror})"
    why = check_cache_dir(path)
    return "cannot be created" if why == "missing" else why


def _user_configured() -> bool:
    # (jax.config's flags are attributes it creates at run time, which type checkers do not see)
    if jax.config.jax_compilation_cache_dir:  # pyright: ignore[reportAttributeAccessIssue]
        return True  # set in code, or JAX_COMPILATION_CACHE_DIR
    return not jax.config.jax_enable_compilation_cache  # pyright: ignore[reportAttributeAccessIssue]


def enable_compilation_cache(environ: Mapping[str, str] | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache in the user's cache folder.

    Call it once, right after importing jaxnh and before anything is compiled:
    JAX decides whether to use a cache at the first compilation of a process.

    See the module docstring for the folder, the opt-out (`JAXNH_CACHE_DIR=off`)
    and the safety rules. Leaves JAX alone when the user configured its cache
    (`jax_compilation_cache_dir` or `jax_enable_compilation_cache`). Lowers
    `jax_persistent_cache_min_compile_time_secs` from JAX's default 1 s to
    `MIN_COMPILE_TIME_SECS` unless the user changed it. Never raises: an
    unusable folder gives a warning and no cache.

    Returns:
        The folder now in use, or None (disabled, configured by the user, or refused).
    """
    global _active

    env = os.environ if environ is None else environ
    # jax.config's flags are attributes it creates at run time, which type checkers do not see
    if _active is not None and jax.config.jax_compilation_cache_dir == _active:  # pyright: ignore[reportAttributeAccessIssue]
        return _active  # already set up by an earlier call
    if _user_configured():
        return None
    path = cache_dir(env)
    if path is None:
        return None
    why = _prepare(path)
    if why is not None:
        warnings.warn(
            f"jaxnh: not using the compilation cache folder {path}: it {why}. Compiled programs are native "
            "code, so a folder others can write would let them run code as you. Fix: remove or chmod 700 it "
            "(it must be your own directory), or set JAXNH_CACHE_DIR to another folder, or JAXNH_CACHE_DIR=off.",
            UnsafeCacheDirWarning,
            stacklevel=2,
        )
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    if (
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in env
        and jax.config.jax_persistent_cache_min_compile_time_secs == JAX_DEFAULT_MIN_COMPILE_TIME  # pyright: ignore[reportAttributeAccessIssue]
    ):
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_SECS)
    _active = path
    return path
