"""Host-side arithmetic without compiling: the array module for concrete inputs.

A few operations on concrete arrays (packing the starting parameters, a noise
estimate) compile one small XLA program per operation when done with
`jax.numpy` outside `jit`, a few tens of milliseconds each the first time. The
same code with `numpy` costs microseconds; under a transformation (a tracer among
the inputs) it must stay `jax.numpy`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxnh._base.status import is_traced


def array_module(*trees):
    """`jax.numpy` if any leaf of `trees` is a JAX tracer (inside jit, vmap, grad), else `numpy`."""
    return jnp if is_traced(*trees) else np
