"""Measured records: reading, checking, the embedded data set, noise levels.

A record holds, at sample times t (s), the measured coordinates (encoder
angles, rad) and the applied inputs (torques, N·m). Coordinates are what a
fit compares with the simulation; inputs are known functions of time that
go into the model's parameters (interpolated between samples, see
`jaxnh.profiles.Sampled`).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
from importlib import resources

import jax.numpy as jnp
import numpy as np

__all__ = ["Record", "read_csv", "write_csv", "load_default", "noise_level", "DEFAULT_DATA", "MIN_SAMPLES"]

DEFAULT_DATA = "variator_record.csv"
MIN_SAMPLES = 20


@dataclasses.dataclass(frozen=True)
class Record:
    """A measured record.

    Attributes:
        t: sample times (n,), s, strictly increasing.
        channels: measured coordinates by name, each (n,), in the units of
            the coordinate (rad for encoder angles).
        inputs: applied inputs by name, each (n,), e.g. torques in N·m.
        source: where the record came from (a path, or a description).
    """

    t: np.ndarray
    channels: dict
    inputs: dict = dataclasses.field(default_factory=dict)
    source: str = ""

    def __post_init__(self):
        t = np.asarray(self.t, dtype=float)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "channels", {k: np.asarray(v, dtype=float) for k, v in self.channels.items()})
        object.__setattr__(self, "inputs", {k: np.asarray(v, dtype=float) for k, v in self.inputs.items()})
        _check_columns({"t": t, **self.channels, **self.inputs}, self.source or "Record")

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.shape[0])

    def head(self, n: int) -> "Record":
        """The first n samples (for quick tests and previews)."""
        return Record(self.t[:n], {k: v[:n] for k, v in self.channels.items()},
                      {k: v[:n] for k, v in self.inputs.items()}, self.source + f" (first {n} samples)")

    def every(self, k: int) -> "Record":
        """Every k-th sample (a lower sampling rate)."""
        return Record(self.t[::k], {c: v[::k] for c, v in self.channels.items()},
                      {c: v[::k] for c, v in self.inputs.items()}, self.source + f" (every {k}th sample)")

    def observed(self, names) -> np.ndarray:
        """The channels `names` stacked as (n, len(names))."""
        missing = [c for c in names if c not in self.channels]
        if missing:
            raise ValueError(f"observe={tuple(names)!r}: the record has no channel(s) {missing}; it has {list(self.channels)}")
        return np.stack([self.channels[c] for c in names], axis=1)


def _check_columns(cols: dict, where: str, min_samples: int = MIN_SAMPLES) -> None:
    t = cols["t"]
    if t.ndim != 1:
        raise ValueError(f"{where}: t must be 1-D; got shape {t.shape}")
    for name, v in cols.items():
        if v.shape != t.shape:
            raise ValueError(f"{where}: column {name!r} has {v.shape[0] if v.ndim else 'no'} samples, t has {t.shape[0]}")
        bad = np.nonzero(~np.isfinite(v))[0]
        if bad.size:
            raise ValueError(
                f"{where}: column {name!r} has non-finite values (NaN or inf) at {bad.size} sample(s), "
                f"first at row {int(bad[0])} (t = {t[bad[0]] if np.isfinite(t[bad[0]]) else 'n/a'}); "
                "expected finite numbers everywhere — remove or fill those samples"
            )
    if t.shape[0] < min_samples:
        raise ValueError(f"{where}: too few samples: {t.shape[0]}; expected at least {min_samples}")
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.nonzero(dt <= 0)[0][0])
        kind = "repeated" if dt[i] == 0 else "decreasing"
        raise ValueError(
            f"{where}: times must be strictly increasing; {kind} time at rows {i} and {i + 1} "
            f"(t = {t[i]!r}, {t[i + 1]!r})"
        )


def read_csv(path, coordinates=("phi1", "phi2"), inputs=("M1", "M2"), min_samples: int = MIN_SAMPLES) -> Record:
    """Read a measured record from a CSV file with a header row.

    Columns (any order; extra columns are ignored; lines starting with `#`
    are comments): `t` (s), the coordinates (default `phi1, phi2`, rad) and
    the inputs (default `M1, M2`, N·m).

    Raises:
        ValueError naming the file and the problem: missing columns, a
        non-number, non-finite values, repeated or decreasing times, fewer
        than `min_samples` samples.
    """
    path = os.fspath(path)
    with open(path, newline="") as f:
        text = f.read()
    return _parse(text, path, tuple(coordinates), tuple(inputs), min_samples)


def _parse(text: str, where: str, coordinates: tuple, inputs: tuple, min_samples: int) -> Record:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{where}: no header row and no data (expected columns t, {', '.join(coordinates + inputs)})")
    rows = list(csv.reader(io.StringIO("\n".join(lines))))
    header = [h.strip() for h in rows[0]]
    wanted = ("t",) + coordinates + inputs
    missing = [c for c in wanted if c not in header]
    if missing:
        raise ValueError(f"{where}: missing column(s) {missing}; the header has {header}; expected {list(wanted)}")
    idx = {c: header.index(c) for c in wanted}
    cols = {c: np.empty(len(rows) - 1) for c in wanted}
    for r, row in enumerate(rows[1:], start=1):
        if len(row) < len(header):
            raise ValueError(f"{where}: data row {r} has {len(row)} fields; the header has {len(header)}")
        for c, j in idx.items():
            try:
                cols[c][r - 1] = float(row[j])
            except ValueError:
                raise ValueError(f"{where}: data row {r}, column {c!r}: {row[j]!r} is not a number") from None
    _check_columns(cols, where, min_samples)
    return Record(cols["t"], {c: cols[c] for c in coordinates}, {c: cols[c] for c in inputs}, where)


def write_csv(record: Record, path, comments=()) -> None:
    """Write `record` as CSV: comment lines, a header `t, channels..., inputs...`, rows."""
    names = ["t"] + list(record.channels) + list(record.inputs)
    cols = [record.t] + list(record.channels.values()) + list(record.inputs.values())
    with open(path, "w", newline="") as f:
        for c in comments:
            f.write(f"# {c}\n")
        f.write(",".join(names) + "\n")
        for row in zip(*cols):
            f.write(",".join(f"{x:.10g}" for x in row) + "\n")


def load_default() -> Record:
    """The embedded variator record (see `jaxnh/data/README.md` for how it was
    made and the true values): 6 s at 250 Hz, two quantised encoders, motor
    and load torques, a smooth change of the transmission ratio."""
    text = resources.files("jaxnh").joinpath("data", DEFAULT_DATA).read_text()
    return _parse(text, f"jaxnh/data/{DEFAULT_DATA}", ("phi1", "phi2"), ("M1", "M2"), MIN_SAMPLES)


def noise_level(y, axis: int = 0):
    """Standard deviation of white measurement noise in a smooth sampled signal.

    Third differences remove a smooth motion (what is left of it is of order
    dt³ times the third derivative, negligible at encoder sampling rates)
    and multiply the variance of independent noise by 20, so
    `sigma² ≈ mean((Δ³y)²) / 20`. This holds for any distribution of the
    noise, e.g. the uniform error of a quantised encoder on a moving shaft
    (step²/12); it is not robust to outliers. Works under `jit`/`vmap`.

    Arguments:
        y: samples, e.g. (n,) or (n, channels), units of the signal.
        axis: the time axis.

    Returns:
        sigma per channel, units of y.
    """
    d3 = jnp.diff(jnp.asarray(y), n=3, axis=axis)
    return jnp.sqrt(jnp.mean(d3**2, axis=axis) / 20.0)
