"""Which parameters a fit changes, and the unconstrained vector it works in.

The estimator sees one flat vector θ. Each free parameter (named by its path
in the params pytree: "J1", "U21", "U21.values", or a dict key) contributes
its trainable leaves (`jaxnh.profiles.trainable`: a spline's values, not its
knot times). Parameters declared positive enter θ as logarithms, so every θ
maps to a physically admissible model and standard errors of log-parameters
are relative errors.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxnh._base.host import array_module
from jaxnh._model.profiles import trainable


__all__ = ["Parametrisation", "resolve"]


def resolve(tree, name: str):
    """The sub-tree of `tree` at the dotted path `name` (attributes or dict keys)."""
    node = tree
    for part in name.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif not isinstance(node, dict) and hasattr(node, part):
            node = getattr(node, part)
        else:
            have = (
                list(node)
                if isinstance(node, dict)
                else [f for f in getattr(node, "__dataclass_fields__", {}) if not f.startswith("_")]
            )
            raise ValueError(f"free/positive: no parameter {name!r} (at {part!r}); available: {have}")
    return node


def _where(name: str):
    parts = name.split(".")

    def get(tree):
        node = tree
        for part in parts:
            node = node[part] if isinstance(node, dict) else getattr(node, part)
        return node

    return get


class Parametrisation(eqx.Module):
    """Map between a params pytree and the estimator's flat vector θ.

    Attributes:
        params: the starting params (its non-free leaves are the fixed values).
        names: the free parameter paths, in the order they appear in θ.
        sizes: number of entries each contributes.
        positive: for each free name, whether it enters θ as a logarithm.
        labels: one label per entry of θ ("J1", "U21[3]").
    """

    params: Any
    names: tuple = eqx.field(static=True)
    sizes: tuple = eqx.field(static=True)
    shapes: tuple = eqx.field(static=True)
    positive: tuple = eqx.field(static=True)
    labels: tuple = eqx.field(static=True)

    def __init__(self, params, free: Sequence[str], positive: Sequence[str] = ()):
        free = (free,) if isinstance(free, str) else tuple(free)
        positive = (positive,) if isinstance(positive, str) else tuple(positive)
        if not free:
            raise ValueError("free: name at least one parameter to estimate, e.g. free=('J1', 'J2')")
        if len(set(free)) != len(free):
            raise ValueError(f"free: repeated names in {free}")
        for a in free:
            for b in free:
                if a != b and b.startswith(a + "."):
                    raise ValueError(f"free: {a!r} already contains {b!r}; name one of them")
        unknown = [p for p in positive if p not in free]
        if unknown:
            raise ValueError(f"positive={positive}: {unknown} not among free={free}")
        sizes, shapes, labels = [], [], []
        for name in free:
            sub = resolve(params, name)
            if isinstance(sub, (int, float)):
                sub = jnp.asarray(sub, dtype=jnp.result_type(float))
                params = eqx.tree_at(_where(name), params, sub)
            leaves = self._leaves(sub, name)
            if not leaves:
                raise ValueError(f"free: parameter {name!r} has no trainable array leaves (got {type(sub).__name__})")
            shapes.append(tuple(tuple(np.shape(x)) for x in leaves))
            n = sum(math.prod(s) for s in shapes[-1])
            sizes.append(n)
            if name in positive:
                vals = np.concatenate([np.ravel(np.asarray(x)) for x in leaves])
                if not np.all(vals > 0):
                    raise ValueError(f"positive parameter {name!r} must be > 0 at the starting guess; got {vals}")
            labels += [name] if n == 1 and shapes[-1][0] == () else [f"{name}[{i}]" for i in range(n)]
        self.params = params
        self.names, self.sizes, self.shapes = free, tuple(sizes), tuple(shapes)
        self.positive = tuple(name in positive for name in free)
        self.labels = tuple(labels)

    @staticmethod
    def _leaves(sub, name):
        mask = trainable(sub)
        free_part, _ = eqx.partition(sub, mask)
        return jax.tree_util.tree_leaves(free_part)

    @property
    def size(self) -> int:
        """Length of θ."""
        return sum(self.sizes)

    def log_mask(self) -> np.ndarray:
        """Boolean (size,): entries of θ that are logarithms."""
        return np.concatenate([np.full(n, p) for n, p in zip(self.sizes, self.positive)])

    def pack(self, params=None):
        """θ (size,) from a params pytree (default: the starting params)."""
        params = self.params if params is None else params
        xp = array_module(params)  # NumPy for concrete params: nothing to compile
        parts = []
        for name, pos in zip(self.names, self.positive):
            v = xp.concatenate([xp.ravel(x) for x in self._leaves(resolve(params, name), name)])
            parts.append(xp.log(v) if pos else v)
        return xp.concatenate(parts)

    def natural(self, theta):
        """The free values themselves (exp of the log entries), (size,)."""
        log = jnp.asarray(self.log_mask())
        return jnp.where(log, jnp.exp(jnp.where(log, theta, 0.0)), theta)

    def unpack(self, theta):
        """The params pytree with the free leaves set from θ (size,)."""
        params = self.params
        values = self.natural(theta)
        start = 0
        for name, n, shapes in zip(self.names, self.sizes, self.shapes):
            chunk = values[start : start + n]
            start += n
            sub = resolve(params, name)
            mask = trainable(sub)
            free_part, rest = eqx.partition(sub, mask)
            leaves, treedef = jax.tree_util.tree_flatten(free_part)
            new, k = [], 0
            for leaf, shape in zip(leaves, shapes):
                m = math.prod(shape)
                new.append(chunk[k : k + m].reshape(shape).astype(jnp.result_type(leaf)))
                k += m
            sub = eqx.combine(jax.tree_util.tree_unflatten(treedef, new), rest)
            params = eqx.tree_at(_where(name), params, sub)
        return params

    def slices(self) -> dict:
        """Name → slice of θ."""
        out, start = {}, 0
        for name, n in zip(self.names, self.sizes):
            out[name] = slice(start, start + n)
            start += n
        return out
