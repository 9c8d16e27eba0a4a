"""How jaxnh compiles its programs.

`lean_jit` compiles a solve (`simulate`) as `equinox.filter_jit` would, with a dispatch light
enough for a simulation that runs in a millisecond, and with XLA's options `SOLVE` when it is
called with concrete arguments.

jaxnh's other programs around solves (a design step's gradient, a fit's reverse-mode gradient,
an experiment's Jacobian, a sweep's chunk) are `solve_jit`: `equinox.filter_jit` with the same
options `SOLVE` when they are the outermost program.

A linearisation, a fit's starting guess or its error bands run a handful of times for each
structure of their arguments: for them XLA's compile time, not the run time, is the cost. Called
with concrete arguments they are compiled with `ONE_SHOT`, XLA's cheapest settings (compiler
options are public arguments of `jax.jit`). Under a transformation (`vmap`, `grad`, a caller's
`jit`) all of them are the ordinary `equinox.filter_jit`, because JAX accepts compiler options
only on the outermost program. So a user's own `jax.grad(loss)(params)` around `simulate`
compiles with XLA's defaults; `jax.jit(jax.grad(loss), compiler_options=jaxnh.COMPILER_OPTIONS)`
gives it the options.
"""

from __future__ import annotations

import functools
from typing import Callable, Optional, TypeVar

import equinox as eqx
import jax
import jax.core
import numpy as np


__all__ = ["COMPILER_OPTIONS", "lean_jit", "ONE_SHOT", "one_shot_jit", "SOLVE", "solve_jit"]

SOLVE = {"xla_cpu_use_fusion_emitters": False}
"""XLA options for a solve called with concrete arguments: XLA's CPU back end then emits its
small elementwise fusions the classic way rather than each through its newer fusion emitters,
which compile one kernel per fusion. Measured (jaxlib 0.10.2, 2-core AMD EPYC, one core,
CPU time of the first `simulate` after the import, then per solve): the variator 4.8 s -> 3.9 s
(827 -> 802 us per solve), a car with 2 trailers 9.5 s -> 6.6 s (6.0 -> 5.1 ms), with 16
trailers 12.5 s -> 8.1 s (44 ms both). An XLA that no longer knows the option compiles with its
defaults (`lean_jit`)."""

COMPILER_OPTIONS = SOLVE
"""XLA's options jaxnh compiles its own solves with (`simulate`, sweeps, design steps), for a
program of yours around `simulate`: `jax.jit(jax.grad(loss), compiler_options=COMPILER_OPTIONS)`.
JAX takes compiler options only on the outermost program, so a `simulate` inside your `jax.jit`,
or under an eager `jax.grad`, is compiled with XLA's defaults unless your outermost `jax.jit` passes
them. Measured (2-core AMD EPYC, one core, fresh process, CPU time after the import): the
first gradient of a car with 4 trailers (27 parameters) took 32.5 s with `jax.grad` and 20.2 s with
`jax.jit(jax.grad(...), compiler_options=COMPILER_OPTIONS)`. They are options of XLA's CPU back end;
other back ends ignore them."""

ONE_SHOT = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""XLA options for programs evaluated a handful of times (a linearisation). Measured on the
Whipple bicycle's linearisation (24k StableHLO operations, 2-core CPU, jaxlib 0.10.2): XLA's
default settings compile it in 8.8 s and run it in 0.9 ms; these options in 3.1–4.3 s / 0.8–1.6 ms.
(`xla_cpu_*` options are ignored by other backends.)"""

_F = TypeVar("_F", bound=Callable)


def _traced(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _outermost_jit(fn: _F, compiler_options: dict) -> _F:
    """`equinox.filter_jit(fn)`, compiled with XLA's `compiler_options` when it is the outermost
    program: called with concrete arguments outside any jit. Under a transformation (traced
    arguments), or with concrete arguments closed over inside a caller's jit (JAX refuses options
    there, before compiling anything), it is the plain `equinox.filter_jit`; an XLA that no longer
    knows one of the options compiles with its defaults."""
    # (equinox's type hints of filter_jit leave out the keyword arguments it passes on to jax.jit)
    programs = [eqx.filter_jit(fn, compiler_options=compiler_options), eqx.filter_jit(fn)]  # pyright: ignore[reportCallIssue]

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if _traced((args, kwargs)):
            return programs[-1](*args, **kwargs)
        return _with_options(programs, *args, **kwargs)

    return call  # pyright: ignore[reportReturnType]


def _with_options(programs: list, *args, **kwargs):
    """`programs[0](*args, **kwargs)`, the program compiled with XLA's options, or the last program
    (the same one without them) where JAX or XLA refuses the options: inside a caller's jit, when
    the arguments are concrete but closed over (JAX refuses options on a nested program before
    anything is compiled), or when XLA no longer knows one of the options (they are XLA's debug
    options, not promised to last); `programs[0]` is then dropped for good."""
    try:
        return programs[0](*args, **kwargs)
    except ValueError as err:
        if len(programs) == 1 or "compiler_options" not in str(err):
            raise
        return programs[-1](*args, **kwargs)
    except jax.errors.JaxRuntimeError as err:
        if len(programs) == 1 or "No such compile option" not in str(err):
            raise
        del programs[0]
        return programs[0](*args, **kwargs)


def one_shot_jit(fn: _F) -> _F:
    """`equinox.filter_jit(fn)`, compiled with `ONE_SHOT` when it is the outermost program."""
    return _outermost_jit(fn, ONE_SHOT)


def solve_jit(fn: _F) -> _F:
    """`equinox.filter_jit(fn)`, compiled with `SOLVE` when it is the outermost program: for
    jaxnh's own programs around solves, whose compile time the options cut as they cut
    `simulate`'s. Measured (2-core AMD EPYC, one core, fresh processes, CPU time after the
    import): `jaxnh.design.optimize` for 2 steps on a car with 2 trailers, 29.0 s -> 12.9 s
    (reverse mode) and 26.8 s -> 11.4 s (forward); `jaxnh.sweep` of the variator over 512 inertias,
    6.6–7.1 s -> 3.8–4.9 s for the first sweep and 11–14 ms -> 7.2–7.6 ms for the next ones.
    Errors raised inside (a loss whose `simulate` throws) read as `equinox.filter_jit` makes them."""
    return _outermost_jit(fn, SOLVE)


_ARRAY = (jax.Array, np.ndarray, np.generic)  # equinox.is_array's kinds: traced; every other leaf is static


class _Static:
    """The static part of a call: the arguments' tree structure and their non-array leaves
    (compared by value, as `equinox.filter_jit` compares them), hashed once."""

    __slots__ = ("key", "hash")

    def __init__(self, key):
        self.key = key
        self.hash = hash(key)

    def __hash__(self) -> int:
        return self.hash

    def __eq__(self, other) -> bool:
        return isinstance(other, _Static) and self.hash == other.hash and self.key == other.key


class _Mixed(eqx.Module):
    arrays: object
    rest: object = eqx.field(static=True)


def lean_jit(fn: _F, compiler_options: Optional[dict] = None) -> _F:
    """`fn` compiled as `equinox.filter_jit` compiles it (array leaves of its arguments are traced,
    every other leaf is a compile-time constant compared by value), with a lighter dispatch, and
    with XLA's `compiler_options` when called with concrete arguments (JAX takes them only for
    the outermost program).

    For a program that runs in a millisecond, `equinox.filter_jit`'s per-call work (binding the
    signature, two partitions of the arguments, a logging filter, a warnings context) costs a
    few hundred microseconds, a third of a small simulation; here a call flattens its arguments
    once and hands `jax.jit` the arrays and one hashable key. An output with leaves that are
    not arrays comes back through a static field, as equinox returns it. A call with traced
    arguments (under `vmap` or `grad`) is `equinox.filter_jit`'s, which makes an error raised
    inside the program (`equinox.error_if`) readable when it is the outermost program; a concrete
    call passes such an error on as JAX raises it (simulate's eager program raises none: it
    reports failures by status).
    """

    def body(static: _Static, arrays: list):
        treedef, fixed = static.key
        it = iter(arrays)
        args, kwargs = jax.tree_util.tree_unflatten(treedef, [next(it) if x is _ARRAY else x for x in fixed])
        out = fn(*args, **dict(kwargs))
        if all(isinstance(x, jax.Array) for x in jax.tree_util.tree_leaves(out)):
            return out  # (decided while tracing: the common case pays no partition per call)
        return _Mixed(*eqx.partition(out, eqx.is_array))

    programs = [jax.jit(body, static_argnums=0, compiler_options=compiler_options)]
    if compiler_options:
        programs.append(jax.jit(body, static_argnums=0))  # XLA's defaults, should an option be unknown

    traced_call = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        leaves, treedef = jax.tree_util.tree_flatten((args, tuple(sorted(kwargs.items()))))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            # under vmap or grad (outside a jit) equinox's wrapper is the outermost program,
            # where it turns an error raised inside into a readable one; the traced program is
            # compiled once for the whole transformation, so its dispatch cost does not count
            return traced_call(*args, **kwargs)
        arrays = [x for x in leaves if isinstance(x, _ARRAY)]
        # (the tuple _ARRAY marks an array's place: no user leaf is that object)
        fixed = tuple(_ARRAY if isinstance(x, _ARRAY) else x for x in leaves)
        out = _with_options(programs, _Static((treedef, fixed)), arrays)
        return eqx.combine(out.arrays, out.rest) if isinstance(out, _Mixed) else out

    return call  # pyright: ignore[reportReturnType]
