"""Forward sensitivities: derivatives of a solve by integrating the variational equations.

For a state y' = f(t, y, p) the sensitivities S = ∂y/∂(y0, p) obey

    S' = ∂f/∂y S + ∂f/∂p,        S(t0) = [I | 0],

one column per differentiated scalar (an entry of q0/qd0 or of a parameter
leaf). `ForwardSensitivity` integrates (y, S) together in the same Runge–Kutta
solver, with the step control looking at y only, so the steps are those of the
plain solve (diffrax stops gradients through step sizes as well), and an RK
method applied to the variational equations is the derivative of the RK
solution: the result is the derivative of the computed solution, as with
`diffrax.ForwardMode`, to rounding.

It is wired in as a `jax.custom_jvp` whose tangent output is `S · tangent`:
linear in the tangents, so `jax.jvp`/`jax.jacfwd` *and* `jax.grad`/`jax.jacrev`
(which transpose that product) both work, and one augmented solve serves every
mode. Only the columns of inputs that are actually differentiated are built
(symbolic zeros), so the cost is one solve of (1 + P) times the state for P
differentiated scalars — far below reverse mode through diffrax's checkpointed
loop for small mechanisms with tens of parameters (see benchmarks/RESULTS.md).

`simulate(adjoint=None)` chooses it automatically for up to
`FORWARD_MAX_PARAMETERS` float scalars in (params, q0, qd0) (`auto_adjoint`);
measurements in benchmarks/RESULTS.md ("Gradients").
"""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jax.tree_util as jtu
import optimistix as optx

__all__ = ["ForwardSensitivity", "solve_forward_sensitivity", "FORWARD_MAX_PARAMETERS", "auto_adjoint"]

FORWARD_MAX_PARAMETERS = 64
"""Above this many float scalars in (params, q0, qd0) the automatic choice is reverse mode."""


class ForwardSensitivity(eqx.Module):
    """Derivatives of `simulate` by forward sensitivities (for jvp, jacfwd, grad).

    The cost of a derivative is one solve of the state and its P sensitivity
    columns, P = number of differentiated scalars: cheapest for up to a few
    tens of parameters. Report times `ts` cannot be differentiated this way.
    """


def auto_adjoint(params, q0, qd0, max_forward: int = FORWARD_MAX_PARAMETERS):
    """`ForwardSensitivity()` for at most `max_forward` float scalars in the inputs, else
    `diffrax.RecursiveCheckpointAdjoint()`."""
    n = sum(math.prod(jnp.shape(x)) for x in jtu.tree_leaves((params, q0, qd0)) if eqx.is_inexact_array(x))
    return ForwardSensitivity() if n <= max_forward else diffrax.RecursiveCheckpointAdjoint()


def solve_at(vector_field, solver, y0, args, ts, controller, max_steps, dt0, throw,
             adjoint=diffrax.ForwardMode()):
    """diffrax's solve of y' = vector_field(t, y, args) from ts[0], reported at ts:
    (ys, result, stats)."""
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=dt0,
        y0=y0,
        args=args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,  # ForwardMode for the sensitivity solves: only reached by higher-order derivatives
        throw=throw,
    )
    return sol.ys, sol.result, sol.stats


@eqx.filter_custom_jvp
def solve_forward_sensitivity(params, y0, ts, controller, *, vector_field, solver, max_steps, dt0, throw):
    """The solve `vector_field(t, y, params)` from y0 reported at ts: (ys, result, stats).

    `controller` is a `diffrax.PIDController` (its norm must be the default
    RMS norm). Differentiable in `params` and `y0` by forward sensitivities
    (see the module docstring).
    """
    return solve_at(vector_field, solver, y0, params, ts, controller, max_steps, dt0, throw)


@solve_forward_sensitivity.def_jvp
def _solve_jvp(primals, tangents, *, vector_field, solver, max_steps, dt0, throw):
    params, y0, ts, controller = primals
    t_params, t_y0, t_ts, t_controller = tangents
    if any(x is not None for x in jtu.tree_leaves((t_ts, t_controller))):
        raise NotImplementedError(
            "ForwardSensitivity differentiates with respect to the parameters and the initial state only, "
            "not the report times or controller settings; use adjoint=diffrax.RecursiveCheckpointAdjoint() for those."
        )
    # Split the inputs into differentiated leaves (nonzero tangent) and the rest.
    is_none = lambda x: x is None  # noqa: E731
    p_mask = jtu.tree_map(lambda t: t is not None, t_params, is_leaf=is_none)
    y_mask = jtu.tree_map(lambda t: t is not None, t_y0, is_leaf=is_none)
    p_diff, p_rest = eqx.partition(params, p_mask)
    tp_diff = eqx.filter(t_params, p_mask, is_leaf=is_none)
    p_leaves, p_def = jtu.tree_flatten(p_diff)
    y_leaves, y_def = jtu.tree_flatten(y0)
    y_on = jtu.tree_leaves(y_mask)
    sizes_p = [x.size for x in p_leaves]
    sizes_y = [x.size if on else 0 for x, on in zip(y_leaves, y_on)]
    P = sum(sizes_p) + sum(sizes_y)
    if P == 0:
        out = solve_at(vector_field, solver, y0, params, ts, controller, max_steps, dt0, throw)
        return out, jtu.tree_map(lambda _: None, out)

    dtype = jnp.result_type(*y_leaves)
    eye = jnp.eye(P, dtype=dtype)
    # Column j is the derivative along one scalar input: y-columns first, then params.
    offset = 0
    S0 = []
    for x, n in zip(y_leaves, sizes_y):
        block = jnp.zeros((P, x.size), x.dtype)
        if n:
            block = eye[:, offset:offset + n].astype(x.dtype)
            offset += n
        S0.append(block.reshape((P,) + x.shape))
    E = []
    for x, n in zip(p_leaves, sizes_p):
        E.append(eye[:, offset:offset + n].astype(x.dtype).reshape((P,) + x.shape))
        offset += n
    S0 = jtu.tree_unflatten(y_def, S0)
    E = jtu.tree_unflatten(p_def, E)

    # The augmented state (y, S) travels as one flat vector: the solver then
    # handles one array instead of 2 × (leaves of y), which costs less per step.
    z0, unravel = jax.flatten_util.ravel_pytree((y0, S0))
    ny = sum(x.size for x in y_leaves)

    def augmented(t, z, args):
        y, S = unravel(z)
        pd, E_ = args
        fy, lin = jax.linearize(lambda y_, pd_: vector_field(t, y_, eqx.combine(pd_, p_rest)), y, pd)
        return jax.flatten_util.ravel_pytree((fy, jax.vmap(lin)(S, E_)))[0].astype(z.dtype)

    def y_norm(scaled_error):  # step control on the state only: the sensitivities follow its steps
        return optx.rms_norm(scaled_error[:ny])

    y_controller = eqx.tree_at(lambda c: c.norm, controller, y_norm)
    if hasattr(solver, "for_sensitivities"):  # a projection after each step: project the columns too
        solver = solver.for_sensitivities(unravel, p_rest)
    zs, result, stats = solve_at(augmented, solver, z0, (p_diff, E), ts, y_controller, max_steps, dt0, throw)
    ys, Ss = jax.vmap(unravel)(zs)
    # Tangent of the inputs as one vector, in the column order above.
    parts = [jnp.ravel(t).astype(dtype) for t, on in zip(jtu.tree_leaves(t_y0, is_leaf=is_none), y_on) if on]
    parts += [jnp.ravel(t).astype(dtype) for t in jtu.tree_leaves(tp_diff)]
    tvec = jnp.concatenate(parts)
    # saved sensitivities have shape (n, P, ...): contract the column axis
    t_ys = jtu.tree_map(lambda s: jnp.tensordot(s, tvec, axes=([1], [0])).astype(s.dtype), Ss)
    no_tangent = lambda tree: jtu.tree_map(lambda _: None, tree)  # noqa: E731
    return (ys, result, stats), (t_ys, no_tangent(result), no_tangent(stats))

