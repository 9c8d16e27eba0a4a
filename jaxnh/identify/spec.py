"""`FitSpec`: what `jaxnh fit --model module:function` needs to fit a user's own mechanism.

The contract. `--model pkg.module:function` (an importable module) or
`--model path/to/file.py:function` names a function taking no arguments that
returns a `FitSpec` (or a dict with the same keys):

    import jax.numpy as jnp
    import jaxnh as nh
    from jaxnh.identify.spec import FitSpec
    from jaxnh._model.profiles import Sampled

    def cart():
        def T(q, qd, t, p):                    # J
            return 0.5 * p["m"] * qd[0] ** 2
        def force(q, qd, t, p):                # N
            return jnp.stack([p["F"](t) - p["c"] * qd[0]])
        mech = nh.Mechanism(T, forces=force, names=("x",))
        return FitSpec(
            mechanism=mech,
            params=lambda record: {"m": 1.0, "c": 0.1, "F": Sampled(record.t, record.inputs["F"])},
            free=("m", "c"), positive=("m", "c"),
            observed=("x",), inputs=("F",))

Fields:
    mechanism: the `jaxnh.Mechanism` (its coordinate names are the CSV
        columns of the measured coordinates).
    params: the starting params pytree (the free parameters' values are the
        starting guess, everything else stays fixed), or a function
        `params(record) -> pytree` to put measured inputs into it (e.g. as
        `jaxnh.profiles.Sampled(record.t, record.inputs["F"])`).
    free: names (paths) of the parameters to estimate.
    positive: the subset of `free` estimated as logarithms (kept > 0).
    observed: the measured coordinates, CSV columns named like the
        mechanism's coordinates (default: all of them); `--observe` picks a subset.
    inputs: CSV columns of applied inputs (units of the model), read into
        `record.inputs`.
    q0, qd0: optional starting guesses of the initial state (s,).
    options: further keyword arguments for `jaxnh.fit` (e.g. `method`,
        `rtol`, `noise`); the command line's `--noise`, `--shooting` and
        `--max-iterations` take precedence.

The CSV needs a column `t` (s), the observed columns and the inputs.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import sys
import traceback
from typing import Any, Callable, Optional, Sequence, Union

import equinox as eqx

from jaxnh._model.mechanism import Mechanism


__all__ = ["FitSpec", "load_model", "ModelError"]


class ModelError(ValueError):
    """`--model module:function` could not be loaded or did not keep the contract."""


@dataclasses.dataclass
class FitSpec:
    """A user's mechanism as `jaxnh fit --model module:function` fits it (see the module docstring)."""

    mechanism: Any
    params: Union[Any, Callable[[Any], Any]]
    free: Sequence[str]
    positive: Sequence[str] = ()
    observed: Optional[Sequence[str]] = None
    inputs: Sequence[str] = ()
    q0: Any = None
    qd0: Any = None
    options: dict = dataclasses.field(default_factory=dict)

    def params_for(self, record: Any) -> Any:
        """The starting params for `record` (calls `params(record)` when it is a function)."""
        p = self.params
        if callable(p) and not isinstance(p, (dict, list, tuple)) and not _is_pytree_module(p):
            return p(record)
        return p


def _is_pytree_module(x) -> bool:
    try:
        return isinstance(x, eqx.Module)
    except ImportError:  # pragma: no cover
        return False


def _names(x, what: str) -> tuple:
    if x is None:
        return ()
    if isinstance(x, str):
        x = (x,)
    try:
        x = tuple(x)
    except TypeError:
        raise ModelError(f"{what} must be a sequence of names; got {type(x).__name__}") from None
    bad = [v for v in x if not isinstance(v, str) or not v]
    if bad:
        raise ModelError(f"{what} must be non-empty strings; got {bad!r}")
    return x


def _where_in_user_code(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    here = os.path.dirname(os.path.abspath(__file__))
    user = [f for f in tb if not os.path.abspath(f.filename).startswith(here)]
    if not user:
        return ""
    f = user[-1]
    return f" (at {f.filename}:{f.lineno})"


def _import(module: str, ref: str):
    if module.endswith(".py") or os.sep in module or (os.altsep and os.altsep in module):
        path = os.path.abspath(module)
        if not os.path.isfile(path):
            raise ModelError(f"--model {ref}: no file {module}")
        name = "_jaxnh_user_model_" + os.path.splitext(os.path.basename(path))[0] + f"_{abs(hash(path)):x}"
        mtime = os.stat(path).st_mtime_ns
        old = sys.modules.get(name)
        if old is not None and getattr(old, "__jaxnh_mtime__", None) == mtime:
            return old  # unchanged file: the same functions, so compiled programs are reused
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise ModelError(f"--model {ref}: cannot load {module} as Python")
        mod = importlib.util.module_from_spec(spec)
        setattr(mod, "__jaxnh_mtime__", mtime)
        sys.modules[name] = mod
        try:
            spec.loader.exec_module(mod)
        except Exception as e:
            sys.modules.pop(name, None)
            raise ModelError(
                f"--model {ref}: importing {module} raised {type(e).__name__}: {e}{_where_in_user_code(e)}"
            ) from None
        return mod
    added = os.getcwd() not in sys.path
    if added:
        sys.path.insert(0, os.getcwd())  # like `python -m`: modules in the current folder
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and module.startswith(e.name):
            raise ModelError(
                f"--model {ref}: no module named {e.name!r} (give an importable module, or a "
                "file: --model path/to/file.py:function)"
            ) from None
        raise ModelError(
            f"--model {ref}: importing {module} raised {type(e).__name__}: {e}{_where_in_user_code(e)}"
        ) from None
    except Exception as e:
        raise ModelError(
            f"--model {ref}: importing {module} raised {type(e).__name__}: {e}{_where_in_user_code(e)}"
        ) from None
    finally:
        if added:
            try:
                sys.path.remove(os.getcwd())
            except ValueError:
                pass


def load_model(ref: str) -> FitSpec:
    """Import `module:function` (or `file.py:function`), call the function and
    check the `FitSpec` it returns. Raises `ModelError` (a ValueError) naming
    what is wrong."""
    if not isinstance(ref, str) or ":" not in ref:
        raise ModelError(f"--model {ref}: expected 'variator' or 'module:function' (or 'file.py:function')")
    module, _, func = ref.rpartition(":")
    if not module or not func or not func.isidentifier():
        raise ModelError(f"--model {ref}: expected 'module:function' with a function name after the colon")
    mod = _import(module, ref)
    fn = getattr(mod, func, None)
    if fn is None:
        raise ModelError(f"--model {ref}: {module} has no attribute {func!r}")
    if not callable(fn):
        raise ModelError(f"--model {ref}: {func} is a {type(fn).__name__}, not a function")
    try:
        spec = fn()
    except Exception as e:
        raise ModelError(
            f"--model {ref}: calling {func}() raised {type(e).__name__}: {e}{_where_in_user_code(e)}"
        ) from None
    if isinstance(spec, dict):
        unknown = set(spec) - {f.name for f in dataclasses.fields(FitSpec)}
        if unknown:
            raise ModelError(
                f"--model {ref}: {func}() returned a dict with unknown key(s) {sorted(unknown)}; "
                f"keys are {[f.name for f in dataclasses.fields(FitSpec)]}"
            )
        try:
            spec = FitSpec(**spec)
        except TypeError as e:
            raise ModelError(f"--model {ref}: {func}() returned a dict that is not a FitSpec: {e}") from None
    if not isinstance(spec, FitSpec):
        raise ModelError(
            f"--model {ref}: {func}() must return a jaxnh.identify.spec.FitSpec (or a dict with its "
            f"keys); got {type(spec).__name__}"
        )
    if not isinstance(spec.mechanism, Mechanism):
        raise ModelError(
            f"--model {ref}: FitSpec.mechanism must be a jaxnh.Mechanism; got {type(spec.mechanism).__name__}"
        )
    if spec.mechanism.names is None:
        raise ModelError(
            f"--model {ref}: the mechanism needs coordinate names (Mechanism(..., names=(...))): "
            "they are the CSV columns of the measured coordinates"
        )
    names = tuple(spec.mechanism.names)
    spec.free = _names(spec.free, f"--model {ref}: FitSpec.free")
    if not spec.free:
        raise ModelError(f"--model {ref}: FitSpec.free names no parameter to estimate")
    spec.positive = _names(spec.positive, f"--model {ref}: FitSpec.positive")
    extra = [p for p in spec.positive if p not in spec.free]
    if extra:
        raise ModelError(f"--model {ref}: FitSpec.positive names {extra}, which are not in free {list(spec.free)}")
    observed = _names(spec.observed, f"--model {ref}: FitSpec.observed") if spec.observed is not None else names
    bad = [c for c in observed if c not in names]
    if bad or not observed:
        raise ModelError(
            f"--model {ref}: FitSpec.observed must name coordinates of the mechanism {list(names)}; "
            f"got {list(observed)}"
        )
    spec.observed = observed
    spec.inputs = _names(spec.inputs, f"--model {ref}: FitSpec.inputs")
    clash = [c for c in spec.inputs if c in names or c == "t"]
    if clash:
        raise ModelError(f"--model {ref}: FitSpec.inputs {clash} clash with the time column or coordinate names")
    if not isinstance(spec.options, dict):
        raise ModelError(f"--model {ref}: FitSpec.options must be a dict of keyword arguments for jaxnh.fit")
    return spec
