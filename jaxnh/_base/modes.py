"""Outputs that may be differentiated in forward mode only, and say so when reverse mode is tried.

A solve by `diffrax.ForwardMode()` carries tangents through a `lax.while_loop`: `jax.jvp` and
`jax.jacfwd` go through it, but reverse mode (`jax.grad`, `jax.jacrev`, `jax.vjp`) must transpose
the loop, which JAX cannot do, and JAX's own message names neither the adjoint nor the fix. The
refusal has to happen when JAX transposes the program, after the solve has returned, so it is
a rule of the program itself.

`forward_only(tree, message)` passes every inexact array of `tree` through the identity
primitive `jaxnh_forward_only`. Its derivative is itself (it is linear), so values, `jit`, `vmap`,
`jax.jvp`, `jax.jacfwd` and higher forward derivatives are unchanged; its transpose, which only
reverse mode asks for, raises `TypeError(message)`. On the program's outputs it is transposed
before the loop behind it, so the user reads the message and not JAX's. A zero cotangent (an
output the loss does not use) transposes without asking the rule.

`reverse_once(tree, message)` is its counterpart for a solve differentiated by a backward loop
(diffrax's `RecursiveCheckpointAdjoint`, `BacksolveAdjoint`): an identity on the solve's inputs,
linear, whose transpose passes the cotangent the backward loop computed through `forward_only`.
A first derivative in either mode, and forward mode over reverse mode, are unchanged; reverse mode
over reverse mode (`jax.grad(jax.grad(f))`), which would have to transpose that backward loop,
raises `TypeError(message)`.

`differentiated_once(tree, message)` refuses a derivative of a derivative in any mode, before the
solve's own derivative rules are reached: an identity whose derivative rule returns its value
through a second identity primitive, `jaxnh_differentiated`, and passes the tangent unchanged. In a
first derivative that second primitive is applied to values nothing else differentiates; inside a
second derivative the value it marks is itself being differentiated, and its derivative rule
raises `TypeError(message)`. It is placed on a solve's inputs, so it is met in the program's
forward part, before the backward pass of a custom VJP that cannot be differentiated again (diffrax's
`BacksolveAdjoint`, whose failure there names neither the adjoint nor the fix).

They are built with JAX's public interface for primitives (`jax.extend.core.Primitive` and the rule
tables of `jax.interpreters`, the interface JAX documents for defining primitives).
"""

from __future__ import annotations

import equinox as eqx
import jax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir


__all__ = ["differentiated_once", "forward_only", "reverse_once"]


def _identity_primitive(name: str) -> Primitive:
    """An identity primitive carrying a `message` parameter: value, lowering and batching rules
    (its derivative rules are each primitive's own)."""
    p = Primitive(name)
    p.def_impl(lambda x, *, message: x)
    p.def_abstract_eval(lambda x, *, message: x)
    mlir.register_lowering(p, lambda ctx, x, *, message: [x])
    batching.primitive_batchers[p] = lambda args, dims, *, message: (p.bind(args[0], message=message), dims[0])
    return p


_forward_only_p = _identity_primitive("jaxnh_forward_only")


def _transpose(cotangent, x, *, message):
    raise TypeError(message)


ad.deflinear2(_forward_only_p, _transpose)


def forward_only(tree, message: str):
    """`tree` unchanged in value and forward-mode derivative; reverse-mode differentiation through
    any of its inexact arrays raises `TypeError(message)`."""
    return jax.tree_util.tree_map(
        lambda x: _forward_only_p.bind(x, message=message) if eqx.is_inexact_array(x) else x, tree
    )


_reverse_once_p = _identity_primitive("jaxnh_reverse_once")


def _transpose_once(cotangent, x, *, message):
    # the cotangent of the solve's input, computed by its backward loop: itself differentiable in
    # forward mode only, which `forward_only` says when a second reverse pass reaches it
    return [_forward_only_p.bind(cotangent, message=message)]


ad.deflinear2(_reverse_once_p, _transpose_once)


def reverse_once(tree, message: str):
    """`tree` (a solve's inputs) unchanged in value and in every first derivative; the cotangents
    reverse mode computes for it are `forward_only(..., message)`: a reverse-mode derivative of a
    reverse-mode derivative (`jax.grad(jax.grad(f))`), which would have to transpose the backward
    loop that computed them, raises `TypeError(message)`, while forward mode over reverse mode
    (`jax.jacfwd(jax.grad(f))`) passes."""
    return jax.tree_util.tree_map(
        lambda x: _reverse_once_p.bind(x, message=message) if eqx.is_inexact_array(x) else x, tree
    )


_once_p = _identity_primitive("jaxnh_differentiated_once")
_marked_p = _identity_primitive("jaxnh_differentiated")


def _once_jvp(primals, tangents, *, message):
    return _marked_p.bind(primals[0], message=message), tangents[0]


def _marked_jvp(primals, tangents, *, message):
    raise TypeError(message)


ad.primitive_jvps[_once_p] = _once_jvp
ad.primitive_jvps[_marked_p] = _marked_jvp


def differentiated_once(tree, message: str):
    """`tree` (a solve's inputs) unchanged in value and in its first derivative, in either mode; a
    derivative of that derivative (`jax.grad(jax.grad(f))`, `jax.hessian(f)`, any nesting) raises
    `TypeError(message)` when JAX traces it."""
    return jax.tree_util.tree_map(lambda x: _once_p.bind(x, message=message) if eqx.is_inexact_array(x) else x, tree)
