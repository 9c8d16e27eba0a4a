"""Programs kept on disk as traced, exported StableHLO (`jax.export`), so that a second
process skips tracing them.

The persistent compilation cache (`jaxnh._cache`) saves XLA's compilation, but every
process still traces and lowers its programs first: for the fit's residual Jacobian
(a forward-sensitivity solve, vmapped over the free parameters) that is 2 s of the
5 s of a warm `jaxnh fit`. An exported program is loaded instead and compiled (from the
persistent cache when it is there).

Only programs built entirely from jaxnh's own code are kept: the key is a fingerprint of
everything static in the arguments (types, static fields, Python numbers, shapes and
dtypes of the arrays, the values captured by jaxnh's own local functions), the versions
of jax, jaxlib, diffrax, equinox, lineax and optimistix, the backend, and a digest of
jaxnh's source files. A function from outside the jaxnh package (a user's kinetic
energy, say) could change without changing anything the fingerprint sees (a helper it
calls), so arguments holding one are not exported, with one exception: a `Mechanism`,
when the caller passes the state it is evaluated at (`mech_args`, as `simulate` does), is
identified by the jaxprs of its functions there, with the values of the arrays they
capture, which change with anything that changes what they compute
(`_mechanism_fingerprint`). Calls under a trace, and programs JAX cannot export (host
callbacks), fall back to the ordinary compiled path.

Files live in `<cache folder>/exported/` (the folder jaxnh's compilation cache uses and
checks: owned by the user, mode 0700), are written atomically and read only from there.

Shipped programs. The programs of jaxnh's built-in models and command-line jobs (the
bicycle's linearisation, the fit on the embedded record, their checks) are also shipped
in the package, in `jaxnh/programs/` (built by `make programs`). They carry the same key, so one is used only where this
process would trace exactly that program itself: same jaxnh sources, same versions of
the JAX stack, same backend; anywhere else they are simply not found. A first run on a
fresh install then skips tracing those programs, and compiles them.

`JAXNH_CACHE_DIR=off` turns all of this off with the compilation cache: nothing is read
from disk or written to it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import hashlib
import os
import tempfile
import types
from typing import Any, Callable, Optional, TypeVar

import equinox as eqx
import jax
import jax.core
import numpy as np


__all__ = ["exported_call", "one_shot_jit", "compile_ahead", "ONE_SHOT", "SIMULATE_OPTIONS", "SHIPPED", "build_shipped"]

SHIPPED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "programs")
"""The folder of programs shipped with the package (read only, except by `build_shipped`)."""
_BUILDING = False
"""True while `build_shipped` runs: new programs are written to `SHIPPED`, nothing else is read."""

_MEMO: dict = {}
"""key → jitted call of the deserialized program (one load per process)."""
_REFUSED: set = set()
"""keys that could not be exported (host callbacks, ...): not tried again in this process."""
_KEYS: dict = {}
"""`memo` key of a call → its program key ("" when it has none): fingerprints once per process."""
_FAST: dict = {}
"""`memo` key of a call → its compiled program: later calls skip the key and the lookups."""


class _Unstable(Exception):
    """Something in the arguments has no fingerprint that identifies the program."""


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """SHA-256 over jaxnh's Python sources (a changed file changes every key)."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in sorted(filenames):
            if name.endswith(".py"):
                path = os.path.join(dirpath, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def _versions() -> str:
    from importlib.metadata import version

    names = ("jax", "jaxlib", "diffrax", "equinox", "lineax", "optimistix")
    return " ".join(f"{name} {version(name)}" for name in names)


def _own(obj) -> bool:
    module = getattr(obj, "__module__", None) or ""
    return module == "jaxnh" or module.startswith("jaxnh.")


_MECH_ARGS: Optional[tuple] = None
"""While `exported_call` fingerprints a call given `mech_args=(q, qd, t, params)`: those, so that a
`Mechanism` is identified by the jaxprs of its functions at them (`_mechanism_fingerprint`)."""


def _fingerprint(x, depth: int = 0) -> Any:
    """A nested tuple of strings that determines the traced program for these arguments."""
    if depth > 60:
        raise _Unstable("too deep")
    if _MECH_ARGS is not None and _is_mechanism(x):
        return _mechanism_fingerprint(x)
    if isinstance(x, jax.core.Tracer):
        raise _Unstable("traced")
    if isinstance(x, (jax.Array, np.ndarray)):
        return ("array", tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False)))
    if isinstance(x, np.generic):
        return ("scalar", type(x).__name__, repr(x))
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        return (type(x).__name__, repr(x))
    if isinstance(x, enum.Enum):
        return ("enum", type(x).__module__, type(x).__qualname__, x.name)
    if isinstance(x, (tuple, list)):
        return (type(x).__name__, tuple(_fingerprint(v, depth + 1) for v in x))
    if isinstance(x, dict):
        items = sorted(x.items(), key=lambda kv: repr(kv[0]))
        return ("dict", tuple((repr(k), _fingerprint(v, depth + 1)) for k, v in items))
    if isinstance(x, functools.partial):
        return (
            "partial",
            _fingerprint(x.func, depth + 1),
            _fingerprint(x.args, depth + 1),
            _fingerprint(x.keywords, depth + 1),
        )
    if isinstance(x, types.MethodType):
        return ("method", _fingerprint(x.__self__, depth + 1), _fingerprint(x.__func__, depth + 1))
    if isinstance(x, (types.FunctionType, types.BuiltinFunctionType, type)):
        own = _own(x)
        if not own and (getattr(x, "__module__", "") or "").split(".")[0] not in _STABLE_MODULES:
            raise _Unstable(f"foreign callable {getattr(x, '__module__', '?')}.{getattr(x, '__qualname__', '?')}")
        if isinstance(x, types.FunctionType):
            if not own and (x.__closure__ or "<" in x.__qualname__):
                raise _Unstable(f"closure or local function {x.__qualname__}")
            # jaxnh's own local functions: the code is in the source digest, the captured values here
            cells = tuple(_fingerprint(c.cell_contents, depth + 1) for c in (x.__closure__ or ()))
            defaults = _fingerprint((x.__defaults__, x.__kwdefaults__), depth + 1)
            return ("function", x.__module__, x.__qualname__, cells, defaults)
        return ("callable", x.__module__, x.__qualname__)
    cls = type(x)
    if dataclasses.is_dataclass(x):  # equinox Modules are dataclasses
        if not (_own(cls) or (cls.__module__.split(".")[0] in _STABLE_MODULES)):
            raise _Unstable(f"foreign class {cls.__module__}.{cls.__qualname__}")
        return (
            "object",
            cls.__module__,
            cls.__qualname__,
            tuple((f.name, _fingerprint(getattr(x, f.name, None), depth + 1)) for f in dataclasses.fields(x)),
        )
    raise _Unstable(f"unknown object {cls.__module__}.{cls.__qualname__}")


def _is_mechanism(x) -> bool:
    from ._mechanism import Mechanism

    return isinstance(x, Mechanism)


def _mechanism_fingerprint(mech) -> tuple:
    """A mechanism identified by what its functions compute at the call's arguments: the jaxpr of
    each (T, c, Q, V, g, S) at the shapes and dtypes of (q, qd, t, params), with the values of the
    arrays it captures, and its other fields. A helper the functions call, a global they read, a
    closure's values: any change in what they compute changes a jaxpr. Functions whose jaxpr holds
    Python code that JAX does not trace (custom derivative rules, host callbacks) give no key."""
    assert _MECH_ARGS is not None
    q, qd, t, params = _MECH_ARGS
    qdd = jax.ShapeDtypeStruct(q.shape, q.dtype)
    signatures = {
        "kinetic": (q, qd, t, params),
        "constraints": (q, qd, t, params),
        "forces": (q, qd, t, params),
        "potential": (q, t, params),
        "holonomic": (q, t, params),
        "acceleration_energy": (q, qd, qdd, t, params),
    }
    parts = []
    for f in dataclasses.fields(mech):
        value = getattr(mech, f.name)
        if f.name in signatures and value is not None:
            parts.append((f.name, _jaxpr_fingerprint(value, signatures[f.name])))
        else:
            parts.append((f.name, _fingerprint(value, 1)))
    cls = type(mech)
    return ("mechanism", cls.__module__, cls.__qualname__, tuple(parts))


def _jaxpr_fingerprint(fn, args) -> tuple:
    try:
        closed = jax.make_jaxpr(fn)(*args)
    except Exception as e:  # noqa: BLE001 - the ordinary path will report it
        raise _Unstable(f"not traceable: {type(e).__name__}") from None
    _only_traced_code(closed.jaxpr)
    consts = tuple(
        (tuple(np.shape(c)), str(np.asarray(c).dtype), hashlib.sha256(np.ascontiguousarray(c).tobytes()).hexdigest())
        for c in closed.consts
    )
    return ("jaxpr", str(closed.jaxpr), consts)


def _only_traced_code(jaxpr) -> None:
    """Refuse a jaxpr whose equations carry Python callables (custom_jvp/custom_vjp rules, host
    callbacks): their code is not in the jaxpr's text, so a change in it would go unseen."""
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if "custom" in name or "callback" in name:
            raise _Unstable(f"Python code in a jaxpr ({name})")
        for value in eqn.params.values():
            for v in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(v, "jaxpr", v)
                if hasattr(inner, "eqns"):
                    _only_traced_code(inner)
                elif callable(v) or type(v).__name__ == "WrappedFun":
                    raise _Unstable(f"Python code in a jaxpr ({name})")


_STABLE_MODULES = ("diffrax", "equinox", "lineax", "optimistix", "jax", "numpy", "builtins")
"""Libraries whose version is part of the key: their classes and functions are identified by
name (their code is fixed for a given version)."""


def _folder() -> Optional[str]:
    from . import _cache

    base = _cache._active
    if base is None:
        return None
    path = os.path.join(base, "exported")
    if not os.path.isdir(path):
        try:
            os.mkdir(path, 0o700)
            os.chmod(path, 0o700)
        except FileExistsError:
            pass
        except OSError:
            return None
    return path if _cache.check_cache_dir(path) is None else None


SIMULATE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
"""XLA options for simulations called with concrete values: XLA's classic elemental emitters
instead of its newer fusion emitters (on CPU; other backends ignore `xla_cpu_*` options).
Measured on this 2-core CPU, jaxlib 0.10.2 (`python -m benchmarks.lean_loop --quick` with and
without `XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`; the README's variator cold): the
variator's simulation compiles in 0.64 s instead of 1.05–1.08 s, one trajectory steps at the
same cost (3.72 against 3.76 µs per DOP853 step with the derived Appell field) and a vmapped
batch of 1000 runs 21 % faster (53.5 against 67.9 ms)."""

ONE_SHOT = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""XLA options for programs evaluated a handful of times (a linearisation). Measured on the
Whipple bicycle's linearisation (24k StableHLO operations, 2-core CPU, jaxlib 0.10.2): XLA's
default settings compile it in 8.8 s and run it in 0.9 ms; optimisation level 0 with the
newer fusion emitters in 7.1 s / 3.3 ms; optimisation level 0 with the classic elemental
emitters (these options) in 3.1–4.3 s / 0.8–1.6 ms. (`xla_cpu_*` options are ignored by
other backends.)"""

_F = TypeVar("_F", bound=Callable)


def one_shot_jit(fn: _F) -> _F:
    """`equinox.filter_jit` with `ONE_SHOT`, for jaxnh's programs that run a few times per
    structure (a linearisation, a fit's starting guess and error bands, a check), which are
    also kept and shipped as exported programs (`exported_call`) when the arguments allow.
    Inside a caller's `jit` it is traced into the caller's program (JAX refuses compiler options on
    a nested jit); under `vmap` alone (every traced argument batched values, nothing else) it is
    compiled with the options, for the batch; under `grad` and other transformations it is the
    ordinary `filter_jit`, without them."""
    from ._status import is_traced, under_jit

    # (equinox's type hints of filter_jit leave out the keyword arguments it passes on to jax.jit)
    jitted = eqx.filter_jit(fn, compiler_options=ONE_SHOT)  # pyright: ignore[reportCallIssue]
    plain = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if under_jit():  # part of the caller's program (JAX takes compiler options only at the top)
            return fn(*args, **kwargs)
        if is_traced(args, kwargs):
            if _only_batched(args, kwargs):  # an eager vmap: compiled for the batch, with the options
                try:
                    return jitted(*args, **kwargs)
                except ValueError as e:  # a transformation below the vmap after all
                    if "compiler_options" not in str(e):
                        raise
            return plain(*args, **kwargs)  # under grad and the like: without the options
        out = exported_call(
            fn, args, kwargs, name=fn.__name__, compiler_options=ONE_SHOT, memo=_static_memo(args, kwargs)
        )
        return jitted(*args, **kwargs) if out is None else out

    def lower(*args, **kwargs):
        """The program `call(*args, **kwargs)` would compile, lowered (a `jax.stages.Lowered`), or
        None under a transformation. Arrays may be stand-ins of the same shapes and dtypes (NumPy
        zeros, say): only the structure counts."""
        if under_jit() or is_traced(args, kwargs):
            return None
        resolved = _exported_program(fn, args, kwargs, name=fn.__name__, compiler_options=ONE_SHOT)
        if resolved is None:
            return jitted.lower(*args, **kwargs)
        program, inputs, lapack_free = resolved
        with _lapack_left_alone() if lapack_free else contextlib.nullcontext():
            return program.lower(*inputs)

    call.lower = lower  # pyright: ignore[reportAttributeAccessIssue]
    return call  # pyright: ignore[reportReturnType]


def _only_batched(*trees) -> bool:
    """Whether every traced leaf is `jax.vmap`'s batched value of a concrete array (an eager vmap,
    perhaps nested, and no other transformation), judged by JAX's tracer classes; False when they
    cannot be found (another JAX version)."""
    try:
        from jax._src.interpreters.batching import BatchTracer
    except ImportError:
        return False
    for x in jax.tree_util.tree_leaves(trees):
        while isinstance(x, BatchTracer):
            x = x.val
        if isinstance(x, jax.core.Tracer):
            return False
    return True


def _static_memo(args, kwargs) -> Any:
    """A hashable stand-in for everything static in a call's arguments (their tree structure, with
    the static fields of equinox Modules, and each leaf that is not an array, with its type), for
    `exported_call` to find the program of a later call with equal static arguments without
    fingerprinting them again; None when something static cannot be hashed."""
    leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
    static = tuple((type(x), x) for x in leaves if not isinstance(x, (jax.Array, np.ndarray, np.generic)))
    memo = (treedef, static)
    try:
        hash(memo)
    except TypeError:
        return None
    return memo


def compile_ahead(jobs) -> None:
    """Compile several one-shot programs before they are called, at the same time on as many
    threads as there are cores.

    XLA compiles one program on one core: the Whipple bicycle's linearisation, split into its
    kinematics, its dynamics and its checks (`jaxnh._linearize`), compiles in about the time of
    its largest part on two cores instead of the sum. `jobs`: `(one_shot_fn, args, kwargs)` with
    functions from `one_shot_jit`; arguments that are not known yet (outputs of an earlier job)
    may be stand-in arrays of their shapes and dtypes (which the calls must then pass as NumPy
    arrays too: an exported program's outputs are committed to a device, and JAX compiles anew for
    committed inputs). Each program is lowered here, in order (tracing is Python, on this thread),
    and compiled on a thread pool as soon as it is; the compiled programs land in JAX's caches (in
    memory, and the persistent cache when it is on), where the calls that follow find them. A job
    that cannot be lowered or compiled is skipped: its call reports the problem.
    """
    import concurrent.futures

    def compile_one(low):
        try:
            low.compile()
        except Exception:  # noqa: BLE001 - the call itself raises, with its own message
            pass

    # each program goes to the pool as soon as it is lowered: XLA compiles the first while Python
    # traces the next (a shipped program needs no tracing, and is lowered in a fraction of a second)
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, min(len(jobs), os.cpu_count() or 1))) as pool:
        for fn, args, kwargs in jobs:
            try:
                low = fn.lower(*args, **(kwargs or {}))
            except Exception:  # noqa: BLE001 - the call itself raises, with its own message
                continue
            if low is not None:
                pool.submit(compile_one, low)


def exported_call(
    fn: Callable,
    args: tuple,
    kwargs: Optional[dict] = None,
    *,
    name: str,
    compiler_options: Optional[dict] = None,
    mech_args: Optional[tuple] = None,
    memo: Any = None,
):
    """`fn(*args, **kwargs)` through an exported program kept on disk (or shipped), or None when
    that does not apply (the caller then runs its ordinary compiled path). `fn` must be a
    module-level jaxnh function; `args`, `kwargs` any pytrees of arrays and static data;
    `compiler_options` are XLA's (e.g. `ONE_SHOT`). With `mech_args=(q, qd, t, params)`, a
    `Mechanism` among the arguments is identified by the jaxprs of its functions at those
    (`_mechanism_fingerprint`), so that programs of users' own mechanisms are kept too. `memo`:
    a hashable stand-in for the static arguments (the caller's own cache key), which spares
    fingerprinting them again on later calls in this process."""
    resolved = _exported_program(
        fn, args, kwargs, name=name, compiler_options=compiler_options, mech_args=mech_args, memo=memo
    )
    if resolved is None:
        return None
    program, inputs, lapack_free = resolved
    if lapack_free:
        with _lapack_left_alone():  # the first call lowers the program
            return program(*inputs)
    return program(*inputs)


def _exported_program(fn: Callable, args: tuple, kwargs: Optional[dict] = None, *, name: str, **options):
    """`exported_call`'s program for these arguments (and its keyword `options`): `(program, inputs, lapack_free)`, with
    `program(*inputs)` the call (a jitted call of the exported program), and `lapack_free` True
    when it is met for the first time in this process and calls no LAPACK kernel; or None when
    no exported program applies."""
    global _MECH_ARGS
    compiler_options, mech_args, memo = options.get("compiler_options"), options.get("mech_args"), options.get("memo")
    call_args = (args, {} if kwargs is None else kwargs)
    leaves, treedef = jax.tree_util.tree_flatten(call_args)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return None  # under a transformation: the caller's program
    # Python numbers and other non-array leaves are baked in (and part of the key); arrays and NumPy
    # scalars are inputs (as jax.jit treats them), which a `memo`ised call must see, value by value
    dynamic = [isinstance(x, (jax.Array, np.ndarray, np.generic)) for x in leaves]
    memo_key = key = None
    if memo is not None:
        avals = tuple(
            (x.shape, x.dtype, getattr(x, "weak_type", False)) if d else None for x, d in zip(leaves, dynamic)
        )
        memo_key = (name, memo, treedef, avals)
        fast = _FAST.get(memo_key)
        if fast is not None:  # a later call in this process: straight to the compiled program
            return fast, [x for x, d in zip(leaves, dynamic) if d], False
    folder = _folder()
    if folder is None and not _shipped_readable():
        return None
    if memo_key is not None:
        key = _KEYS.get(memo_key)
    if key is None:
        try:
            _MECH_ARGS = mech_args
            fp = (_fingerprint(fn), _fingerprint(call_args))
        except _Unstable as e:
            if os.environ.get("JAXNH_DEBUG_EXPORT"):
                print(f"jaxnh export: {name} not kept: {e}")
            if memo_key is not None:
                _KEYS[memo_key] = ""
            return None
        finally:
            _MECH_ARGS = None
        key_text = repr((name, fp, _versions(), jax.default_backend(), _source_digest(), dynamic, compiler_options))
        key = hashlib.sha256(key_text.encode()).hexdigest()[:40]
        if memo_key is not None:
            _KEYS[memo_key] = key
    if key == "" or key in _REFUSED:
        return None
    inputs = [x for x, d in zip(leaves, dynamic) if d]
    call = _MEMO.get(key)
    if call is None:
        file = f"{name}-{key}.bin"
        exp = None
        if not _BUILDING:
            for where in (folder, SHIPPED if _shipped_readable() else None):
                exp = None if where is None else _load(os.path.join(where, file))
                if exp is not None:
                    break
        target = SHIPPED if _BUILDING else folder
        if exp is None and target is None:
            return None  # nothing found, and nowhere to keep it: the ordinary path
        if exp is None:
            static = [None if d else x for x, d in zip(leaves, dynamic)]

            def flat(*xs):
                it = iter(xs)
                full = [next(it) if d else s for d, s in zip(dynamic, static)]
                a, kw = jax.tree_util.tree_unflatten(treedef, full)
                return fn(*a, **kw)

            try:
                exp = jax.export.export(jax.jit(flat))(*(jax.ShapeDtypeStruct(np.shape(x), x.dtype) for x in inputs))
            except Exception as e:  # noqa: BLE001 - not exportable (host callbacks, ...): the ordinary path
                if os.environ.get("JAXNH_DEBUG_EXPORT"):
                    print("jaxnh export refused:", type(e).__name__, str(e)[:2000])
                _REFUSED.add(key)
                return None
            if target is not None:
                try:
                    data = exp.serialize()
                except Exception as e:  # noqa: BLE001 - e.g. an output type without serialization:
                    # not kept on disk, but this process uses the traced program (no second trace)
                    if os.environ.get("JAXNH_DEBUG_EXPORT"):
                        print(f"jaxnh export: {name} not serialisable:", type(e).__name__, str(e)[:500])
                else:
                    _save(os.path.join(target, file), data)
        # a jitted call (JAX's fast dispatch on later calls; compiled on the first, from the
        # persistent cache when it is there)
        call = jax.jit(exp.call, compiler_options=compiler_options)
        _MEMO[key] = call
        if memo_key is not None:
            _FAST[memo_key] = call
        return call, inputs, _calls_no_lapack(exp)
    if memo_key is not None:
        _FAST[memo_key] = call
    return call, inputs, False


def _calls_no_lapack(exp) -> bool:
    """Whether an exported program calls no LAPACK kernel: custom-call targets are named in its
    serialized module ("lapack_dpotrf_ffi", ...). Any occurrence of the word counts, also in a
    source location, so a doubtful case is taken to call one (and is set up as usual)."""
    try:
        return b"lapack" not in bytes(exp.mlir_module_serialized)
    except Exception:  # noqa: BLE001
        return False


@contextlib.contextmanager
def _lapack_left_alone():
    """Lowering a call of an exported program on CPU first initialises JAX's LAPACK kernels,
    which imports SciPy's LAPACK bindings (0.15 s of a warm first answer of 1 s, measured with
    cProfile). A program that calls no LAPACK kernel does not need them: this skips that step
    while such a program is lowered. JAX's private hook is looked up defensively: if it is not
    there (another JAX version), nothing is changed."""
    try:
        from jax._src.export import _export as internal

        original = internal._ensure_backends_initialized
    except (ImportError, AttributeError):
        yield
        return
    internal._ensure_backends_initialized = lambda platforms: None
    try:
        yield
    finally:
        internal._ensure_backends_initialized = original


def _shipped_readable() -> bool:
    """Shipped programs are read unless the user turned the cache off (`JAXNH_CACHE_DIR=off`)."""
    from . import _cache

    return _BUILDING or _cache.cache_dir() is not None


def _load(path: str):
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return None
    try:
        return jax.export.deserialize(bytearray(data))
    except Exception:  # noqa: BLE001 - a damaged or foreign file: rebuilt and overwritten
        return None


def _save(path: str, data) -> None:
    folder = os.path.dirname(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".bin")
        with os.fdopen(fd, "wb") as f:
            f.write(bytes(data))
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only or full disk: the program is used in this process only


# --- the programs shipped with the package ------------------------------------------------


def _bicycle_job() -> None:
    from .models import bicycle

    jax.block_until_ready(bicycle.linear_lean_steer(5.0))


def _fit_job() -> None:
    import contextlib
    import io

    from .cli import main

    with tempfile.TemporaryDirectory() as out, contextlib.redirect_stdout(io.StringIO()):
        main(["fit", "--quiet", "--out", out])


SHIPPED_JOBS: dict = {
    "bicycle": (_bicycle_job, "models.bicycle.linear_lean_steer(5.0): the linearisation and its check"),
    "fit": (_fit_job, "`jaxnh fit` on the embedded record: starting guess, residual Jacobian, error bands"),
}
"""What `build_shipped` runs: every exportable program these jobs meet is written to `SHIPPED`."""

MANIFEST = "MANIFEST.json"


def manifest() -> dict:
    """What the shipped programs were built from: jaxnh's source digest, the versions of the
    JAX stack, the backend, and the files ({} when none are shipped)."""
    import json

    try:
        with open(os.path.join(SHIPPED, MANIFEST)) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def build_shipped() -> dict:
    """Rebuild `SHIPPED`: remove its programs, run `SHIPPED_JOBS` with every exported program
    written there (and none read from anywhere), write the manifest, and return it. Run after
    any change to jaxnh's sources (`make programs`); `tests/test_export.py` checks that the
    manifest matches the sources."""
    import json

    global _BUILDING
    os.makedirs(SHIPPED, exist_ok=True)
    for f in os.listdir(SHIPPED):
        if f.endswith(".bin"):
            os.remove(os.path.join(SHIPPED, f))
    _MEMO.clear()
    _REFUSED.clear()
    _KEYS.clear()
    _FAST.clear()
    _BUILDING = True
    try:
        for job, _ in SHIPPED_JOBS.values():
            job()
    finally:
        _BUILDING = False
    info = {
        "source_digest": _source_digest(),
        "versions": _versions(),
        "backend": jax.default_backend(),
        "x64": bool(jax.config.jax_enable_x64),  # pyright: ignore[reportAttributeAccessIssue]
        "jobs": {name: text for name, (_, text) in SHIPPED_JOBS.items()},
        "files": sorted(f for f in os.listdir(SHIPPED) if f.endswith(".bin")),
    }
    with open(os.path.join(SHIPPED, MANIFEST), "w") as f:
        json.dump(info, f, indent=1)
        f.write("\n")
    return info


def main() -> None:
    """`make programs`: rebuild the shipped programs and say what was written."""
    import jaxnh  # noqa: F401  (64-bit mode, the compilation cache)

    built = build_shipped()
    size = sum(os.path.getsize(os.path.join(SHIPPED, f)) for f in built["files"])
    print(f"jaxnh: {len(built['files'])} programs ({size / 1e6:.1f} MB) written to {SHIPPED}")
    for f in built["files"]:
        print("  ", f)
