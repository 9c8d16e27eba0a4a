"""Batched sweeps: one function over many parameter sets or initial states.

`sweep(fn, *args)` evaluates `fn` for every member of a batch — typically
`simulate` over thousands of inertias, ratio laws or initial velocities — and
returns the results stacked in input order, as `jax.vmap` would, but

* in chunks of a fixed size, so device memory holds one or two chunks however
  large the batch is (the inputs and the results live in host memory);
* sharded over every device JAX sees, with `jax.shard_map` over a
  one-dimensional `jax.sharding.Mesh`: each device runs its own vmapped
  adaptive solve on its slice of the chunk, so a slow member holds back only
  the members on the same device;
* unchanged on one CPU, on several local devices, and on several hosts after
  `jax.distributed.initialize()` (then every process calls `sweep` with the
  same arguments, as in any JAX multi-controller program, and every process
  gets the whole result).

All chunks have the same shape (the last one is padded by repeating the last
member, whose results are dropped), so `fn` is compiled once per sweep
signature; a second sweep with the same `fn`, structure and chunk size reuses
the compiled code.

A vmapped adaptive solve steps its whole batch until the slowest member
finishes, and one failed member would raise for all: inside `fn` call
`simulate(..., throw=False)` and return `sol.status` (or `sol.success`) so
each member reports its own outcome.
"""

from __future__ import annotations

import sys
import time
from typing import Any, Callable, Optional, Sequence, Union

import equinox as eqx
import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from jaxnh._base.compile import solve_jit
from jaxnh._base.types import PyTree


__all__ = ["sweep", "default_mesh", "DEFAULT_CHUNK_PER_DEVICE"]

DEFAULT_CHUNK_PER_DEVICE = 256
"""Members per device in one chunk when `chunk_size` is not given."""

PROGRESS_INTERVAL = 1.0
"""Seconds between printed progress lines (`progress=True`)."""


def default_mesh(devices: Optional[Sequence[Any]] = None) -> Mesh:
    """A one-dimensional mesh, axis "batch", over `devices` (default: all
    devices of all processes, `jax.devices()`).

    The axis type is `Auto`: JAX 0.10's `jax.make_mesh` defaults to `Explicit`
    axes, on which a vmapped diffrax solve fails inside equinox's loop.
    """
    devices = jax.devices() if devices is None else list(devices)
    if len(devices) == 0:
        raise ValueError("default_mesh: devices is empty")
    return jax.make_mesh((len(devices),), ("batch",), axis_types=(jax.sharding.AxisType.Auto,), devices=devices)


def sweep(
    fn: Callable[..., Any],
    *args: PyTree,
    in_axes: Any = 0,
    chunk_size: Optional[int] = None,
    mesh: Optional[Mesh] = None,
    progress: Union[None, bool, Callable[[int, int, float], Any]] = None,
) -> Any:
    """Evaluate `fn` over a batch and return the results in input order.

    `sweep(fn, *args)` equals `jax.vmap(fn, in_axes)(*args)` up to rounding
    (every member follows the same arithmetic as a single call of `fn`), but
    runs in chunks and shards each chunk over the devices of `mesh`.

    Example — the variator's output speed over 10⁴ inertias and ratio laws::

        def run(p):
            sol = nh.simulate(mech, p, q0, qd0, ts, throw=False, record=("multipliers",))
            return sol.qd[-1, 1], jnp.max(jnp.abs(sol.multipliers)), sol.status

        ps = jax.vmap(make_params)(J2s, amps)          # a batch of VariatorParams
        w2, lam_max, status = nh.sweep(run, ps, progress=True)

    Arguments:
        fn: function of one member, `fn(*member_args) -> pytree`. Return only
            what is needed (final values, peaks, status): every array in the
            result comes back to host memory for every member.
        *args: pytrees. Leaves of the batched arguments carry the batch on
            their leading axis, the same size N ≥ 1 for all of them (NumPy or
            JAX arrays, or anything `numpy.asarray` accepts).
        in_axes: 0 (batched) or None (shared by every member) — one value
            for all arguments, a tuple with one entry per argument, or a pytree
            prefix of `args` as in `jax.vmap` (only 0 and None are allowed).
            Shared array leaves are traced (a new value does not recompile);
            shared non-array leaves (callables, strings, Python numbers) are
            static, and so are callables and strings inside batched arguments.
        chunk_size: members evaluated per compiled call, over all devices;
            rounded up to a multiple of the device count (default
            `DEFAULT_CHUNK_PER_DEVICE` per device, and never more than the
            batch needs). It bounds device memory and sets the batch over
            which a vmapped adaptive solve waits for its slowest member.
        mesh: a `jax.sharding.Mesh`; the batch is split over all its axes
            (default `default_mesh()`: every device of every process).
        progress: None (silent); True: a line on stderr from process 0
            after the first chunk, the last, and at most every
            `PROGRESS_INTERVAL` s between; or a callable
            `progress(done, total, elapsed_s)` called after every chunk.

    Returns:
        The pytree `fn` returns, each array leaf with a leading axis of size
        N in input order, as NumPy arrays on every process. Non-array leaves
        (e.g. coordinate names) appear once.
    """
    if not callable(fn):
        raise TypeError(f"sweep: fn must be callable; got {type(fn).__name__}")
    if len(args) == 0:
        raise ValueError("sweep: give at least one batched argument after fn")
    mesh = default_mesh() if mesh is None else mesh
    if not isinstance(mesh, Mesh):
        raise TypeError(f"sweep: mesh must be a jax.sharding.Mesh; got {type(mesh).__name__}")
    n_dev = int(mesh.size)

    leaves, treedef, axes, paths = _flatten_with_axes(args, in_axes)
    # Non-array leaves (callables, strings) are static even inside batched
    # arguments, as in `equinox.filter_vmap`; numbers there must be arrays.
    axes = [a if (a is None or _is_data(leaves[i])) else None for i, a in enumerate(axes)]
    batched_ix = [i for i, a in enumerate(axes) if a == 0]
    if not batched_ix:
        raise ValueError("sweep: in_axes marks no array argument as batched (0); nothing to sweep over")
    host = {}
    N = None
    for i in batched_ix:
        x = np.asarray(leaves[i])
        if x.ndim == 0:
            raise ValueError(
                f"sweep: batched leaf args{paths[i]} is a scalar; batched leaves need a leading batch axis "
                "(use in_axes=None for values shared by every member)"
            )
        if N is None:
            N, first = x.shape[0], i
        elif x.shape[0] != N:
            raise ValueError(
                f"sweep: batched leaves must share the batch size; args{paths[first]} has {N} members "
                f"(shape {np.shape(leaves[first])}) but args{paths[i]} has shape {x.shape}"
            )
        host[i] = x
    assert N is not None  # batched_ix is not empty
    if N == 0:
        raise ValueError(f"sweep: the batch is empty (args{paths[first]} has shape {np.shape(leaves[first])})")

    if chunk_size is None:
        chunk = DEFAULT_CHUNK_PER_DEVICE * n_dev
    else:
        if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
            raise ValueError(f"sweep: chunk_size must be a positive integer; got {chunk_size!r}")
        chunk = int(chunk_size)
    chunk = min(chunk, N)
    chunk = -(-chunk // n_dev) * n_dev  # a multiple of the device count
    n_chunks = -(-N // chunk)

    shared_ix = [i for i, a in enumerate(axes) if a is None and eqx.is_array(leaves[i])]
    static = tuple((i, leaves[i]) for i, a in enumerate(axes) if a is None and not eqx.is_array(leaves[i]))
    batch_sharding = NamedSharding(mesh, P(tuple(mesh.axis_names)))
    replicated = NamedSharding(mesh, P())
    shared = _place([np.asarray(leaves[i]) for i in shared_ix], replicated)
    layout = _Layout(treedef, tuple(batched_ix), tuple(shared_ix), static)

    report = _reporter(progress)
    t_start = time.perf_counter()
    out_host = None  # preallocated host arrays, (N, ...) per output leaf
    out_static = None
    pending = None  # (chunk index, device result) in flight

    def collect(k, dev_out):
        nonlocal out_host, out_static
        dyn, out_static = dev_out
        lo = k * chunk
        hi = min(N, lo + chunk)
        parts = jax.tree_util.tree_map(_to_host, dyn)
        if out_host is None:
            out_host = jax.tree_util.tree_map(lambda x: np.empty((N,) + x.shape[1:], x.dtype), parts)
        jax.tree_util.tree_map(lambda o, x: o.__setitem__(slice(lo, hi), x[: hi - lo]), out_host, parts)
        if report is not None:
            report(hi, N, time.perf_counter() - t_start)

    for k in range(n_chunks):
        lo = k * chunk
        rows = np.minimum(np.arange(lo, lo + chunk), N - 1)  # pad by repeating the last member
        batched = _place([host[i][rows] for i in batched_ix], batch_sharding)
        dev_out = _run_chunk(fn, layout, mesh, batched, shared)  # dispatched asynchronously
        if pending is not None:  # fetch the previous chunk while this one runs
            collect(*pending)
        pending = (k, dev_out)
    assert pending is not None  # n_chunks >= 1
    collect(*pending)
    return eqx.combine(out_host, out_static)


# --- internals ---------------------------------------------------------------------


class _Layout(eqx.Module):
    """How the flat leaves of `args` are rebuilt inside the compiled call (static)."""

    treedef: Any = eqx.field(static=True)
    batched: tuple = eqx.field(static=True)
    shared: tuple = eqx.field(static=True)
    static: tuple = eqx.field(static=True)

    def rebuild(self, batched, shared):
        n = len(self.batched) + len(self.shared) + len(self.static)
        leaves = [None] * n
        for i, x in zip(self.batched, batched):
            leaves[i] = x
        for i, x in zip(self.shared, shared):
            leaves[i] = x
        for i, x in self.static:
            leaves[i] = x
        return jax.tree_util.tree_unflatten(self.treedef, leaves)


@solve_jit
def _run_chunk(fn, layout: _Layout, mesh: Mesh, batched, shared):
    """One chunk: shard_map over the mesh, vmap over each device's members.

    Returns (array results sharded on the batch axis, non-array results).
    """
    out_static = []

    def per_device(batched, shared):
        def one(*b):
            return fn(*layout.rebuild(b, shared))

        out = eqx.filter_vmap(one, out_axes=eqx.if_array(0))(*batched)
        dyn, st = eqx.partition(out, eqx.is_array)
        out_static.append(st)
        return dyn

    spec = P(tuple(mesh.axis_names))
    dyn = jax.shard_map(per_device, mesh=mesh, in_specs=(spec, P()), out_specs=spec, check_vma=False)(batched, shared)
    return dyn, out_static[0]


def _is_data(x) -> bool:
    return eqx.is_array(x) or isinstance(x, (bool, int, float, complex, np.number))


def _place(xs: list, sharding: NamedSharding) -> list:
    """Put host arrays on the mesh. One process: a single batched transfer.
    Several: each process supplies the shards its own devices hold."""
    if sharding.is_fully_addressable:
        return list(jax.device_put(xs, sharding))
    return [jax.make_array_from_callback(x.shape, sharding, lambda idx, x=x: x[idx]) for x in xs]


def _to_host(x):
    if not isinstance(x, jax.Array):
        return np.asarray(x)
    if x.is_fully_addressable:
        return np.asarray(x)

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def _flatten_with_axes(args: tuple, in_axes):
    """Flat leaves of `args`, the batch axis (0 or None) of each, and their paths."""
    if in_axes is None or isinstance(in_axes, int):
        in_axes = (in_axes,) * len(args)
    elif isinstance(in_axes, list):
        in_axes = tuple(in_axes)
    if isinstance(in_axes, tuple) and len(in_axes) != len(args):
        raise ValueError(f"sweep: in_axes has {len(in_axes)} entries but {len(args)} arguments were given")
    is_none = lambda x: x is None  # noqa: E731
    ax_leaves, ax_def = jax.tree_util.tree_flatten(in_axes, is_leaf=is_none)
    for a in ax_leaves:
        if not (a is None or (isinstance(a, int) and not isinstance(a, bool) and a == 0)):
            raise ValueError(f"sweep: in_axes entries must be 0 (batched) or None (shared); got {a!r}")
    try:
        subtrees = ax_def.flatten_up_to(args)
    except (ValueError, TypeError) as e:
        raise ValueError(f"sweep: in_axes must be a pytree prefix of the arguments: {e}") from None
    axes = []
    for a, sub in zip(ax_leaves, subtrees):
        axes.extend([a] * len(jax.tree_util.tree_leaves(sub)))
    path_leaves, treedef = jax.tree_util.tree_flatten_with_path(args)
    paths = [jax.tree_util.keystr(p) for p, _ in path_leaves]
    leaves = [x for _, x in path_leaves]
    assert len(axes) == len(leaves)
    return leaves, treedef, axes, paths


def _reporter(progress):
    if progress is None or progress is False:
        return None
    if progress is True:
        if jax.process_index() != 0:
            return None

        last = [-np.inf]

        def report(done, total, elapsed):
            # the first chunk, the last, and at most one line a second between
            if done < total and elapsed - last[0] < PROGRESS_INTERVAL and last[0] > -np.inf:
                return
            last[0] = elapsed
            eta = elapsed * (total - done) / max(done, 1)
            print(
                f"sweep: {done}/{total} members ({100 * done / total:.0f}%), {elapsed:.1f} s elapsed, "
                f"~{eta:.1f} s left",
                file=sys.stderr,
                flush=True,
            )

        return report
    if callable(progress):
        return progress
    raise TypeError(f"sweep: progress must be None, True or a callable(done, total, elapsed); got {progress!r}")
