"""How jaxnh compiles programs that run only a few times per structure.

A linearisation, a fit's starting guess or its error bands run a handful of times for each
structure of their arguments: for them XLA's compile time, not the run time, is the cost. Called
with concrete arguments they are compiled with `ONE_SHOT`, XLA's cheapest settings (compiler
options are public arguments of `jax.jit`). Under a transformation (`vmap`, `grad`, a caller's
`jit`) they are the ordinary `equinox.filter_jit`, because JAX accepts compiler options only on
the outermost program.
"""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import equinox as eqx
import jax
import jax.core


__all__ = ["ONE_SHOT", "one_shot_jit"]

ONE_SHOT = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""XLA options for programs evaluated a handful of times (a linearisation). Measured on the
Whipple bicycle's linearisation (24k StableHLO operations, 2-core CPU, jaxlib 0.10.2): XLA's
default settings compile it in 8.8 s and run it in 0.9 ms; these options in 3.1–4.3 s / 0.8–1.6 ms.
(`xla_cpu_*` options are ignored by other backends.)"""

_F = TypeVar("_F", bound=Callable)


def _traced(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def one_shot_jit(fn: _F) -> _F:
    """`equinox.filter_jit(fn)`, compiled with `ONE_SHOT` when called with concrete arguments."""
    # (equinox's type hints of filter_jit leave out the keyword arguments it passes on to jax.jit)
    cheap = eqx.filter_jit(fn, compiler_options=ONE_SHOT)  # pyright: ignore[reportCallIssue]
    plain = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        return (plain if _traced((args, kwargs)) else cheap)(*args, **kwargs)

    return call  # pyright: ignore[reportReturnType]
