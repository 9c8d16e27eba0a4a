"""Forward sensitivities: derivatives of a solve by integrating the variational equations.

For a state y' = f(t, y, p) the sensitivities S = ∂y/∂(y0, p) obey

    S' = ∂f/∂y S + ∂f/∂p,        S(t0) = [I | 0],

one column per differentiated scalar (an entry of q0/qd0 or of a parameter
leaf). `ForwardSensitivity` integrates (y, S) together in the same Runge–Kutta
solver. An RK method applied to the variational equations is the derivative
of the RK solution for the same steps, so the result is the derivative of the
computed solution.

Error control includes the sensitivities (as CVODES does with `errconS`):
the step size is chosen so that both the state and every sensitivity column
meet the tolerances (the norm is the larger of the two RMS norms). Without
this, an explicit method running at its stability limit on a stiff problem
keeps the state accurate while its sensitivities grow without bound (damping
of 300/s on the variator: a derivative of −5.6e93 against −6.0e-6). Step
maps of the formulation (re-choosing Appell's partition, projection for
Lagrange's) are applied to the sensitivity columns by their derivatives
(`jaxnh._solve.stepping.SensitivityMaps`), so sensitivities compose with any
stabilisation.

It is wired in as a `jax.custom_jvp` whose tangent output is `S · tangent`:
linear in the tangents, so `jax.jvp`/`jax.jacfwd` *and* `jax.grad`/`jax.jacrev`
(which transpose that product) both work, and one augmented solve serves every
mode. Only the columns of inputs that are actually differentiated are built.
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

from jaxnh._base.modes import differentiated_once, forward_only, reverse_once
from jaxnh._base.types import PyTree
from jaxnh._solve.stepping import MappedSolver, SensitivityMaps


__all__ = ["ForwardSensitivity", "FORWARD_MAX_PARAMETERS", "choose_adjoint", "diffrax_solve", "forward_mode_outputs"]

FORWARD_MAX_PARAMETERS = 64
"""Above this many float scalars in (params, q0, qd0) the automatic choice is reverse mode."""


class ForwardSensitivity(eqx.Module):
    """Derivatives of `simulate` by forward sensitivities (for jvp, jacfwd, grad).

    The cost of a derivative is one solve of the state and its P sensitivity
    columns, P = number of differentiated scalars: cheapest for up to a few
    tens of parameters. Report times `ts` cannot be differentiated this way,
    and dense output and events need a diffrax adjoint.

    Arguments:
        error_control: include the sensitivities in the step-size error
            control (default True; see the module docstring).
    """

    error_control: bool = eqx.field(static=True, default=True)

    def solve(
        self,
        vector_field: object,
        solver: diffrax.AbstractSolver,
        maps: object,
        y0: PyTree,
        args: PyTree,
        saveat: diffrax.SaveAt,
        controller: diffrax.AbstractStepSizeController,
        *,
        t0: jax.typing.ArrayLike,
        t1: jax.typing.ArrayLike,
        max_steps: int | None,
        dt0: jax.typing.ArrayLike | None,
        error_mask: tuple[float, ...] | None = None,
    ) -> tuple[jax.Array, PyTree, diffrax.RESULTS, dict]:
        """The solve of `vector_field(t, y, args)` from y0 at t0 to t1, saved at `saveat`.

        Returns `(ts, ys, result, stats)`, differentiable in `args` and `y0` by
        forward sensitivities. `maps` (a `StepMaps` or None) is applied around
        every step; `error_mask` (a static tuple of 0/1, one per leaf of y0)
        excludes bookkeeping components from the error control.
        """
        return _solve(
            args,
            y0,
            controller,
            t0,
            t1,
            saveat,
            vector_field=vector_field,
            solver=solver,
            maps=maps,
            max_steps=max_steps,
            dt0=dt0,
            error_mask=error_mask,
            error_control=self.error_control,
        )


SECOND_REVERSE = (
    "simulate: adjoint=ForwardSensitivity() (the default for at most 64 differentiated scalars) computes its "
    "derivatives by a forward sensitivity solve, which can itself be differentiated in forward mode only: a "
    "derivative of a derivative with reverse mode outside (jax.grad(jax.grad(f)), jax.grad(jax.jacfwd(f)), "
    "jax.jacrev(jax.jacrev(f))) cannot go through it. Take the outer derivative in forward mode: "
    "jax.jacfwd(jax.grad(f)), jax.jacfwd(jax.jacfwd(f)) or jax.hessian(f), or pass adjoint=diffrax.DirectAdjoint() "
    "(every order and mode)"
)
"""The refusal of a reverse-mode derivative of a derivative through `ForwardSensitivity`'s rule."""


def _masked_rms(err, mask):
    w = jnp.sum(mask)
    return jnp.sqrt(jnp.sum(mask * err**2) / jnp.maximum(w, 1))


def _flat_mask(error_mask, y0):
    """Per-element weights (n,) of y0 from a formulation's error mask: one weight per entry of
    the flat state (None: all ones). A state augmented with sensitivity columns has the same
    weights in each column."""
    leaves = jtu.tree_leaves(y0)
    size = sum(x.size for x in leaves)
    dtype = jnp.result_type(*leaves)
    if error_mask is None:
        return jnp.ones((size,), dtype)
    w = jnp.asarray(error_mask, dtype)
    return jnp.tile(w, size // w.shape[0])


def diffrax_solve(
    vector_field,
    solver,
    maps,
    y0,
    args,
    saveat,
    controller,
    *,
    t0,
    t1,
    max_steps,
    dt0,
    adjoint: diffrax.AbstractAdjoint = diffrax.ForwardMode(),
    event=None,
    progress_meter=None,
    error_mask=None,
):
    """One `diffrax.diffeqsolve` of y' = vector_field(t, y, args) with `maps` around every step,
    the `error_mask` applied to a default-norm PID controller, and throw=False."""
    if maps is not None:
        solver = MappedSolver(solver, maps)
    if error_mask is not None and isinstance(controller, diffrax.PIDController) and _default_norm(controller):
        flat_mask = _flat_mask(error_mask, y0)
        controller = eqx.tree_at(
            lambda c: c.norm, controller, lambda e: _masked_rms(jax.flatten_util.ravel_pytree(e)[0], flat_mask)
        )
    kwargs = {} if progress_meter is None else {"progress_meter": progress_meter}
    if isinstance(adjoint, diffrax.BacksolveAdjoint):
        # diffrax's continuous adjoint is a custom VJP that can be differentiated once: a derivative
        # of its derivative fails inside its backward pass with equinox's "Unexpected tangent"
        y0, args = differentiated_once(
            (y0, args),
            "simulate: adjoint=diffrax.BacksolveAdjoint() gives first derivatives only: diffrax's continuous "
            "adjoint cannot itself be differentiated (jax.grad(jax.grad(f)), jax.hessian(f), a derivative "
            "inside another). For second derivatives pass adjoint=diffrax.DirectAdjoint() (every order and "
            "mode), or the default adjoint and take jax.jacfwd(jax.grad(f)) or jax.hessian(f)",
        )
    if isinstance(adjoint, (diffrax.RecursiveCheckpointAdjoint, diffrax.BacksolveAdjoint)):
        name = type(adjoint).__name__
        y0, args = reverse_once(
            (y0, args),
            f"simulate: adjoint=diffrax.{name}() differentiates the solve in reverse mode once: a reverse-mode "
            "derivative of its derivative (jax.grad(jax.grad(f)), jax.jacrev(jax.grad(f))) cannot go through the "
            "backward loop that computed it. For second derivatives pass adjoint=diffrax.DirectAdjoint() (every "
            "order and mode), or adjoint=jaxnh.ForwardSensitivity() and take jax.jacfwd(jax.grad(f)) or "
            "jax.hessian(f)",
        )
    return diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        solver,
        t0=t0,
        t1=t1,
        dt0=dt0,
        y0=y0,
        args=args,
        saveat=saveat,
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        event=event,
        throw=False,
        **kwargs,
    )


def forward_mode_outputs(tree, adjoint, given: str = "diffrax.ForwardMode()"):
    """`tree` (a solve's outputs) as it is; when `adjoint` is `diffrax.ForwardMode()`, reverse-mode
    differentiation through it raises a `TypeError` naming the adjoint (`given`, as the user passed
    it) and the fix, instead of JAX's words about transposing a while loop."""
    if not isinstance(adjoint, diffrax.ForwardMode):
        return tree
    return forward_only(
        tree,
        f"simulate: adjoint={given} differentiates the solve in forward mode only (jax.jvp, jax.jacfwd, "
        "jax.linearize): reverse mode (jax.grad, jax.jacrev, jax.vjp) cannot go through its loop. For reverse mode "
        "pass adjoint=diffrax.RecursiveCheckpointAdjoint() (or leave the default adjoint), or take the derivative "
        "with jax.jacfwd",
    )


def _default_norm(controller) -> bool:
    return controller.norm is optx.rms_norm


def _plain(
    args,
    y0,
    controller,
    t0,
    t1,
    saveat,
    *,
    vector_field,
    solver,
    maps,
    max_steps,
    dt0,
    error_mask,
    norm=None,
    adjoint: diffrax.AbstractAdjoint = diffrax.ForwardMode(),
):
    if norm is not None and hasattr(controller, "norm"):  # (a constant step size has no error norm)
        controller = eqx.tree_at(lambda c: c.norm, controller, norm)
    sol = diffrax_solve(
        vector_field,
        solver,
        maps,
        y0,
        args,
        saveat,
        controller,
        t0=t0,
        t1=t1,
        max_steps=max_steps,
        dt0=dt0,
        error_mask=None if norm is not None else error_mask,
        adjoint=adjoint,
    )
    return sol.ts, sol.ys, sol.result, sol.stats


@eqx.filter_custom_jvp
def _solve(
    args,
    y0,
    controller,
    t0,
    t1,
    saveat,
    *,
    vector_field,
    solver,
    maps,
    max_steps,
    dt0,
    error_mask,
    error_control,
):
    # the primal solve is never differentiated by JAX (the rule below is), so it takes diffrax's
    # default adjoint, the one a plain diffeqsolve uses; the rule's own solves keep ForwardMode,
    # so that a second derivative can go through them
    return _plain(
        args,
        y0,
        controller,
        t0,
        t1,
        saveat,
        vector_field=vector_field,
        solver=solver,
        maps=maps,
        max_steps=max_steps,
        dt0=dt0,
        error_mask=error_mask,
        adjoint=diffrax.RecursiveCheckpointAdjoint(),
    )


@_solve.def_jvp
def _solve_jvp(primals, tangents, *, vector_field, solver, maps, max_steps, dt0, error_mask, error_control):
    args, y0, controller, t0, t1, saveat = primals
    t_args, t_y0, *t_rest = tangents
    if any(x is not None for x in jtu.tree_leaves(t_rest)):
        raise NotImplementedError(
            "ForwardSensitivity differentiates with respect to the parameters and the initial state only, "
            "not the report times or controller settings; use adjoint=diffrax.RecursiveCheckpointAdjoint() for those."
        )
    is_none = lambda x: x is None  # noqa: E731
    p_mask = jtu.tree_map(lambda t: t is not None, t_args, is_leaf=is_none)
    y_mask = jtu.tree_map(lambda t: t is not None, t_y0, is_leaf=is_none)
    p_diff, p_rest = eqx.partition(args, p_mask)
    tp_diff = eqx.filter(t_args, p_mask, is_leaf=is_none)
    p_leaves, p_def = jtu.tree_flatten(p_diff)
    y_leaves, y_def = jtu.tree_flatten(y0)
    y_on = jtu.tree_leaves(y_mask)
    sizes_p = [x.size for x in p_leaves]
    sizes_y = [x.size if on else 0 for x, on in zip(y_leaves, y_on)]
    P = sum(sizes_p) + sum(sizes_y)
    kw = dict(
        vector_field=vector_field,
        solver=solver,
        maps=maps,
        max_steps=max_steps,
        dt0=dt0,
        error_mask=error_mask,
    )
    if P == 0:
        out = _plain(args, y0, controller, t0, t1, saveat, **kw)
        return out, jtu.tree_map(lambda _: None, out)

    dtype = jnp.result_type(*y_leaves)
    eye = jnp.eye(P, dtype=dtype)
    # Column j is the derivative along one scalar input: y-columns first, then args.
    offset = 0
    S0 = []
    for x, n in zip(y_leaves, sizes_y):
        block = jnp.zeros((P, x.size), x.dtype)
        if n:
            block = eye[:, offset : offset + n].astype(x.dtype)
            offset += n
        S0.append(block.reshape((P,) + x.shape))
    E = []
    for x, n in zip(p_leaves, sizes_p):
        E.append(eye[:, offset : offset + n].astype(x.dtype).reshape((P,) + x.shape))
        offset += n
    S0 = jtu.tree_unflatten(y_def, S0)
    E = jtu.tree_unflatten(p_def, E)

    # The augmented state (y, S) travels as one flat vector: the solver then
    # handles one array instead of 2 × (leaves of y), which costs less per step.
    z0, unravel = jax.flatten_util.ravel_pytree((y0, S0))
    ny = sum(x.size for x in y_leaves)

    def augmented(t, z, a):
        y, S = unravel(z)
        pd, E_ = a
        fy, lin = jax.linearize(lambda y_, pd_: vector_field(t, y_, eqx.combine(pd_, p_rest)), y, pd)
        return jax.flatten_util.ravel_pytree((fy, jax.vmap(lin)(S, E_)))[0].astype(z.dtype)

    mask = _flat_mask(error_mask, y0).astype(dtype)
    # S travels as ravel_pytree of its one leaf (P, n): column after column, each weighted like y
    mask_S = _flat_mask(error_mask, S0).astype(dtype)

    def norm(e):
        ey = _masked_rms(e[:ny], mask)
        if not error_control:  # the steps of the plain solve: the state alone
            return ey
        return jnp.maximum(ey, _masked_rms(e[ny:], mask_S))

    z_maps = None if maps is None else SensitivityMaps(maps, unravel, p_rest)
    ts, zs, result, stats = _plain(
        (p_diff, E),
        z0,
        controller,
        t0,
        t1,
        saveat,
        vector_field=augmented,
        solver=solver,
        maps=z_maps,
        max_steps=max_steps,
        dt0=dt0,
        error_mask=None,
        norm=norm,
    )
    # the sensitivities are the primal values of this rule: first derivatives never transpose them,
    # but a reverse-mode derivative of a derivative (jax.grad of jax.grad or of jax.jacfwd) would have
    # to transpose this forward-mode solve's loop, which JAX cannot: say so, and what works instead
    zs = forward_only(zs, SECOND_REVERSE)
    if isinstance(zs, list):  # several SubSaveAts
        ys, Ss = zip(*[jax.vmap(unravel)(z) for z in zs])
        ys, Ss = list(ys), list(Ss)
    else:
        assert zs is not None  # simulate always saves at the report times
        ys, Ss = jax.vmap(unravel)(zs)
    # Tangent of the inputs as one vector, in the column order above.
    parts = [jnp.ravel(t).astype(dtype) for t, on in zip(jtu.tree_leaves(t_y0, is_leaf=is_none), y_on) if on]
    parts += [jnp.ravel(t).astype(dtype) for t in jtu.tree_leaves(tp_diff)]
    tvec = jnp.concatenate(parts)

    # saved sensitivities have shape (n, P, ...): contract the column axis. Rows the solve never
    # reached (diffrax's inf: SaveAt(steps=True) beyond the last step) get a zero tangent: their
    # inf would otherwise meet a zero cotangent when reverse mode transposes this map (NaN)
    def zero_unreached(t, S):
        return jtu.tree_map(lambda s: jnp.where(jnp.isfinite(t).reshape((-1,) + (1,) * (s.ndim - 1)), s, 0.0), S)

    if isinstance(Ss, list):
        assert isinstance(ts, (list, tuple))  # one time array per SubSaveAt
        Ss = [zero_unreached(t, S) for t, S in zip(ts, Ss)]
    else:
        Ss = zero_unreached(ts, Ss)
    t_ys = jtu.tree_map(lambda s: jnp.tensordot(s, tvec, axes=([1], [0])).astype(s.dtype), Ss)
    no_tangent = lambda tree: jtu.tree_map(lambda _: None, tree)  # noqa: E731
    return (ts, ys, result, stats), (no_tangent(ts), t_ys, no_tangent(result), no_tangent(stats))


def count_float_scalars(*trees) -> int:
    """Number of float scalars in the array leaves of `trees`."""
    return sum(math.prod(jnp.shape(x)) for x in jtu.tree_leaves(trees) if eqx.is_inexact_array(x))


def choose_adjoint(
    adjoint: diffrax.AbstractAdjoint | ForwardSensitivity | None,
    *inputs: PyTree,
    dense: bool = False,
    max_forward: int = FORWARD_MAX_PARAMETERS,
) -> diffrax.AbstractAdjoint | ForwardSensitivity:
    """The one forward/reverse policy of `simulate` and `fit`.

    `adjoint=None`: `ForwardSensitivity()` for at most `max_forward` float
    scalars in the inputs (one augmented solve serves grad, jacfwd and jvp),
    else `diffrax.RecursiveCheckpointAdjoint()`; dense output and events
    always take the diffrax adjoint. An adjoint given is returned unchanged.
    """
    if adjoint is not None:
        return adjoint
    if dense or count_float_scalars(*inputs) > max_forward:
        return diffrax.RecursiveCheckpointAdjoint()
    return ForwardSensitivity()
