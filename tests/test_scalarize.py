"""Small vector fields flattened to scalar operations (jaxnh._equations.scalarize).

The flattened function must be the same function: the same values up to the
rounding of re-associated sums (written-out reductions and small matrix
products add in another order: a few ulps of the largest term), the same
derivatives, and the same under jit, vmap and grad. Primitives it does not
write out (control flow, custom derivative rules, gathers) go through
unchanged. Large functions are left alone.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxnh._equations.scalarize as S
from jaxnh._equations.scalarize import scalarized
from jaxnh.equations import formulation
from jaxnh.models import disc, knife_edge, sleigh, variator


# sums of at most 64 terms re-associated: rounding within a few hundred ulps of the largest term
RTOL = 1e-13


def close(a, b, rtol=RTOL):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    scale = max(1.0, float(np.max(np.abs(b)))) if b.size else 1.0
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


def flat_ops(f, *args) -> list:
    """Primitive names of the jaxpr of f: the flattened one has only scalar arithmetic and stacking."""
    return [e.primitive.name for e in jax.make_jaxpr(f)(*args).jaxpr.eqns]


@jax.custom_jvp
def soft(x):
    return jnp.log1p(jnp.exp(x))


@soft.defjvp
def _soft_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return soft(x), 7.0 * dx  # a deliberately unusual rule: it must survive flattening


def kitchen_sink(x, M, k):
    """Every kind of operation the flattener rewrites, and some it passes through."""
    y = jnp.concatenate([x, x[::-1] * 2.0])  # concatenate, rev
    P = jax.lax.pad(M, 0.0, ((1, -1, 0), (0, 2, 0)))  # pad with a negative edge
    Q = jax.lax.pad(M, 0.5, ((0, 0, 1), (1, 0, 0)))  # interior padding
    B = jnp.einsum("ij,jk->ik", M, M.T) + jnp.outer(x[:3], x[1:4])  # dot_general, transpose
    C = jnp.einsum("bij,bj->bi", jnp.stack([M, 2 * M]), jnp.stack([x[:3], x[1:4]]))  # batched dot
    top, rest = jnp.split(y, [3])
    z = jnp.where(top > 0.1, jnp.sin(top), jnp.cos(top) ** 2)  # select_n, integer_pow
    g = y[k]  # gather with a traced index: passed through
    c = jax.lax.cond(x[0] > 0, lambda: jnp.sum(M), lambda: jnp.max(M))  # cond: passed through
    s = soft(x).sum()  # custom_jvp: passed through with its rule
    n = jnp.sum(jnp.arange(4.0) * x)  # iota
    return (
        jnp.sum(P)
        + jnp.prod(Q[:2, :2])
        + jnp.min(B)
        + jnp.max(C, axis=1).sum()
        + z.sum() * rest.mean()
        + g
        + c
        + s
        + n,
        B.reshape(-1)[::2],
    )


ARGS = (jnp.array([0.3, -1.2, 0.7, 2.0]), jnp.arange(9.0).reshape(3, 3) / 7 - 0.4, 2)


def test_kitchen_sink_values_and_structure():
    got, want = jax.jit(scalarized(kitchen_sink))(*ARGS), kitchen_sink(*ARGS)
    for a, b in zip(got, want):
        close(a, b)
    names = set(flat_ops(scalarized(kitchen_sink), *ARGS))
    assert not names & {"dot_general", "pad", "transpose", "reduce_sum", "reduce_max", "reduce_min", "rev"}
    assert {"cond", "custom_jvp_call"} <= names  # passed through, not inlined


def test_kitchen_sink_derivatives_and_batches():
    f = lambda x, M: kitchen_sink(x, M, 2)[0]  # noqa: E731
    g = scalarized(f)
    for a, b in zip(jax.grad(g, argnums=(0, 1))(*ARGS[:2]), jax.grad(f, argnums=(0, 1))(*ARGS[:2])):
        close(a, b)
    xs = ARGS[0] * jnp.linspace(0.5, 1.5, 5)[:, None]
    close(jax.jit(jax.vmap(g, (0, None)))(xs, ARGS[1]), jax.vmap(f, (0, None))(xs, ARGS[1]))
    close(jax.jacfwd(g)(*ARGS[:2]), jax.jacfwd(f)(*ARGS[:2]))
    # the custom rule (7 per unit of x) is kept: d soft(x) / dx would otherwise be a sigmoid
    assert float(jax.grad(lambda x: scalarized(soft)(x))(0.2)) == 7.0


def test_closure_over_outer_tracer():
    """A function closing over a value of an enclosing trace (a captured, traced array)."""

    def outer(a, x):
        return scalarized(lambda x: a * x + jnp.sum(a) * x[::-1])(x)

    a, x = jnp.array([1.0, 2.0, 3.0]), jnp.array([0.5, -0.5, 2.0])
    close(jax.jit(outer)(a, x), a * x + jnp.sum(a) * x[::-1])
    close(jax.grad(lambda a: outer(a, x).sum())(a), jax.grad(lambda a: (a * x + jnp.sum(a) * x[::-1]).sum())(a))


def test_large_functions_are_left_alone():
    x = jnp.ones(S.MAX_ENTRIES + 1)
    f = lambda x: jnp.cumsum(x) * 2.0  # noqa: E731
    assert flat_ops(scalarized(f), x) == flat_ops(f, x)
    M = jnp.ones((8, 8))  # 64 entries, but a product of 2·8·64 scalar operations per call...
    h = lambda M: M @ M @ M @ M @ M @ M @ M @ M  # noqa: E731  ...times seven: over MAX_SCALAR_OPS
    assert flat_ops(scalarized(h), M) == flat_ops(h, M)


CASES = {
    "variator": lambda: (variator.mechanism(), variator.default_params(), jnp.zeros(2), jnp.array([1.0, 1.5])),
    "sleigh": lambda: (
        sleigh.mechanism(),
        sleigh.default_params(),
        jnp.array([0.1, 0.2, 0.3]),
        sleigh.initial_velocities(jnp.array([0.1, 0.2, 0.3]), 1.0, 0.5),
    ),
    "knife_edge": lambda: (
        knife_edge.mechanism(),
        knife_edge.default_params(),
        jnp.zeros(3),
        jnp.array([0.0, 0.0, 1.0]),
    ),
    "disc": lambda: (disc.mechanism(), disc.default_params(), *disc.steady_state(0.3, 1.0, disc.default_params())),
}


@pytest.mark.parametrize("method", ["appell", "lagrange"])
@pytest.mark.parametrize("model", sorted(CASES))
def test_model_fields_are_the_same_function(model, method):
    mech, p, q0, qd0 = CASES[model]()
    if model == "variator":
        qd0 = qd0.at[1].set(variator.default_params().U21(0.0) * qd0[0])
    t = jnp.asarray(0.37)
    form = formulation(mech, method, q0, qd0, t, p, None)
    y = form.state(q0, qd0, t, p)
    z, unravel = ravel_pytree(y)
    f, g = form.vector_field, scalarized(form.vector_field)
    flat = lambda fn: lambda z_: ravel_pytree(fn(t, unravel(z_), p))[0]  # noqa: E731
    # each side compiled once (eagerly, every operation of a nested derivative is a program of its own)
    close(jax.jit(flat(g))(z), jax.jit(flat(f))(z))
    close(jax.jit(jax.jacfwd(flat(g)))(z), jax.jit(jax.jacfwd(flat(f)))(z), rtol=1e-12)


@jax.custom_vjp
def clipped(x):
    return jnp.minimum(x, 1.0)


def _clipped_fwd(x):
    return clipped(x), x


def _clipped_bwd(x, g):
    return (3.0 * g,)  # an unusual rule, which must survive flattening


clipped.defvjp(_clipped_fwd, _clipped_bwd)


def test_custom_vjp_and_static_leaves_pass_through():
    """A custom_vjp rule is kept; leaves that are not arrays (a string, a Python number, a
    function) stay static, as they are in a trace of the function itself."""

    def f(x, p):
        scale = 2.0 if p["mode"] == "double" else 1.0
        return p["gain"] * scale * clipped(x) + p["fn"](x)

    p = {"gain": 1.5, "mode": "double", "fn": jnp.sin}
    x = jnp.array([0.3, 2.0])
    close(jax.jit(lambda x: scalarized(f)(x, p))(x), f(x, p))
    g = jax.grad(lambda x: scalarized(f)(x, p).sum())(x)
    close(g, jax.grad(lambda x: f(x, p).sum())(x))
    close(g, 1.5 * 2.0 * 3.0 + jnp.cos(x))
