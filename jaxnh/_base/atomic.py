"""Files that appear whole or not at all: write to a temporary name, then rename.

`os.replace` within one folder is atomic on POSIX and Windows, so a reader
(or a crash, or Ctrl-C) never sees a half-written result: the target either
keeps its old content or has the complete new one.
"""

from __future__ import annotations

import contextlib
import os
import tempfile


__all__ = ["atomic_write", "check_writable_file", "check_writable_dir"]


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", **open_kw):
    """Open a temporary file next to `path`; on success rename it to `path`.

    On an exception the temporary file is removed and `path` is untouched.
    The new file gets the usual permissions of a new file (0666 minus the umask).
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    base = os.path.basename(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=".tmp", dir=folder)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give a normal new file's mode
        with os.fdopen(fd, mode, **open_kw) as f:
            fd = None
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
    finally:
        if fd is not None:
            os.close(fd)
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def atomic_save_figure(fig, path, **savefig_kw) -> str:
    """`fig.savefig(path)` through a temporary file in the same folder, then rename."""
    path = os.fspath(path)
    fmt = savefig_kw.pop("format", None) or os.path.splitext(path)[1].lstrip(".") or "png"
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format=fmt, **savefig_kw)
    return path


def check_writable_file(path, what: str) -> str | None:
    """Why a file cannot be written at `path` (None when it can): the folder
    must exist and be writable, and `path` must not be a folder."""
    path = os.fspath(path)
    if not path:
        return f"{what}: empty path"
    full = os.path.abspath(path)
    if os.path.isdir(full):
        return f"{what} {path}: is a folder; give a file name"
    folder = os.path.dirname(full)
    if not os.path.isdir(folder):
        return f"{what} {path}: the folder {folder} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"{what} {path}: the folder {folder} is not writable"
    if os.path.exists(full) and not os.access(full, os.W_OK):
        return f"{what} {path}: the file exists and is not writable"
    return None


def check_writable_dir(path, what: str) -> str | None:
    """Why figures cannot be written into folder `path` (None when they can).
    A missing folder is fine when its parent exists and is writable (it is created)."""
    path = os.fspath(path)
    if not path:
        return f"{what}: empty path"
    full = os.path.abspath(path)
    if os.path.exists(full):
        if not os.path.isdir(full):
            return f"{what} {path}: exists and is not a folder"
        if not os.access(full, os.W_OK | os.X_OK):
            return f"{what} {path}: the folder is not writable"
        return None
    parent = os.path.dirname(full)
    if not os.path.isdir(parent):
        return f"{what} {path}: its parent folder {parent} does not exist"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"{what} {path}: the parent folder {parent} is not writable"
    return None
