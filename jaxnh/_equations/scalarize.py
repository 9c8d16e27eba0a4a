"""Small vector fields flattened to scalar operations.

A derived vector field of a small mechanism works on tiny arrays: 2×2 mass
matrices, 1×3 constraint rows, stacks and pads made by differentiation. On the
CPU, XLA cuts such a graph into several kernels (a broadcast or reduction that
would recompute an expensive producer ends a fusion), and at this size each
kernel's launch costs as much as its arithmetic: the variator's Appell field
compiled to 8 kernels against 2 for the hand-written eq. (9).

`scalarized(f)` traces f to a jaxpr and evaluates that jaxpr again with every
array held as a NumPy object array of scalar JAX values: elementwise
primitives are applied entry by entry, shape operations (broadcast, reshape,
slice, pad, concatenate, transpose) only rearrange the entries, and
reductions and small matrix products are written out as chains of scalar
additions. What XLA receives is then one graph of scalar operations, which it
fuses like hand-written code. Every other primitive (control flow, custom
derivative rules, gathers, solves, ...) is applied to the re-assembled array
unchanged, so the result is always the same function, and its derivatives are
those of the same operations. Fields whose arrays are large are returned
unchanged: there the arithmetic dominates and scalar code would only grow the
program.

A floating-point quotient a / b is written as a · (1 / b). XLA's CPU fusion
does not copy a division into each of the places that read its result, so a
quotient used twice ends a kernel; a product is copied freely. With the
partition chosen as data, the variator's Appell field compiled to 5 kernels
with divisions and to 1 with reciprocals. The product differs from the
quotient by at most one more rounding (a relative 1.1e-16 in float64).
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore


#: largest array (entries) that is flattened; fields with a larger array are left as they are
MAX_ENTRIES = 64
#: largest number of scalar operations the flattened field may have
MAX_SCALAR_OPS = 4000

_ELEMENTWISE = {
    p.name
    for p in (
        lax.abs_p,
        lax.acos_p,
        lax.acosh_p,
        lax.add_p,
        lax.and_p,
        lax.asin_p,
        lax.asinh_p,
        lax.atan2_p,
        lax.atan_p,
        lax.atanh_p,
        lax.cbrt_p,
        lax.ceil_p,
        lax.clamp_p,
        lax.convert_element_type_p,
        lax.cos_p,
        lax.cosh_p,
        lax.div_p,
        lax.eq_p,
        lax.erf_p,
        lax.erfc_p,
        lax.exp2_p,
        lax.exp_p,
        lax.expm1_p,
        lax.floor_p,
        lax.ge_p,
        lax.gt_p,
        lax.integer_pow_p,
        lax.is_finite_p,
        lax.le_p,
        lax.log1p_p,
        lax.log_p,
        lax.logistic_p,
        lax.lt_p,
        lax.max_p,
        lax.min_p,
        lax.mul_p,
        lax.ne_p,
        lax.neg_p,
        lax.nextafter_p,
        lax.not_p,
        lax.or_p,
        lax.pow_p,
        lax.rem_p,
        lax.round_p,
        lax.rsqrt_p,
        lax.select_n_p,
        lax.sign_p,
        lax.sin_p,
        lax.sinh_p,
        lax.sqrt_p,
        lax.square_p,
        lax.sub_p,
        lax.tan_p,
        lax.tanh_p,
        lax.xor_p,
    )
} | {"add_any", "copy", "copy_p"}

_REDUCE = {"reduce_sum": lax.add, "reduce_max": lax.max, "reduce_min": lax.min, "reduce_prod": lax.mul}
_INLINE = {"pjit", "jit", "closed_call", "core_call"}


def _size(aval) -> int:
    return math.prod(getattr(aval, "shape", ()))


def _survey(jaxpr) -> tuple[int, int]:
    """(largest array, estimated scalar operations) of a jaxpr, nested calls included."""
    biggest, ops = 0, 0
    for v in list(jaxpr.invars) + list(jaxpr.constvars):
        biggest = max(biggest, _size(v.aval))
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        for v in list(eqn.outvars) + [x for x in eqn.invars if hasattr(x, "aval")]:
            biggest = max(biggest, _size(v.aval))
        if name in _INLINE:
            b, o = _survey(eqn.params["jaxpr"].jaxpr)
            biggest, ops = max(biggest, b), ops + o
        elif name == "dot_general":
            (lhs_contract, _), _ = eqn.params["dimension_numbers"]
            k = math.prod(eqn.invars[0].aval.shape[d] for d in lhs_contract)
            ops += 2 * k * _size(eqn.outvars[0].aval)
        elif name in _REDUCE:
            ops += _size(eqn.invars[0].aval)
        else:
            ops += sum(_size(v.aval) for v in eqn.outvars)
    return biggest, ops


def _entries(x, aval=None) -> np.ndarray:
    """A JAX value as an object array of its scalar entries."""
    shape = tuple(np.shape(x)) if aval is None else tuple(aval.shape)
    out = np.empty(shape, dtype=object)
    if not shape:
        out[()] = x
        return out
    n = math.prod(shape)
    if n == 0:
        return out
    if isinstance(x, np.ndarray) or np.isscalar(x):
        flat = np.asarray(x).reshape(-1)
        for i in range(n):
            out.reshape(-1)[i] = flat[i]
        return out
    flat = lax.reshape(x, (n,))
    # one split (whose derivative's transpose is one concatenation, not a pad per entry)
    parts = [lax.squeeze(part, (0,)) for part in lax.split(flat, (1,) * n)] if n > 1 else [lax.reshape(flat, ())]
    view = out.reshape(-1)
    for i, p in enumerate(parts):
        view[i] = p
    return out


def _assemble(e: np.ndarray, aval):
    """The JAX array made of an object array's scalar entries."""
    shape, dtype = tuple(aval.shape), aval.dtype
    if not shape:
        return e[()]
    n = math.prod(shape)
    if n == 0:
        return jnp.zeros(shape, dtype)
    flat = [lax.broadcast_in_dim(jnp.asarray(v, dtype), (1,), ()) for v in e.reshape(-1)]
    return lax.reshape(lax.concatenate(flat, 0), shape)


def _constant(val, aval) -> np.ndarray:
    arr = np.asarray(val, dtype=aval.dtype)
    out = np.empty(arr.shape, dtype=object)
    for idx in np.ndindex(arr.shape):
        out[idx] = arr[idx]
    return out


def _const_entries(c) -> np.ndarray:
    """A captured constant: a tracer of an enclosing trace stays symbolic, a concrete array is data."""
    if isinstance(c, jax.core.Tracer):
        return _entries(c)
    c = np.asarray(c)
    return _constant(c, c)


def _divide(a, b):
    """a / b as a · (1 / b) (see the module docstring)."""
    return lax.mul(a, lax.div(lax.full_like(b, 1), b))


def _elementwise(eqn, args):
    shape = tuple(eqn.outvars[0].aval.shape)
    args = [np.broadcast_to(a, shape) for a in args]
    out = np.empty(shape, dtype=object)
    op = eqn.primitive.bind
    if eqn.primitive is lax.div_p and jnp.issubdtype(eqn.outvars[0].aval.dtype, jnp.floating):
        op = _divide
    for idx in np.ndindex(shape):
        out[idx] = op(*(a[idx] for a in args), **eqn.params)
    return [out]


def _tree_reduce(op, xs):
    xs = list(xs)
    while len(xs) > 1:
        xs = [op(xs[i], xs[i + 1]) if i + 1 < len(xs) else xs[i] for i in range(0, len(xs), 2)]
    return xs[0]


def _reduce(op, x: np.ndarray, axes, aval_out):
    axes = tuple(axes)
    keep = [d for d in range(x.ndim) if d not in axes]
    moved = np.transpose(x, keep + list(axes)).reshape(tuple(x.shape[d] for d in keep) + (-1,))
    out = np.empty(tuple(aval_out.shape), dtype=object)
    for idx in np.ndindex(out.shape):
        out[idx] = _tree_reduce(op, moved[idx])
    return out


def _pad(x: np.ndarray, value, config) -> np.ndarray:
    for d, (lo, hi, interior) in enumerate(config):
        n = x.shape[d]
        size = n + max(n - 1, 0) * interior
        parts = []
        body = np.empty(x.shape[:d] + (size,) + x.shape[d + 1 :], dtype=object)
        body.fill(value)
        idx = [slice(None)] * x.ndim
        idx[d] = slice(0, size, interior + 1)
        body[tuple(idx)] = x
        if lo > 0:
            block = np.empty(x.shape[:d] + (lo,) + x.shape[d + 1 :], dtype=object)
            block.fill(value)
            parts.append(block)
        parts.append(body)
        if hi > 0:
            block = np.empty(x.shape[:d] + (hi,) + x.shape[d + 1 :], dtype=object)
            block.fill(value)
            parts.append(block)
        x = np.concatenate(parts, axis=d)
        cut = [slice(None)] * x.ndim
        cut[d] = slice(max(-lo, 0), x.shape[d] - max(-hi, 0))
        x = x[tuple(cut)]
    return x


def _dot_general(eqn, lhs: np.ndarray, rhs: np.ndarray):
    ((lc, rc), (lb, rb)) = eqn.params["dimension_numbers"]
    lf = [d for d in range(lhs.ndim) if d not in lc and d not in lb]
    rf = [d for d in range(rhs.ndim) if d not in rc and d not in rb]
    L = np.transpose(lhs, list(lb) + lf + list(lc))
    R = np.transpose(rhs, list(rb) + rf + list(rc))
    nb, nlf, nrf = len(lb), len(lf), len(rf)
    bshape = L.shape[:nb]
    lshape, rshape = L.shape[nb : nb + nlf], R.shape[nb : nb + nrf]
    k = math.prod(L.shape[nb + nlf :])
    L = L.reshape(bshape + lshape + (k,))
    R = R.reshape(bshape + rshape + (k,))
    out = np.empty(bshape + lshape + rshape, dtype=object)
    for b in np.ndindex(bshape):
        for i in np.ndindex(lshape):
            for j in np.ndindex(rshape):
                terms = [lax.mul(L[b + i + (c,)], R[b + j + (c,)]) for c in range(k)]
                out[b + i + j] = _tree_reduce(lax.add, terms)
    return [out]


def _structural(eqn, args):
    """Shape operations on the object arrays; None when the primitive is not one."""
    name, p = eqn.primitive.name, eqn.params
    aval = eqn.outvars[0].aval
    if name == "broadcast_in_dim":
        x = args[0]
        shape = tuple(p["shape"])
        expanded = [1] * len(shape)
        for src, dst in enumerate(p["broadcast_dimensions"]):
            expanded[dst] = x.shape[src]
        return [np.broadcast_to(x.reshape(expanded), shape)]
    if name == "reshape":
        if p.get("dimensions") is not None:
            return None
        return [args[0].reshape(tuple(p["new_sizes"]))]
    if name == "squeeze":
        return [args[0].reshape(tuple(aval.shape))]
    if name == "transpose":
        return [np.transpose(args[0], p["permutation"])]
    if name == "slice":
        strides = p["strides"] or (1,) * args[0].ndim
        idx = tuple(slice(a, b, s) for a, b, s in zip(p["start_indices"], p["limit_indices"], strides))
        return [args[0][idx]]
    if name == "concatenate":
        return [np.concatenate(args, axis=p["dimension"])]
    if name == "stack":
        return [np.stack(args, axis=p["axis"])]
    if name == "split":
        cuts = np.cumsum(p["sizes"])[:-1]
        return list(np.split(args[0], cuts, axis=p["axis"]))
    if name == "rev":
        return [np.flip(args[0], axis=tuple(p["dimensions"]))]
    if name == "pad":
        return [_pad(args[0], args[1][()], p["padding_config"])]
    return None


def _iota(eqn):
    p = eqn.params
    shape, d = tuple(p["shape"]), p["dimension"]
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(shape):
        out[idx] = np.asarray(idx[d], dtype=p["dtype"])[()]
    return [out]


def _bind(eqn, arrays):
    """The equation's primitive applied to whole arrays (as `jax.core.eval_jaxpr` does)."""
    got = eqn.primitive.get_bind_params(eqn.params)
    # older JAX returns (subfunctions, params), newer the params alone
    subfuns, params = got if isinstance(got, tuple) else ((), got)
    return eqn.primitive.bind(*subfuns, *arrays, **params)


def _eval(jaxpr, consts, args) -> list:
    env: dict[Any, np.ndarray] = {}

    def read(v):
        if isinstance(v, jcore.Literal):
            return _constant(v.val, v.aval)
        return env[v]

    for v, x in zip(jaxpr.constvars, consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, args):
        env[v] = x
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        ins = [read(v) for v in eqn.invars]
        if name in _ELEMENTWISE:
            outs = _elementwise(eqn, ins)
        elif name in _REDUCE:
            outs = [_reduce(_REDUCE[name], ins[0], eqn.params["axes"], eqn.outvars[0].aval)]
        elif name == "dot_general" and eqn.params.get("preferred_element_type") in (
            None,
            eqn.invars[0].aval.dtype,
        ):
            outs = _dot_general(eqn, *ins)
        elif name == "iota":
            outs = _iota(eqn)
        elif name in _INLINE:
            inner = eqn.params["jaxpr"]
            outs = _eval(inner.jaxpr, [_const_entries(c) for c in inner.consts], ins)
        else:
            outs = _structural(eqn, ins)
            if outs is None:
                # anything else: the primitive itself, on the re-assembled arrays
                arrays = [_assemble(x, v.aval) for x, v in zip(ins, eqn.invars)]
                res = _bind(eqn, arrays)
                res = res if eqn.primitive.multiple_results else [res]
                outs = [_entries(r, v.aval) for r, v in zip(res, eqn.outvars)]
        for v, x in zip(eqn.outvars, outs):
            env[v] = x
    return [read(v) for v in jaxpr.outvars]


def scalarized(f: Callable) -> Callable:
    """`f` evaluated as one graph of scalar operations when its arrays are small.

    The returned function gives the same values as f (and the same derivatives)
    for arguments of the shapes it is called with; when an array of f's jaxpr
    has more than `MAX_ENTRIES` entries, or flattening would take more than
    `MAX_SCALAR_OPS` scalar operations, it is f itself.
    """

    @functools.wraps(f)
    def g(*args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        # arrays (and tracers) are the jaxpr's inputs; anything else (Python numbers, strings,
        # callables) stays as it is, as in a trace of f
        where = [i for i, x in enumerate(leaves) if eqx.is_array(x)]

        def with_arrays(*xs):
            full = list(leaves)
            for i, x in zip(where, xs):
                full[i] = x
            return f(*jax.tree_util.tree_unflatten(tree, full))

        arrays_in = [leaves[i] for i in where]
        closed, out_shape = jax.make_jaxpr(with_arrays, return_shape=True)(*arrays_in)
        biggest, ops = _survey(closed.jaxpr)
        out_tree = jax.tree_util.tree_structure(out_shape)
        if biggest > MAX_ENTRIES or ops > MAX_SCALAR_OPS:  # f's own operations, from the trace just made
            return jax.tree_util.tree_unflatten(out_tree, jcore.jaxpr_as_fun(closed)(*arrays_in))
        consts = [_const_entries(c) for c in closed.consts]
        ins = [_entries(x, v.aval) for x, v in zip(arrays_in, closed.jaxpr.invars)]
        outs = _eval(closed.jaxpr, consts, ins)
        arrays = [_assemble(o, v.aval) for o, v in zip(outs, closed.jaxpr.outvars)]
        return jax.tree_util.tree_unflatten(out_tree, arrays)

    return g
