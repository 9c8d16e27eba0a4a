"""What the sub-commands of `jaxnh` share: exit statuses, the figure backend, optional plotting.

Figures need matplotlib, an optional dependency (jaxnh's `plot` extra).
Without it every sub-command still computes and writes its results; it says
on stderr which figures it leaves out, and the exit status is the one the
results call for (a missing matplotlib is never a failure).
"""

from __future__ import annotations

import os
import sys
import tempfile


__all__ = [
    "EXIT_OK",
    "EXIT_FAILED",
    "EXIT_BAD_INPUT",
    "EXIT_INTERRUPTED",
    "PLOT_HINT",
    "use_agg",
    "plotting_available",
    "probe_writable_dir",
    "occupied_outputs",
]

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a command stopped by Ctrl-C
PLOT_HINT = "pip install matplotlib, or jaxnh[plot]"  # the wording of jaxnh.identify.plots


def use_agg() -> None:
    """Figures of the command line go to files: the Agg backend, unless pyplot is already in use."""
    if "matplotlib.pyplot" in sys.modules:
        return
    if sys.modules.get("matplotlib") is not None:
        sys.modules["matplotlib"].use("Agg")
    else:  # read by matplotlib when (if) it is imported: a run that draws nothing does not import it (0.2 s)
        os.environ["MPLBACKEND"] = "Agg"


def plotting_available(command: str, skipped: str) -> bool:
    """Whether figures can be drawn (matplotlib and its pyplot import). If not, say on stderr
    what is left out (`skipped`, e.g. "design.png is not drawn") and how to get it."""
    try:
        import matplotlib.pyplot  # noqa: F401  (optional dependency: the plot extra)
    except ImportError as e:
        if isinstance(e, ModuleNotFoundError) and (e.name or "").split(".")[0] == "matplotlib":
            why = "matplotlib is not installed"
        else:  # installed but broken (e.g. one of its own dependencies is missing)
            why = f"matplotlib cannot be imported ({type(e).__name__}: {e})"
        print(f"jaxnh {command}: {why}: {skipped} ({PLOT_HINT}); everything else is written as usual", file=sys.stderr)
        return False
    return True


def probe_writable_dir(path, what: str) -> str | None:
    """Why files cannot be created in folder `path` (None when they can), found by creating and
    removing an empty file there (in its parent when `path` does not exist yet: it is created
    later), before any work. Permission bits do not tell (root passes them; a read-only or
    special file system refuses anyway), so this is tried after the checks of the path itself."""
    full = os.path.abspath(os.fspath(path))
    where = full if os.path.isdir(full) else os.path.dirname(full)
    try:
        fd, probe = tempfile.mkstemp(prefix=".jaxnh-probe-", dir=where)
    except OSError as e:
        return f"{what} {path}: cannot create a file in {where}: {e.strerror or e}"
    os.close(fd)
    os.unlink(probe)
    return None


def occupied_outputs(folder, names, what: str) -> str | None:
    """Why an output file cannot be written in `folder`: one of its `names` is a folder there."""
    for name in names:
        f = os.path.join(os.fspath(folder), name)
        if os.path.isdir(f):
            return f"{what}: {f} is a folder; it must be free for an output file"
    return None
