"""A lean adaptive Runge–Kutta loop for ODEs that need none of diffrax's machinery.

`lean_solve` integrates `dy/dt = f(t, y, args)` for a flat state `y` (shape (n,))
with an explicit embedded Runge–Kutta pair (Tsitouras' 5(4) or Dormand–Prince
8(5,3), the tableaus of `jaxnh.solvers`) and returns the state at given report
times. It is one `lax.while_loop` over step attempts whose body is a single
straight-line computation: the unrolled stages, the error norm, a PI step-size
controller and the reports. Nothing else: no events, no saving of steps, no
reverse-mode adjoint, no host callbacks. Failures are returned as an integer
status, never raised, so the compiled program can be stored in JAX's
persistent compilation cache and serialised with `jax.export`.

It runs under `jax.jit`, `jax.vmap` (the loop runs until the slowest member of
the batch is done; finished members are frozen) and forward-mode `jax.jvp`
(tangents of `y0` and `args` are carried through the same loop; the step
sizes are not differentiated, as in diffrax). Reverse mode is not supported:
use `diffrax.diffeqsolve` for that.

With the same tableau, tolerances, controller and first step it takes the same
steps as `diffrax.diffeqsolve` with `jaxnh.solvers.Tsit5`/`DOP853`,
`diffrax.PIDController(rtol, atol)` and `SaveAt(ts=...)` (same acceptance test
and step-size update), so the two agree to rounding, when `report="interpolate"`
and no step would hold more than 2 report times (tests/test_lean.py checks it).
Two differences: with `dt0=None` this loop selects the first step by Hairer's
algorithm (diffrax 0.7.2 has the same code, but it never runs for
`diffeqsolve`'s wrapped terms, which start at dt0 = 0.01: pass `dt0=0.01` to
reproduce diffrax's steps), and the default `report="step"` lands a step on
every report time (measured faster; see `lean_solve`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.export
import jax.lax as lax
import jax.numpy as jnp

from . import solvers as _S


__all__ = ["LeanSolution", "Tableau", "TSIT5", "DOP853", "STATUS_MESSAGES", "lean_solve"]

#: Meaning of `LeanSolution.status`.
STATUS_MESSAGES = {
    0: "success: every report time was reached",
    1: "max_steps reached before the last report time (step attempts, accepted or rejected, hit max_steps)",
    2: (
        "step size underflow: the step size became too small to advance t in floating point (after a "
        "rejection, or for an attempt itself), or non-finite. Almost always a non-finite value (NaN/inf) in the "
        "vector field or the state, which makes every attempt fail; otherwise a singularity or a tolerance below "
        "rounding."
    ),
}


class LeanSolution(NamedTuple):
    """What `lean_solve` returns.

    Attributes:
        ys: state at the report times, shape (len(ts), n), dtype of y0. Report
            times not reached (status != 0) hold NaN.
        status: int32 scalar (per batch member under vmap): 0 success, 1
            max_steps reached, 2 step size underflow / non-finite values; see
            `STATUS_MESSAGES`.
        stats: dict of int32 scalars: `num_steps` (step attempts), `num_accepted_steps`,
            `num_rejected_steps`, `rhs_evaluations` (calls of the vector field,
            including the initial-step selection, dense-output stages and the
            re-evaluations after `pre_step`/`post_step` changed the state).
        t_final: time the integration reached (ts[-1] on success; where it stopped otherwise).
        y_final: the state at `t_final` (n,): where a failed solve stalled, for its diagnosis.
    """

    ys: jax.Array
    status: jax.Array
    stats: dict
    t_final: jax.Array
    y_final: jax.Array


# Exported programs (`jax.export`) that return a LeanSolution can be serialised.
jax.export.register_namedtuple_serialization(LeanSolution, serialized_name="jaxnh.LeanSolution")


# ----------------------------------------------------------------------------- tableaus


def _lincomb(coeffs: Mapping[int, float], fs: Mapping[int, jax.Array]) -> jax.Array:
    """sum_j coeffs[j] * fs[j] as a chain of multiply-adds (weakly typed Python floats)."""
    acc = None
    for j, c in coeffs.items():
        if c == 0.0:
            continue
        term = float(c) * fs[j]
        acc = term if acc is None else acc + term
    assert acc is not None, "a linear combination with every coefficient zero"
    return acc


@dataclasses.dataclass(frozen=True, eq=False)
class Tableau:
    """An explicit first-same-as-last embedded Runge–Kutta pair with a continuous extension.

    Attributes:
        name: label.
        order: order of the propagated solution.
        error_order: exponent q of the controller, factor ∝ err^(-1/q) (diffrax's
            `solver.error_order`, so steps match diffrax's).
        c: nodes c_1..c_s (s stages before the FSAL stage).
        a: {i: {j: a_ij}} for stages i = 2..s (1-based, zeros omitted).
        b: {j: b_j} weights of the solution; stage s+1 is f(t1, y1) (FSAL).
        error: `error(fs, h) -> err` local error estimate from the stages
            fs = {1..s+1: f_j} (fs[s+1] = f(t1, y1)).
        evals_per_step: vector-field evaluations of one step attempt (FSAL: s).
        dense_evals: extra evaluations the continuous extension needs per step (made
            only in steps that contain a report time).
        dense_prepare: `(vf, t0, h, y0, y1, fs, args) -> (coeffs, extra_evals)`:
            what the continuous extension needs for one step.
        dense_eval: `(coeffs, y0, s) -> y(t0 + s h)`, s in [0, 1].
    """

    name: str
    order: int
    error_order: int
    c: tuple
    a: dict
    b: dict
    error: Callable
    evals_per_step: int
    dense_evals: int
    dense_prepare: Callable
    dense_eval: Callable

    @property
    def stages(self) -> int:
        return len(self.c)

    def step(self, vf, t0, h, y0, f0, args):
        """One step from (t0, y0) with f0 = f(t0, y0): (y1, f(t1, y1), err, fs)."""
        fs = {1: f0}
        s = self.stages
        t1 = t0 + h
        for i in range(2, s + 1):
            ci = self.c[i - 1]
            ti = t1 if ci == 1.0 else t0 + ci * h
            fs[i] = vf(ti, y0 + h * _lincomb(self.a[i], fs), args)
        y1 = y0 + h * _lincomb(self.b, fs)
        fs[s + 1] = vf(t1, y1, args)
        return y1, fs[s + 1], self.error(fs, h), fs

    def __repr__(self):
        return f"Tableau({self.name})"


# Tsit5 ---------------------------------------------------------------------------


def _t5_error(fs, h):
    return h * _lincomb(_S._T5_E, fs)


def _t5_dense_prepare(vf, t0, h, y0, y1, fs, args):
    return jnp.stack([h * fs[j] for j in range(1, 8)]), 0


def _t5_dense_eval(ks, y0, s):
    w = _S._tsit5_dense_weights(s)
    out = y0
    for j in range(1, 8):
        out = out + w[j].astype(y0.dtype) * ks[j - 1]
    return out


TSIT5 = Tableau(
    name="tsit5",
    order=5,
    error_order=5,
    c=tuple(_S._T5_C[:6]),
    a=_S._T5_A,
    b=_S._T5_B,
    error=_t5_error,
    evals_per_step=6,
    dense_evals=0,
    dense_prepare=_t5_dense_prepare,
    dense_eval=_t5_dense_eval,
)
"""Tsitouras' 5(4) pair (Comput. Math. Appl. 62 (2011) 770), as `jaxnh.solvers.Tsit5`."""


# DOP853 --------------------------------------------------------------------------


def _dop853_error(fs, h):
    e5 = h * _lincomb(_S._ER, fs)
    e3 = h * _lincomb(_S._E3, fs)
    den2 = e5 * e5 + 0.01 * (e3 * e3)
    pos = den2 > 0
    return jnp.where(pos, e5 * jnp.abs(e5) / jnp.sqrt(jnp.where(pos, den2, 1)), 0)


def _dop853_dense_prepare(vf, t0, h, y0, y1, fs, args):
    fs = dict(fs)
    for i in range(14, 17):
        fs[i] = vf(t0 + _S._C[i - 1] * h, y0 + h * _lincomb(_S._A[i], fs), args)
    ydiff = y1 - y0
    bspl = h * fs[1] - ydiff
    r4 = ydiff - h * fs[13] - bspl
    r58 = [h * _lincomb(_S._D[k], fs) for k in (4, 5, 6, 7)]
    return jnp.stack([ydiff, bspl, r4, *r58]), 3


def _dop853_dense_eval(r, y0, s):
    s = s.astype(y0.dtype)
    sc = 1 - s
    inner = r[3] + s * (r[4] + sc * (r[5] + s * r[6]))
    return y0 + s * (r[0] + sc * (r[1] + s * (r[2] + sc * inner)))


DOP853 = Tableau(
    name="dop853",
    order=8,
    error_order=8,
    c=tuple(_S._C[:12]),
    a={i: _S._A[i] for i in range(2, 13)},
    b=_S._B,
    error=_dop853_error,
    evals_per_step=12,
    dense_evals=3,
    dense_prepare=_dop853_dense_prepare,
    dense_eval=_dop853_dense_eval,
)
"""Dormand–Prince 8(5,3) with Hairer's error estimate and 7th-order dense output (Hairer,
Nørsett & Wanner, Solving ODEs I, 2nd ed., §II.10), as `jaxnh.solvers.DOP853`."""

_METHODS = {"tsit5": TSIT5, "dop853": DOP853, "dopri8": DOP853}


def _tableau(method) -> Tableau:
    if isinstance(method, Tableau):
        return method
    if isinstance(method, str) and method.lower() in _METHODS:
        return _METHODS[method.lower()]
    raise ValueError(f"lean_solve: method must be one of {sorted(_METHODS)} or a jaxnh._lean.Tableau; got {method!r}")


# ----------------------------------------------------------------------------- the loop


def rms_norm(x):
    """sqrt(mean(x²)): diffrax's default error norm."""
    return jnp.sqrt(jnp.mean(x * x))


def _any(x):
    """True if any batch member's x is true (one branch taken for the whole batch under vmap)."""
    return eqxi.unvmap_any(x)


# In report="interpolate" mode a step never contains more than this many report times
# strictly inside it (it is clipped to the next one after them): reports are written
# straight-line. Report times denser than this per natural step cost extra steps.
_INTERIOR_REPORTS = 2


class _Carry(NamedTuple):
    t: Any
    y: Any
    f: Any
    dt: Any
    k: Any  # next report index to fill
    ys: Any
    inv_prev: Any  # 1/err of the previous accepted step (PI memory)
    n_steps: Any
    n_acc: Any
    n_evals: Any
    status: Any


def lean_solve(
    vector_field,
    y0,
    args,
    ts,
    *,
    method="tsit5",
    rtol=1e-8,
    atol=1e-10,
    max_steps=100_000,
    dt0=None,
    norm=None,
    pre_step=None,
    post_step=None,
    report="step",
    pcoeff=0.0,
    icoeff=1.0,
    safety=0.9,
    factormin=0.2,
    factormax=10.0,
) -> LeanSolution:
    """Integrate dy/dt = vector_field(t, y, args) from ts[0] and report y at the times ts.

    Arguments:
        vector_field: `f(t, y, args) -> dy/dt`, y and dy flat arrays of shape (n,)
            (ravel pytree states before calling). Units: those of y per unit of t.
        y0: initial state at ts[0], shape (n,); its floating dtype (float32 or
            float64) is the dtype of the whole computation (times included).
        args: any pytree passed to `vector_field` (and to `pre_step`/`post_step`).
        ts: report times, shape (r,), non-decreasing; ts[0] is the start time.
            Steps never pass ts[-1].
        method: "tsit5" (5th order, 6 evaluations per step), "dop853" (8th order,
            12 per step; "dopri8" is an alias for it: Hairer's DOP853 tableau,
            the one of `jaxnh.solvers.DOP853`, not diffrax.Dopri8's
            coefficients), or a `Tableau`.
        rtol, atol: relative and absolute tolerance (may be traced). A step is
            accepted when norm(err / (atol + rtol·max(|y0|, |y1|))) < 1.
        max_steps: bound on step attempts (accepted + rejected).
        dt0: first step size; None selects it like diffrax (Hairer's algorithm,
            one extra evaluation).
        norm: `norm(scaled_error) -> scalar` replacing the RMS norm over all of y
            (e.g. to leave sensitivity columns out of error control).
        pre_step: `(t, y, args) -> (y_new, jumped)`, applied at the start of every
            step attempt. When `jumped` is true the first stage f(t, y_new) is
            evaluated again (no first-same-as-last reuse), and the step, its dense
            output and the carried state start from y_new.
        post_step: `(t0, y0, t1, y1, args) -> (y1_new, extra_error or None, reject)`,
            applied after every step attempt: y1_new replaces y1 (e.g. a
            projection onto constraints), `extra_error` (shape (n,)) is added to
            the error estimate before the norm, `reject=True` forces a rejection
            (the next step size is at most half the rejected one). When y1_new differs from y1,
            f(t1, y1_new) is evaluated again. Report times inside a step are
            interpolated from the step's own stages (unprojected); a report time
            that a step ends on gets y1_new.
        report: "step" (default: every report time is a step end; the
            controller's step size is kept across such clipped steps) or
            "interpolate" (report times inside a step are filled by the method's
            continuous extension: Tsit5's 4th-degree polynomial, free; DOP853's
            7th-order one, 3 more evaluations in steps that contain a report time;
            a step holds at most 2 report times strictly inside it). Measured
            (benchmarks/lean_loop.py, variator, 101 report times over ~80 natural
            DOP853 steps): "step" was faster for one trajectory and for a vmap
            batch, and more accurate with Tsit5 (whose interpolant is of lower
            order than its steps); "interpolate" wins when report times are much
            denser than the natural steps (see the report-density table there).
        pcoeff, icoeff, safety, factormin, factormax: PI controller as
            `diffrax.PIDController` (same defaults: integral control, 0.9, 0.2, 10).
            Measured on the variator (`python -m benchmarks.lean_loop --controllers`):
            PI settings (0.3, 0.4) and (0.2, 0.3) halved the rejections but took
            as many steps or more at matched error (DOP853 79 → 76 at 1e-8, 37 → 39
            at 1e-6; Tsit5 287 → 290 and 122 → 129), so integral control stays.

    Returns:
        `LeanSolution(ys, status, stats)`; see its docstring. No exception is
        raised for a failed solve: check `status` (0 = success).
    """
    tab = _tableau(method)
    if report not in ("interpolate", "step"):
        raise ValueError(f"lean_solve: report must be 'interpolate' or 'step'; got {report!r}")
    y0 = jnp.asarray(y0)
    if y0.ndim != 1:
        raise ValueError(f"lean_solve: y0 must be a flat 1-D array (ravel pytree states); got shape {y0.shape}")
    if not jnp.issubdtype(y0.dtype, jnp.floating):
        y0 = y0.astype(jnp.result_type(float))
    dtype = y0.dtype
    ts = jnp.asarray(ts).astype(dtype)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"lean_solve: ts must be a 1-D array of at least one time; got shape {ts.shape}")
    n, r = y0.shape[0], ts.shape[0]
    norm = rms_norm if norm is None else norm
    rtol = jnp.asarray(rtol, dtype)
    atol = jnp.asarray(atol, dtype)
    q = float(tab.error_order)
    beta1 = (icoeff + pcoeff) / q
    beta2 = -pcoeff / q
    t0 = ts[0]
    eps = jnp.finfo(dtype).eps

    # One traced and lowered sub-computation shared by every stage (as jaxnh.solvers does): the
    # unrolled stages would otherwise trace and lower the vector field once each.
    @eqx.filter_jit
    def vf(t, y, a):
        return jnp.asarray(vector_field(t, y, a)).astype(dtype)

    def floor(x):  # x minus ~100 ulp: a step ending past it is snapped onto x (as diffrax)
        return x - 100 * eps * jnp.maximum(jnp.abs(x), jnp.finfo(dtype).tiny)

    f0 = vf(t0, y0, args)
    n_evals0 = jnp.int32(1)
    if dt0 is None:
        # Hairer, Nørsett & Wanner (1993) §II.4, as diffrax's PIDController.
        yc = lax.stop_gradient(y0)
        fc = lax.stop_gradient(f0)
        scale = atol + jnp.abs(yc) * rtol

        def big_norm(x):
            # the norm is homogeneous: scaled by its largest entry first, so that rates of 1e160
            # against atol = 1e-10 give 1e170, not an overflowed square (inf, then a 0/0 step)
            m = jnp.max(jnp.abs(x))
            ok = jnp.isfinite(m) & (m > 0)
            return jnp.where(ok, m * norm(x / jnp.where(ok, m, 1)), norm(x))

        d0 = big_norm(yc / scale)
        d1 = big_norm(fc / scale)
        small = (d0 < 1e-5) | (d1 < 1e-5)
        h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1, d1)).astype(dtype)
        f1 = lax.stop_gradient(vf(t0 + h0, yc + h0 * fc, lax.stop_gradient(args)))
        d2 = big_norm((f1 - fc) / scale) / h0
        max_d = jnp.maximum(d1, d2)
        h1 = jnp.where(
            max_d <= 1e-15, jnp.maximum(1e-6, h0 * 1e-3), (0.01 / jnp.where(max_d <= 1e-15, 1, max_d)) ** (1 / q)
        )
        dt_init = jnp.minimum(100 * h0, h1).astype(dtype)
        n_evals0 = n_evals0 + 1
    else:
        dt_init = jnp.asarray(dt0, dtype)
    dt_init = lax.stop_gradient(dt_init)

    ys = jnp.full((r, n), jnp.nan, dtype).at[0].set(y0)
    zero = jnp.int32(0)
    carry = _Carry(
        t=t0,
        y=y0,
        f=f0,
        dt=dt_init,
        k=jnp.int32(1),
        ys=ys,
        inv_prev=jnp.ones((), dtype),
        n_steps=zero,
        n_acc=zero,
        n_evals=n_evals0,
        status=zero,
    )

    def cond(c):
        return (c.k < r) & (c.status == 0) & (c.n_steps < max_steps)

    def body(c):
        t, y, f = c.t, c.y, c.f
        n_evals = c.n_evals
        if pre_step is not None:
            y_new, jumped = pre_step(t, y, args)
            y_new = jnp.asarray(y_new).astype(dtype)
            jumped = jnp.asarray(jumped, bool)
            f = lax.cond(_any(jumped), lambda: jnp.where(jumped, vf(t, y_new, args), f), lambda: f)
            n_evals = n_evals + jumped.astype(jnp.int32)
            y = y_new
        if report == "step":
            target = ts[c.k]
        else:  # the end, or the report time after the next _INTERIOR_REPORTS ones
            target = ts[jnp.minimum(c.k + _INTERIOR_REPORTS, r - 1)]
        t1 = t + c.dt
        clipped = t1 > floor(target)
        t1 = jnp.where(clipped, target, t1)
        h = t1 - t
        y1, f1, err, fs = tab.step(vf, t, h, y, f, args)
        n_evals = n_evals + tab.evals_per_step
        reject = jnp.zeros((), bool)
        if post_step is not None:
            y1p, extra, reject = post_step(t, y, t1, y1, args)
            y1p = jnp.asarray(y1p).astype(dtype)
            if extra is not None:
                err = err + jnp.asarray(extra).astype(dtype)
            changed = jnp.any(y1p != y1)
            f1 = lax.cond(_any(changed), lambda: jnp.where(changed, vf(t1, y1p, args), f1), lambda: f1)
            n_evals = n_evals + changed.astype(jnp.int32)
            y1_end = y1p
            reject = jnp.asarray(reject, bool)
        else:
            y1_end = y1

        # error control (not differentiated)
        y1s = lax.stop_gradient(y1_end)
        ys_ = lax.stop_gradient(y)
        y1s = jnp.where(jnp.any(jnp.isnan(y1s)), ys_, y1s)
        scale = atol + rtol * jnp.maximum(jnp.abs(ys_), jnp.abs(y1s))
        e = norm(lax.stop_gradient(err) / scale)
        e = jnp.where(jnp.isfinite(e), e, jnp.inf)
        accept = (e < 1) & ~reject
        inv = 1 / e
        factor = safety * inv**beta1 if beta1 != 0 else jnp.asarray(safety, dtype)
        if beta2 != 0:
            factor = factor * c.inv_prev**beta2
        factor = jnp.clip(factor, jnp.where(accept, 1, factormin), jnp.where(accept, factormax, safety))
        if post_step is not None:
            factor = jnp.where(reject, jnp.minimum(factor, 0.5), factor)
        dt_next = (h * factor).astype(dtype)
        # a step shortened to land on a report time (or the end) does not shrink the next one
        dt_next = jnp.where(clipped & accept, jnp.maximum(dt_next, c.dt), dt_next)
        inv_keep = jnp.where((inv == 0) | jnp.isinf(inv), 1, inv)
        inv_prev = jnp.where(accept, inv_keep, c.inv_prev)

        # reports (one row written at a time: no select over the whole output buffer)
        ys_out, k = c.ys, c.k
        if report == "step":
            hit = accept & clipped
            kk = jnp.minimum(k, r - 1)
            ys_out = ys_out.at[kk].set(jnp.where(hit, y1_end, ys_out[kk]))
            k = jnp.where(hit, k + 1, k)
        else:
            # at most _INTERIOR_REPORTS report times lie strictly inside a step (see `target`): they are
            # written straight-line, without an inner loop (which under vmap would select the whole
            # output buffer on every iteration)
            need = accept & (ts[jnp.minimum(k, r - 1)] <= t1) & (k < r)
            idx = [jnp.minimum(k + j, r - 1) for j in range(_INTERIOR_REPORTS + 1)]

            def rows():  # the state at the next report times, by the continuous extension
                coeffs = tab.dense_prepare(vf, t, h, y, y1, fs, args)[0]
                hh = jnp.where(h == 0, 1, h)
                return jnp.stack(
                    [jnp.where(ts[i] == t1, y1_end, tab.dense_eval(coeffs, y, (ts[i] - t) / hh)) for i in idx]
                )

            # computed only in steps that hold a report time (for any member of a vmap batch); the
            # rows are written outside the conditional, in place
            yks = lax.cond(_any(need), rows, lambda: jnp.zeros((len(idx), n), dtype))
            k0 = k
            for j, i in enumerate(idx):
                valid = accept & (k0 + j < r) & (ts[i] <= t1)
                ys_out = ys_out.at[i].set(jnp.where(valid, yks[j], ys_out[i]))
                k = k + valid.astype(jnp.int32)
            n_evals = n_evals + jnp.where(need, tab.dense_evals, 0)

        n_steps = c.n_steps + 1
        # the step cannot advance t: after a rejection the next step would not move t, or this
        # attempt itself did not (t + dt == t without landing on a report time)
        # (or a rejected step onto a report time within ~100 ulp, which would be attempted unchanged)
        underflow = (~accept & ((t + dt_next <= t) | ~jnp.isfinite(dt_next) | (t + dt_next > floor(target)))) | (
            (h <= 0) & ~clipped
        )
        status = jnp.where(underflow, 2, 0).astype(jnp.int32)
        return _Carry(
            t=jnp.where(accept, t1, t),
            y=jnp.where(accept, y1_end, y),
            f=jnp.where(accept, f1, f),
            dt=dt_next,
            k=k,
            ys=ys_out,
            inv_prev=inv_prev,
            n_steps=n_steps,
            n_acc=c.n_acc + accept.astype(jnp.int32),
            n_evals=n_evals,
            status=status,
        )

    out = lax.while_loop(cond, body, carry)
    status = jnp.where((out.status == 0) & (out.k < r), 1, out.status).astype(jnp.int32)  # ran out of steps
    stats = dict(
        num_steps=out.n_steps,
        num_accepted_steps=out.n_acc,
        num_rejected_steps=out.n_steps - out.n_acc,
        rhs_evaluations=out.n_evals,
    )
    return LeanSolution(ys=out.ys, status=status, stats=stats, t_final=out.t, y_final=out.y)
