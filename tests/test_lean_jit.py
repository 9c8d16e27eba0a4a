"""`lean_jit`, the dispatch of simulate's compiled program: it must compile exactly as
`equinox.filter_jit` does (array leaves traced, every other leaf a constant compared by value),
return outputs with non-array leaves intact, and compose with jit, vmap and grad.

Every program here is a few scalar operations: the file compiles in about a second.
"""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnh._base.compile import _outermost_jit, lean_jit, one_shot_jit, solve_jit


def counted(fn):
    """`fn` under lean_jit, and a list that grows by one at every trace (a compilation)."""
    traces = []

    def body(*args, **kwargs):
        traces.append(1)
        return fn(*args, **kwargs)

    return lean_jit(body), traces


def test_arrays_traced_and_other_leaves_constants_compared_by_value():
    def f(config, x, *, n):
        return {"y": config["scale"] * x**n, "label": config["label"]}

    g, traces = counted(f)
    out = g({"scale": 2.0, "label": "a"}, jnp.arange(3.0), n=2)
    np.testing.assert_array_equal(out["y"], [0.0, 2.0, 8.0])
    assert out["label"] == "a"  # a non-array output leaf comes back as it was
    g({"scale": 2.0, "label": "a"}, jnp.arange(3.0) + 1, n=2)  # new array values, equal constants
    assert len(traces) == 1
    g({"scale": 3.0, "label": "a"}, jnp.arange(3.0), n=2)  # a Python float is a constant: new program
    g({"scale": 3.0, "label": "a"}, jnp.arange(3.0), n=3)  # so is a keyword
    g({"scale": 3.0, "label": "a"}, jnp.arange(4.0), n=3)  # a new shape
    assert len(traces) == 4


def test_equal_modules_share_a_program():
    """A new but equal diffrax object (a controller made per call) reuses the compiled program;
    its array fields are data."""

    def f(controller, x):
        return controller.rtol * x

    g, traces = counted(f)
    a = g(diffrax.PIDController(rtol=jnp.asarray(1e-6), atol=1e-9), jnp.asarray(2.0))
    b = g(diffrax.PIDController(rtol=jnp.asarray(1e-3), atol=1e-9), jnp.asarray(2.0))
    assert len(traces) == 1
    assert float(a) == 2e-6 and float(b) == 2e-3
    g(diffrax.PIDController(rtol=jnp.asarray(1e-3), atol=1e-8), jnp.asarray(2.0))  # atol a Python float
    assert len(traces) == 2


def test_numpy_leaves_are_data_like_jax_arrays():
    g, traces = counted(lambda x: x + 1)
    assert float(g(np.float64(1.0))) == 2.0
    assert float(g(np.float64(5.0))) == 6.0
    assert len(traces) == 1


def test_composes_with_jit_vmap_grad_and_jacfwd():
    g = lean_jit(lambda p, x: p["k"] * jnp.sin(x))
    p, x = {"k": jnp.asarray(3.0)}, jnp.asarray(0.5)
    expected_dk = np.sin(0.5)
    assert float(jax.jit(jax.grad(lambda q: g(q, x)))(p)["k"]) == pytest.approx(expected_dk, rel=1e-15)
    assert float(jax.jacfwd(lambda k: g({"k": k}, x))(p["k"])) == pytest.approx(expected_dk, rel=1e-15)
    batch = jax.vmap(lambda k: g({"k": k}, x))(jnp.asarray([1.0, 2.0]))
    np.testing.assert_allclose(batch, [np.sin(0.5), 2 * np.sin(0.5)], rtol=1e-15)


def test_module_outputs_with_static_fields():
    @dataclasses.dataclass(frozen=True)
    class Tag:
        name: str

    class Out(eqx.Module):
        value: jax.Array
        tag: Tag = eqx.field(static=True)
        note: object = None

    g = lean_jit(lambda x: Out(2 * x, Tag("q"), note=len))  # `len`: a non-array leaf in a field
    out = g(jnp.asarray(1.5))
    assert isinstance(out, Out) and float(out.value) == 3.0 and out.tag == Tag("q") and out.note is len


def test_an_error_raised_inside_is_readable_under_vmap():
    """Traced calls (vmap, grad outside a jit) go through equinox's wrapper, which turns an
    `equinox.error_if` into an error carrying its message, not JAX's runtime error."""
    g = lean_jit(lambda x: eqx.error_if(x, x < 0, "x must be ≥ 0: pass a distance"))
    np.testing.assert_array_equal(jax.vmap(g)(jnp.asarray([1.0, 2.0])), [1.0, 2.0])
    with pytest.raises(Exception, match="x must be ≥ 0: pass a distance") as info:
        jax.vmap(g)(jnp.asarray([1.0, -2.0]))
    assert not isinstance(info.value, jax.errors.JaxRuntimeError)


def test_compiler_options_apply_and_an_unknown_option_falls_back_to_xla_defaults():
    """Concrete calls compile with the given XLA options; an option this XLA does not know (as a
    future one might drop a debug option) compiles with its defaults instead of failing."""
    known = lean_jit(lambda x: 2 * x, compiler_options={"xla_cpu_use_fusion_emitters": False})
    assert float(known(jnp.asarray(1.5))) == 3.0
    unknown = lean_jit(lambda x: 2 * x, compiler_options={"xla_no_such_option_in_any_xla": True})
    assert float(unknown(jnp.asarray(1.5))) == 3.0
    assert float(unknown(jnp.asarray(2.5))) == 5.0
    # under a transformation the options are left out (JAX refuses them on a nested program)
    assert float(jax.jit(lambda x: known(x) + 1)(jnp.asarray(1.5))) == 4.0


@pytest.mark.parametrize("jit", [solve_jit, one_shot_jit, lambda f: _outermost_jit(f, {"xla_no_such_option": True})])
def test_outermost_programs_compile_with_options_and_compose(jit):
    """`solve_jit` and `one_shot_jit` (jaxnh's programs around solves, and those run a few times):
    options on a concrete call; the plain program under vmap and grad, with concrete arguments
    closed over inside a caller's jit (JAX refuses options on a nested program: this raised before),
    and for an option this XLA does not know. An error raised inside reads as equinox's."""
    g = jit(lambda p, x: eqx.error_if(p["k"] * jnp.sin(x), x < 0, "x must be ≥ 0: pass a distance"))
    p, x = {"k": jnp.asarray(3.0)}, jnp.asarray(0.5)
    assert float(g(p, x)) == pytest.approx(3 * np.sin(0.5), rel=1e-15)
    assert float(jax.jit(lambda: g(p, x))()) == pytest.approx(3 * np.sin(0.5), rel=1e-15)
    assert float(jax.grad(lambda q: g(q, x))(p)["k"]) == pytest.approx(np.sin(0.5), rel=1e-15)
    batch = jax.vmap(lambda k: g({"k": k}, x))(jnp.asarray([1.0, 2.0]))
    np.testing.assert_allclose(batch, [np.sin(0.5), 2 * np.sin(0.5)], rtol=1e-15)
    with pytest.raises(Exception, match="x must be ≥ 0: pass a distance") as info:
        g(p, jnp.asarray(-1.0))
    assert not isinstance(info.value, jax.errors.JaxRuntimeError)
