"""Type aliases of the public signatures (for type checkers and the API reference)."""

from __future__ import annotations

from typing import Any, Sequence, Union

from jax.typing import ArrayLike


__all__ = ["PyTree", "ArrayInput"]

PyTree = Any
"""A pytree (nested tuples, lists, dicts, equinox modules) of arrays and other leaves, such as the
parameters of a mechanism; JAX gives pytrees no finer static type."""

ArrayInput = Union[ArrayLike, Sequence[Any]]
"""An array, a number, or a (nested) list or tuple of numbers: what `jnp.asarray` accepts."""
