"""Helpers shared by the solves of `simulate` (plain and with friction contacts) for their inputs
and outputs: finiteness checks, NaN derivatives for failed solves, stopped gradients, masks."""

from __future__ import annotations

from typing import Callable, TypeVar

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp

from jaxnh._base.compat import status_code


__all__ = ["all_finite", "nan_link", "input_sum", "no_grad", "bcast", "run_checked"]

_S = TypeVar("_S")


def run_checked(run: Callable[[bool], _S], traced: bool, throw: bool) -> tuple[_S, bool]:
    """`run(graph_throw)`, the compiled part of a solve, and whether its outputs are traced.

    A failure raises from inside the program (`graph_throw`) when `throw` and the solve is
    traced. Traced inputs say so before the run; a call whose inputs are all concrete but which
    sits inside a caller's jit (everything closed over) shows it only by its traced outputs:
    it is then traced again with the raise (only tracing is repeated, the first program is
    unused and pruned).
    """
    out = run(throw and traced)
    if not traced and isinstance(status_code(out.status), jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
        traced = True
        if throw:
            out = run(True)
    return out, traced


def all_finite(tree):
    """Whether every floating array leaf of `tree` is finite (a traced bool)."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree) if eqx.is_inexact_array(x)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


@jax.custom_jvp
def nan_link(bad, total):
    """0, whose derivative with respect to `total` is NaN when `bad` is True (else 0).

    Added to every output with `total` a sum over the inputs: a failed solve or
    non-finite input then has NaN derivatives with respect to every input, in
    forward and reverse mode, while its values are left as they are (a mask
    on the outputs alone would hide the NaN from reverse mode).
    """
    return _zero_like_both(bad, total)


def _zero_like_both(bad, total):
    # batched like either argument, so the primal and its tangent batch alike under vmap
    return jnp.where(bad, 0.0, 0.0).astype(total.dtype) + jnp.zeros_like(total)


@nan_link.defjvp
def _nan_link_jvp(primals, tangents):
    bad, total = primals
    _, dtotal = tangents
    return _zero_like_both(bad, total), dtotal * jnp.where(bad, jnp.nan, 0.0).astype(total.dtype)


def input_sum(tree):
    """The sum of every floating array leaf of `tree` (the `total` of `nan_link`)."""
    leaves = [jnp.sum(x) for x in jax.tree_util.tree_leaves(tree) if eqx.is_inexact_array(x)]
    return sum(leaves[1:], leaves[0]) if leaves else jnp.zeros(())


def no_grad(tree):
    """`tree` with `stop_gradient` on its array leaves (other leaves as they are)."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree)


def bcast(mask, x):
    """`mask` with trailing axes of length 1 so that it broadcasts against `x`."""
    return mask.reshape(mask.shape + (1,) * (x.ndim - mask.ndim))
