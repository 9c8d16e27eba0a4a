"""Data out: a `Solution` as a pandas DataFrame or an xarray Dataset, a `FitResult` as JSON-ready data.

pandas and xarray are optional (the `data` extra): each is imported only inside
the function that needs it (`solution_to_dataframe`, `solution_to_xarray`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


__all__ = [
    "solution_to_dataframe",
    "solution_to_xarray",
    "fit_result_to_dict",
    "json_safe",
    "fit_status",
    "FIT_STATUSES",
]

FIT_STATUSES = ("fitted", "not_converged", "not_identifiable", "simulation_failed", "non_finite")


def json_safe(x: Any) -> Any:
    """`x` as plain JSON data: dicts (string keys), lists, str, bool, int, float
    and None; NumPy/JAX arrays become (nested) lists and every non-finite
    float (NaN, ±inf) becomes None, so `json.dumps(..., allow_nan=False)`
    cannot fail half-way. Raises TypeError for anything else."""
    if x is None or isinstance(x, (bool, str)):
        return x
    if isinstance(x, (int, np.integer)) and not isinstance(x, np.bool_):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if hasattr(x, "__array__") or isinstance(x, np.ndarray):
        a = np.asarray(x)
        if a.dtype == object:
            return [json_safe(v) for v in a.tolist()]
        if a.dtype.kind in "fc":
            a = np.real(a).astype(float)
            return json_safe(a.tolist()) if a.ndim else json_safe(float(a))
        return json_safe(a.tolist())
    raise TypeError(f"json_safe: cannot represent a {type(x).__name__} as JSON")


def fit_status(result) -> str:
    """One word for a `FitResult`: "fitted" when converged, identifiable and every
    reported number finite; else "simulation_failed", "non_finite",
    "not_converged" or "not_identifiable" (the first that applies)."""
    if "SIMULATION FAILED" in result.message:
        return "simulation_failed"
    nums = [
        np.asarray(result.values, dtype=float),
        np.asarray([result.rms_residual, result.chi2_dof], dtype=float),
        np.asarray(result.q0, dtype=float),
        np.asarray(result.qd0, dtype=float),
    ]
    if not all(np.all(np.isfinite(a)) for a in nums):
        return "non_finite"
    if not result.converged:
        return "not_converged"
    if not result.identifiable or not np.all(np.isfinite(np.asarray(result.std, dtype=float))):
        return "not_identifiable"
    return "fitted"


def fit_result_to_dict(result, arrays: bool = False) -> dict:
    """`FitResult.to_dict`: see there. Every number is a finite float or None."""
    par = result.problem.par
    free = tuple(par.names)
    status = fit_status(result)
    est = result.estimates
    lof = result.lack_of_fit
    ident = result.identifiability
    out = {
        "status": status,
        "ok": status == "fitted",
        "converged": bool(result.converged),
        "identifiable": bool(result.identifiable),
        "iterations": int(result.iterations),
        "message": result.message,
        "parameters": {k: {"value": est[k]["value"], "std": est[k]["std"]} for k in free if k in est},
        "positive": [n for n, p in zip(par.names, par.positive) if p],
        "initial_state": {k: v for k, v in est.items() if k not in free},
        "labels": list(result.labels),
        "values": result.values,
        "std": result.std,
        "covariance": result.covariance,
        "q0": result.q0,
        "qd0": result.qd0,
        "observe": list(result.observe),
        "n_samples": int(np.shape(result.t)[0]),
        "t_range": [result.t[0], result.t[-1]] if np.shape(result.t)[0] else None,
        "rms_residual": result.rms_residual,
        "rms_by_channel": result.rms_by_channel,
        "noise": result.noise,
        "chi2_dof": result.chi2_dof,
        "lack_of_fit": {
            "significant": bool(lof.significant),
            "s2": lof.s2,
            "s2_threshold": lof.threshold,
            "model_error_over_noise": lof.model_error_over_noise,
            "model_error_rms": lof.model_error_rms,
            "residual_autocorrelation": lof.autocorrelation,
            "message": lof.message,
        },
        "identifiability": {
            "identifiable": bool(ident.identifiable),
            "condition": ident.condition,
            "singular_values": ident.singular_values,
            "undetermined": ident.undetermined,
            "poorly_determined": list(ident.poorly_determined),
            "messages": list(ident.messages),
        },
        "gn_step": result.gn_step,
        "optimizer": result.optimizer,
        "differentiation": result.differentiation,
        "shooting": int(result.shooting),
        "elapsed_s": result.elapsed,
    }
    if arrays:
        out.update(t=result.t, measured=result.measured, fitted=result.fitted, residuals=result.residuals)
    return json_safe(out)


def _names(sol, s: int) -> tuple:
    names = getattr(sol, "names", None)
    if names is not None and len(names) == s:
        return tuple(str(n) for n in names)
    return tuple(f"q{i}" for i in range(s))


def solution_to_dataframe(sol):
    """A `Solution` as a `pandas.DataFrame`, one row per report time.

    Columns: the coordinates by name (e.g. "phi1", rad), the velocities as
    "<name>_dot" (rad/s), and when recorded "energy" (J), "lambda_<i>" (the
    multipliers) and "residual_<i>" (the constraint values), and for a
    mechanism with `kinematics` the speeds "u_<i>". The index is "t"
    (s). After a failed solve the rows past the failure are NaN (as in the
    Solution); `df.attrs["message"]` holds `sol.message` and
    `df.attrs["success"]` whether the solve succeeded.

    A batched Solution (from `jax.vmap` or `jaxnh.sweep`: arrays with leading
    batch axes) gives a long table with a two-level index ("batch", "t"),
    "batch" counting the batch elements in C order, and a "success" column.

    Raises:
        ImportError when pandas is not installed; ValueError for a traced
        (inside jit) or inconsistent Solution.
    """
    try:
        import pandas as pd
    except ImportError:
        raise ImportError(
            "Solution.to_dataframe needs pandas (pip install pandas); the arrays are "
            "sol.ts, sol.q, sol.qd, sol.energy, sol.multipliers, sol.residual"
        ) from None
    q, qd, ts, batch_shape, n, s = _host_arrays(sol, "to_dataframe")
    names = _names(sol, s)
    optional = {}
    for attr, label in (("energy", "energy"), ("multipliers", "lambda"), ("residual", "residual")):
        v = getattr(sol, attr, None)
        if v is not None:
            optional[label] = np.asarray(v)
    status = getattr(sol, "status", None)
    success = np.asarray(getattr(sol, "success", np.ones(batch_shape, bool)))

    speeds = getattr(sol, "speeds", None)
    if speeds is not None:  # a mechanism with `kinematics`: the speeds too
        optional["u"] = np.asarray(speeds)
    nb = int(np.prod(batch_shape)) if batch_shape else 1
    t = np.broadcast_to(np.asarray(ts, dtype=float), batch_shape + (n,)) if ts.ndim > 1 else ts
    if np.shape(t)[-1:] != (n,) or (ts.ndim > 1 and ts.shape != batch_shape + (n,)):
        raise ValueError(f"to_dataframe: sol.ts has shape {ts.shape}, inconsistent with sol.q {q.shape}")

    # every column at once, as (batch members × report times) rows in C order: one frame built
    # from whole arrays (a frame per member and a concatenation cost 33× more for 2000 members)
    def rows(v, tail):
        return np.asarray(v).reshape((nb * n,) + tail)

    cols: dict = {}
    if batch_shape:
        cols["success"] = np.repeat(
            success.reshape(-1) if success.shape == batch_shape else np.full(nb, bool(np.all(success))), n
        )
    qr, qdr = rows(q, (s,)), rows(qd, (s,))
    for j, nm in enumerate(names):
        cols[nm] = qr[:, j]
    for j, nm in enumerate(names):
        cols[f"{nm}_dot"] = qdr[:, j]
    for label, v in optional.items():
        tail = v.shape[len(batch_shape) + 1 :]
        if v.shape[: len(batch_shape) + 1] != batch_shape + (n,):
            raise ValueError(f"to_dataframe: sol.{label} has shape {v.shape}, inconsistent with sol.q {q.shape}")
        if not tail:
            cols[label] = rows(v, ())
        else:
            vr = rows(v, tail)
            for k in range(tail[0]):
                cols[f"{label}_{k}"] = vr[:, k]
    times = np.asarray(t, dtype=float).reshape(-1) if batch_shape else np.asarray(t, dtype=float)
    if not batch_shape:
        df = pd.DataFrame(cols, index=pd.Index(times, name="t"))
        try:
            df.attrs["message"] = sol.message
        except Exception:
            df.attrs["message"] = ""
        df.attrs["success"] = bool(np.all(success))
        return df
    index = pd.MultiIndex.from_arrays([np.repeat(np.arange(nb), n), times], names=["batch", "t"])
    df = pd.DataFrame(cols, index=index)
    df.attrs["batch_shape"] = tuple(int(x) for x in batch_shape)
    df.attrs["success"] = bool(np.all(success))
    if status is not None:
        df.attrs["message"] = "success" if df.attrs["success"] else "some batch elements failed (see 'success')"
    return df


# attrs of the Dataset's variables: "units" is exact where one unit applies (t, energy); the coordinates,
# and with them the velocities, multipliers and constraint values, have each mechanism's own units
_XARRAY_ATTRS = {
    "t": {"long_name": "time", "units": "s"},
    "q": {"long_name": "generalized coordinates", "units": "each coordinate's own (rad for an angle, m for a length)"},
    "qd": {"long_name": "generalized velocities", "units": "each coordinate's own per second (rad/s, m/s)"},
    "energy": {"long_name": "total energy T + V", "units": "J"},
    "multipliers": {
        "long_name": "constraint multipliers λ (constraint forces Aᵀλ, A = ∂c/∂qd)",
        "units": "generalized force per unit of the constraint's coefficient (N·m for the variator)",
    },
    "residual": {
        "long_name": "constraint values c(q, qd, t), zero for an exact solution",
        "units": "the constraint's own",
    },
    "success": {"long_name": "whether the solve reached its end"},
}


def _host_arrays(sol, who: str):
    """(q, qd, ts) of a Solution as NumPy arrays, its batch shape, n report times and s coordinates;
    a ValueError naming `who` for a traced Solution or a q of the wrong rank."""
    try:
        q = np.asarray(sol.q)
        qd = np.asarray(sol.qd)
        ts = np.asarray(sol.ts)
    except Exception as e:  # a tracer: inside jit/vmap
        raise ValueError(
            f"{who}: the Solution holds traced values (inside jax.jit/vmap); call it on the "
            f"returned Solution outside the transformation ({type(e).__name__})"
        ) from None
    if q.ndim < 2:
        raise ValueError(f"{who}: sol.q must be (n, s) or (batch..., n, s); got shape {q.shape}")
    return q, qd, ts, q.shape[:-2], *q.shape[-2:]


def solution_to_xarray(sol):
    """A `Solution` as an `xarray.Dataset`: `Solution.to_xarray`, see there."""
    try:
        import xarray as xr
    except ImportError:
        raise ImportError(
            "Solution.to_xarray needs xarray (pip install xarray, or the data extra: pip install 'jaxnh[data]'); "
            "the arrays are sol.ts, sol.q, sol.qd, sol.energy, sol.multipliers, sol.residual"
        ) from None
    q, qd, ts, batch_shape, n, s = _host_arrays(sol, "to_xarray")
    nb = int(np.prod(batch_shape))
    lead = ("batch",) if batch_shape else ()

    def shaped(v, tail, label):
        v = np.asarray(v)
        if v.shape != batch_shape + tail:
            raise ValueError(f"to_xarray: sol.{label} has shape {v.shape}, inconsistent with sol.q {q.shape}")
        return v.reshape((nb,) + tail) if batch_shape else v

    if ts.shape not in ((n,), batch_shape + (n,)):
        raise ValueError(f"to_xarray: sol.ts has shape {ts.shape}, inconsistent with sol.q {q.shape}")
    rows = np.broadcast_to(ts, batch_shape + (n,)).reshape(-1, n)
    if not all(np.array_equal(r, rows[0], equal_nan=True) for r in rows[1:]):
        raise ValueError(
            "to_xarray: the batch elements were reported at different times (sol.ts differs between them, "
            "e.g. an event stopped some runs early), so they share no time axis; convert the elements one at "
            "a time, or use to_dataframe (a long table)"
        )
    data = {
        "q": (lead + ("t", "coordinate"), shaped(q, (n, s), "q")),
        "qd": (lead + ("t", "coordinate"), shaped(qd, (n, s), "qd")),
    }
    for name, dims in (("energy", ("t",)), ("multipliers", ("t", "constraint")), ("residual", ("t", "constraint"))):
        v = getattr(sol, name, None)
        if v is not None:
            v = np.asarray(v)
            data[name] = (lead + dims, shaped(v, (n,) + v.shape[len(batch_shape) + 1 :], name))
    if "multipliers" in data and "residual" in data and data["multipliers"][1].shape != data["residual"][1].shape:
        # one multiplier per constraint row is the rule; should they differ, they cannot share a dimension
        data["multipliers"] = (lead + ("t", "multiplier"), data["multipliers"][1])
    success = np.asarray(getattr(sol, "success", True))
    if success.shape != batch_shape:
        success = np.full(batch_shape, bool(np.all(success)))
    data["success"] = (lead, success.reshape(nb) if batch_shape else success)
    coords: dict[str, Any] = {"t": ("t", rows[0].astype(float)), "coordinate": ("coordinate", list(_names(sol, s)))}
    if batch_shape:
        coords["batch"] = ("batch", np.arange(nb))
    ds = xr.Dataset({k: (dims, v, _XARRAY_ATTRS[k]) for k, (dims, v) in data.items()}, coords=coords)
    ds["t"].attrs.update(_XARRAY_ATTRS["t"])
    try:
        ds.attrs["message"] = str(sol.message)
    except Exception:
        ds.attrs["message"] = ""
    if batch_shape:
        ds.attrs["batch_shape"] = [int(x) for x in batch_shape]
    return ds
