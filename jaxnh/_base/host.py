"""Host-side arithmetic without compiling: the array module for concrete inputs,
and the conversion of user input (coordinates, times, parameters) to arrays.

A few operations on concrete arrays (packing the starting parameters, a noise
estimate) compile one small XLA program per operation when done with
`jax.numpy` outside `jit`, a few tens of milliseconds each the first time. The
same code with `numpy` costs microseconds; under a transformation (a tracer among
the inputs) it must stay `jax.numpy`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._base.status import is_traced


def array_module(*trees):
    """`jax.numpy` if any leaf of `trees` is a JAX tracer (inside jit, vmap, grad), else `numpy`."""
    return jnp if is_traced(*trees) else np


def as_float(x):
    """`x` as an array of a floating dtype (the default float for integer input)."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def as_data(params, like):
    """`params` with its Python `float` leaves as arrays of the floating dtype of `like`.

    jaxnh compiles once per structure of the parameters, not per value: a
    Python float would otherwise be a compile-time constant (equinox treats
    non-array leaves as static), so every new value, e.g. in a loop over J2,
    would compile a new program. Other leaves (arrays, ints, bools, strings,
    callables) are left as they are.
    """
    if not any(type(x) is float for x in jax.tree_util.tree_leaves(params)):
        return params  # (the common case, checked first: simulate's per-call cost)
    dtype = jnp.result_type(like, jnp.float32)
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype=dtype) if type(x) is float else x, params)


def as_time(t, like):
    """Time as a scalar array with the floating dtype of `like`."""
    return jnp.asarray(t, dtype=jnp.result_type(like, jnp.float32))
