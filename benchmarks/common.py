"""Shared machinery of the benchmark suite: timing, fresh processes, errors, output, the source stamp.

Timing rules. In-process times are process CPU time (`time.process_time`),
medians over interleaved rounds after compilation: contenders take turns
round by round, so load from other processes hits them alike, and a ratio is
the median of the per-round ratios. Wall times are recorded too. The machine
these run on is shared: wall time there mostly measures waiting for a core,
CPU time what a call costs on an idle core.

Each study pins itself to one core with XLA's thread pools off (`pin`, before
JAX starts) (XLA's idle pool threads spin and inflate CPU times; these
solves are too small to gain from threads); `JAXNH_BENCH_XLA_THREADS=default`
keeps XLA's own setting. Fresh processes (`fresh`) get the user's defaults
back: every core, the original XLA flags, empty cache folders.
"""

from __future__ import annotations

import ast
import datetime
import hashlib
import importlib.util
import json
import os
import pathlib
import platform
import re
import shlex
import subprocess
import sys
import tempfile
import time


HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
_ENV0 = dict(os.environ)  # before `pin`: what fresh processes get back
_CPUS0 = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
PINNED_CPU = None


def pin():
    """Pin this process to one core and turn XLA's thread pools off; call before JAX is imported.
    (Importing this module changes nothing: `stale` can be called from anywhere.)"""
    global PINNED_CPU
    if os.environ.get("JAXNH_BENCH_XLA_THREADS") == "default":
        return
    if "intra_op_parallelism" not in os.environ.get("XLA_FLAGS", ""):
        flags = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flags).strip()
    if _CPUS0:
        PINNED_CPU = _CPUS0[os.getpid() % len(_CPUS0)]
        os.sched_setaffinity(0, {PINNED_CPU})


import numpy as np


# Where JSON results, figures and RESULTS.md go: benchmarks/ itself, or $JAXNH_BENCH_OUT
# (`make bench-quick` writes to benchmarks/quick/ so a short run leaves the record alone).
OUT = pathlib.Path(os.environ["JAXNH_BENCH_OUT"]).resolve() if os.environ.get("JAXNH_BENCH_OUT") else HERE
RESULTS = OUT / "results"
FIGURES = OUT / "figures"
RTOL, ATOL = 1e-8, 1e-10  # simulate's defaults: every contender of a default-settings row uses them


# --------------------------------------------------------------------------- timing


def interleave(calls: dict, rounds: int = 7, budget: float | None = None, min_rounds: int = 5) -> dict:
    """Call each zero-argument callable once per round, in turn; name -> {"cpu": [...], "wall": [...]} (s).
    Stops after `min_rounds` once `budget` seconds of wall time have passed."""
    out = {k: {"cpu": [], "wall": []} for k in calls}
    start = time.perf_counter()
    for r in range(rounds):
        for k, fn in calls.items():
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            out[k]["cpu"].append(time.process_time() - c0)
            out[k]["wall"].append(time.perf_counter() - w0)
        if budget is not None and r + 1 >= min_rounds and time.perf_counter() - start > budget:
            break
    return out


def repeat(fn, seconds: float = 0.05):
    """A callable running `fn` n times (n so that one call of it takes about `seconds`), and n: times of
    sub-millisecond calls are then per call after dividing by n."""
    fn()
    t0 = time.process_time()
    fn()
    n = max(1, int(seconds / max(time.process_time() - t0, 1e-6)))

    def many():
        for _ in range(n):
            fn()

    return many, n


def median(xs) -> float:
    return float(np.median(np.asarray(xs, dtype=float)))


def paired_ratio(num, den) -> float:
    """Median over rounds of num[i] / den[i] (timed in the same round)."""
    n = min(len(num), len(den))
    return float(np.median(np.asarray(num[:n], float) / np.asarray(den[:n], float)))


def max_error(q, qd, q_ref, qd_ref) -> float:
    """Largest absolute error over the report times, coordinates and velocities."""
    return float(max(np.max(np.abs(np.asarray(q) - q_ref)), np.max(np.abs(np.asarray(qd) - qd_ref))))


def growth_exponent(ns, ts) -> float:
    """Least-squares slope of log t against log n: t ∝ n^k."""
    return float(np.polyfit(np.log(np.asarray(ns, float)), np.log(np.asarray(ts, float)), 1)[0])


# --------------------------------------------------------------------------- fresh processes


def fresh(code: str, env: dict | None = None, timeout: float = 1800) -> dict:
    """Run `code` in a new Python process with the user's defaults (every core, the original XLA flags,
    JAX's compilation cache off, `JAXNH_CACHE_DIR` an empty folder, unless `env` says otherwise) and
    return the JSON object it prints last.

    `code` fills a dict `OUT`, printed as JSON by `FRESH_TAIL` with "wall" (s, from before the first
    import) and "cpu" (s, the process's CPU time) added; `IMPORTED` in `code` records both at that point
    as "import" and "import_cpu".
    """
    e = {k: v for k, v in _ENV0.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAXNH_CACHE"))}
    e["PYTHONPATH"] = os.pathsep.join([str(ROOT), e.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    e.update(env or {})
    e.setdefault("JAXNH_CACHE_DIR", cache_dirs()[0])  # empty: no program compiled earlier can be found

    unpin = f"__import__('os').sched_setaffinity(0, {set(_CPUS0)!r})\n" if _CPUS0 else ""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(
            [sys.executable, "-c", unpin + FRESH_HEAD + code + FRESH_TAIL], stdout=out, stderr=err, env=e, cwd=str(ROOT)
        )
        start, peak, why = time.perf_counter(), 0, None
        while proc.poll() is None:  # a guard: some programs need more memory to compile than the machine has
            peak = max(peak, _rss_gb(proc.pid))
            if peak > MAX_RSS_GB or time.perf_counter() - start > timeout:
                proc.kill()
                why = f"more than {MAX_RSS_GB:g} GB of memory" if peak > MAX_RSS_GB else f"more than {timeout:.0f} s"
            time.sleep(0.2)
        proc.wait()
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if why:
        raise RuntimeError(f"killed after {time.perf_counter() - start:.0f} s: it took {why}")
    if proc.returncode != 0:
        raise RuntimeError(f"fresh process failed ({proc.returncode}):\n{stderr[-3000:]}")
    out_ = json.loads(stdout.strip().splitlines()[-1])
    out_["peak_rss_gb"] = peak
    return out_


MAX_RSS_GB = float(os.environ.get("JAXNH_BENCH_MAX_RSS_GB", "6"))
"""A fresh process using more memory than this (GB) is killed (`JAXNH_BENCH_MAX_RSS_GB`)."""


def _rss_gb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            return next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:")) / 1e6
    except (OSError, StopIteration, ValueError):
        return 0.0


FRESH_HEAD = "import time as _t\n_w0, _c0 = _t.perf_counter(), _t.process_time()\n"
IMPORTED = 'OUT = {"import": _t.perf_counter() - _w0, "import_cpu": _t.process_time() - _c0}'
FRESH_TAIL = (
    "\nimport json as _j\nOUT.update(wall=_t.perf_counter() - _w0, cpu=_t.process_time() - _c0)\n"
    "print(_j.dumps(OUT, default=lambda x: __import__('numpy').asarray(x).tolist()))\n"
)


def cache_dirs(n: int = 1) -> list:
    """`n` empty, private temporary folders (removed at exit)."""
    out = []
    for _ in range(n):
        d = tempfile.TemporaryDirectory(prefix="jaxnh-bench-cache-")
        _KEEP.append(d)
        out.append(d.name)
    return out


_KEEP: list = []


# --------------------------------------------------------------------------- the stamp


def _executable(source: str) -> str:
    """The code of a Python module without what cannot change what it computes: comments and
    layout (gone in the syntax tree), string literals standing alone as statements (docstrings of
    modules, classes and functions, and those written under an assignment), and the annotations of
    function arguments and returns (strings under `from __future__ import annotations`). Annotated
    assignments keep theirs: a dataclass or equinox Module makes its fields from them."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        for field in ("body", "orelse", "finalbody"):
            stmts = getattr(node, field, None)
            if isinstance(stmts, list):
                kept = [x for x in stmts if not _bare_string(x)]
                setattr(node, field, kept or ([ast.Pass()] if field == "body" else []))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            node.returns = None
            a = node.args
            for arg in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg]:
                if arg is not None:
                    arg.annotation = None
    return ast.dump(tree)


def _bare_string(stmt) -> bool:
    return isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant) and isinstance(stmt.value.value, str)


def source_digest(root: pathlib.Path = ROOT) -> str:
    """SHA-256 (first 16 hex digits) of the executable code of every jaxnh/**/*.py file (with its
    path): an edit to a comment, a docstring or a signature's type hints leaves the benchmarks'
    records current, any other edit marks them stale."""
    h = hashlib.sha256()
    for f in sorted((root / "jaxnh").rglob("*.py")):
        code = _executable(f.read_text(encoding="utf-8"))
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + code.encode() + b"\0")
    return h.hexdigest()[:16]


DIGEST_LINE = re.compile(r"source digest of jaxnh/: `([0-9a-f]{16})`")


def stale(results_path=None) -> bool:
    """True when a results file (benchmarks/RESULTS.md by default) was measured on other sources than
    today's jaxnh/ (its stamped digest differs from `source_digest()`), or carries no stamp."""
    path = pathlib.Path(results_path) if results_path is not None else HERE / "RESULTS.md"
    if not path.exists():
        return True
    m = DIGEST_LINE.search(path.read_text())
    return m is None or m.group(1) != source_digest()


def machine() -> dict:
    cpu = "unknown"
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass

    def git(*args):
        try:
            return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    import diffrax
    import jax
    import scipy

    return dict(
        cpu=cpu,
        cores=os.cpu_count(),
        platform=platform.platform(),
        python=platform.python_version(),
        versions=dict(jax=jax.__version__, diffrax=diffrax.__version__, numpy=np.__version__, scipy=scipy.__version__),
        load_average=[round(x, 2) for x in os.getloadavg()],
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        revision=git("rev-parse", "--short", "HEAD") or "unknown",
        uncommitted=bool(git("status", "--porcelain", "--untracked-files=all", "jaxnh")),
        digest=source_digest(),
        pinned_cpu=PINNED_CPU,
    )


def report_dir(quick: bool) -> pathlib.Path:
    """Where a study that writes its own report (STABILITY.md, CALIBRATION.md, …) puts it and its results/:
    `$JAXNH_BENCH_OUT` when set, else benchmarks/quick/ for a `--quick` run (a short run leaves the
    recorded report alone), else benchmarks/."""
    out = OUT if OUT != HERE else (HERE / "quick" if quick else HERE)
    out.mkdir(parents=True, exist_ok=True)
    return out


def stamp_line(command: str) -> str:
    """The line under the title of a report that a study writes itself (STABILITY.md, CALIBRATION.md, …):
    the command that wrote it, the revision, the source digest of jaxnh/ (what `stale(path)` compares),
    the date, the CPU and the load. Same facts as RESULTS.md's stamp."""
    m = machine()
    v = m["versions"]
    return (
        f"> Written by `{command}`; **revision** `{m['revision']}`"
        + (" with uncommitted changes in jaxnh/" if m["uncommitted"] else "")
        + f"; source digest of jaxnh/: `{m['digest']}`; {m['date']}; CPU {m['cpu']} ({m['cores']} cores), "
        + f"load average {m['load_average'][0]:.1f} at the end; JAX {v['jax']}, diffrax {v['diffrax']} "
        + "(`benchmarks.common.stale(path)` compares the digest with today's jaxnh/)."
    )


def command(module: str, argv=None) -> str:
    """How this study was run, for its report: `python -m benchmarks.<module> <arguments>`."""
    args = sys.argv[1:] if argv is None else list(argv)
    return shlex.join(["python", "-m", "benchmarks." + module, *args])


def example(name: str):
    """The module examples/<name>.py (the examples are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# --------------------------------------------------------------------------- output


def save(name: str, data: dict, out: pathlib.Path | None = None) -> pathlib.Path:
    """Write `data` and the `machine()` stamp to results/<name>.json under `out` (default `OUT`)."""
    folder = RESULTS if out is None else pathlib.Path(out) / "results"
    folder.mkdir(parents=True, exist_ok=True)
    data = dict(data, machine=machine())
    path = folder / f"{name}.json"
    path.write_text(json.dumps(data, indent=1, default=_jsonable))
    return path


def load(name: str) -> dict | None:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _jsonable(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return np.asarray(x).tolist()


def log(*a):
    print(*a, flush=True)
