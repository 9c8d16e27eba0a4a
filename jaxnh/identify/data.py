"""Measured records: reading, checking, the embedded data set, noise levels.

A record holds, at sample times t (s), the measured coordinates (encoder
angles, rad) and the applied inputs (torques, N·m). Coordinates are what a
fit compares with the simulation; inputs are known functions of time that
go into the model's parameters (interpolated between samples, see
`jaxnh.profiles.Sampled`).

Positions in messages: problems found in a file name the 1-based line number
of the file (comment and blank lines counted, as an editor shows them);
problems in a record built in memory (`Record(...)`, `Record.from_dataframe`)
name the 0-based sample index.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import math
import os
import time
from importlib import resources
from typing import Any, Callable, Iterable, Sequence

import jax
import numpy as np

from jaxnh._base.atomic import atomic_write
from jaxnh._base.host import array_module
from jaxnh._base.types import ArrayInput


__all__ = [
    "Record",
    "read_csv",
    "write_csv",
    "load_default",
    "noise_level",
    "DEFAULT_DATA",
    "MIN_SAMPLES",
    "MAX_SAMPLES",
]

DEFAULT_DATA = "variator_record.csv"
MIN_SAMPLES = 20
MAX_SAMPLES = 200_000
"""`read_csv` stops and refuses a record with more samples than this (pass
`max_samples=` or keep every k-th sample with `every=`): a fit's memory grows
with the samples (its Jacobian alone is samples × channels × unknowns)."""

_CHUNK = 16384  # samples per block while reading
MAX_LINE_BYTES = 1 << 20  # a longer line is not a row of numbers


def _num(x) -> str:
    """A number for a message: plain digits, never `np.float64(...)`."""
    try:
        return repr(float(x))
    except (TypeError, ValueError):
        return repr(x)


def _at(i: int, lines=None) -> str:
    """Position of sample `i` for a message: the file's line, or the 0-based sample index."""
    return f"line {int(lines[i])}" if lines is not None else f"sample {int(i)}"


@dataclasses.dataclass(frozen=True)
class Record:
    """A measured record.

    Attributes:
        t: sample times (n,), s, strictly increasing.
        channels: measured coordinates by name, each (n,), in the units of
            the coordinate (rad for encoder angles).
        inputs: applied inputs by name, each (n,), e.g. torques in N·m.
        source: where the record came from (a path, or a description).
        sigma: measurement noise standard deviation per channel
            ({name: value}, units of the channel), or None. `jaxnh.fit` uses
            it when called without `noise=`; without either, the noise is
            estimated from the data.
    """

    t: np.ndarray
    channels: dict
    inputs: dict = dataclasses.field(default_factory=dict)
    source: str = ""
    sigma: dict | float | None = None

    def __post_init__(self):
        where = self.source or "Record"
        t = _as_column(self.t, "t", where)
        object.__setattr__(self, "t", t)
        if not isinstance(self.channels, dict) or not self.channels:
            raise ValueError(f"{where}: channels must be a non-empty dict {{name: samples}}; got {self.channels!r:.80}")
        if not isinstance(self.inputs, dict):
            raise ValueError(f"{where}: inputs must be a dict {{name: samples}}; got {type(self.inputs).__name__}")
        object.__setattr__(self, "channels", {str(k): _as_column(v, k, where) for k, v in self.channels.items()})
        object.__setattr__(self, "inputs", {str(k): _as_column(v, k, where) for k, v in self.inputs.items()})
        both = set(self.channels) & set(self.inputs)
        if both or "t" in self.channels or "t" in self.inputs:
            raise ValueError(
                f"{where}: a name is used twice (time, channel and input names must differ): "
                f"{sorted(both | ({'t'} & (set(self.channels) | set(self.inputs))))}"
            )
        if self.sigma is not None:
            object.__setattr__(self, "sigma", _check_sigma(self.sigma, tuple(self.channels), where))
        _check_columns({"t": t, **self.channels, **self.inputs}, where)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.shape[0])

    def head(self, n: int) -> "Record":
        """The first n samples (for quick tests and previews)."""
        return Record(
            self.t[:n],
            {k: v[:n] for k, v in self.channels.items()},
            {k: v[:n] for k, v in self.inputs.items()},
            self.source + f" (first {n} samples)",
            self.sigma,
        )

    def every(self, k: int) -> "Record":
        """Every k-th sample (a lower sampling rate)."""
        return Record(
            self.t[::k],
            {c: v[::k] for c, v in self.channels.items()},
            {c: v[::k] for c, v in self.inputs.items()},
            self.source + f" (every {k}th sample)",
            self.sigma,
        )

    def observed(self, names: Sequence[str]) -> np.ndarray:
        """The channels `names` stacked as (n, len(names))."""
        missing = [c for c in names if c not in self.channels]
        if missing:
            raise ValueError(
                f"observe={tuple(names)!r}: the record has no channel(s) {missing}; it has {list(self.channels)}"
            )
        return np.stack([self.channels[c] for c in names], axis=1)

    @classmethod
    def from_dataframe(
        cls,
        df: Any,
        time: str | None = "t",
        observed: str | Sequence[str] | None = None,
        inputs: str | Sequence[str] = (),
        sigma: dict | float | None = None,
        source: str = "",
    ) -> "Record":
        """A record from a pandas DataFrame (pandas is needed only for this).

        Arguments:
            df: a `pandas.DataFrame` with one row per sample.
            time: the column of sample times (s), strictly increasing; or
                None to use the DataFrame's index (e.g. a float index of seconds).
            observed: the columns of measured coordinates, named like the
                mechanism's coordinates (e.g. `["phi1", "phi2"]`, rad); default:
                every column that is neither the time nor an input.
            inputs: the columns of applied inputs (e.g. torques, N·m).
            sigma: measurement noise standard deviation per observed column
                (a number for all, or {column: value}; units of the column),
                or None to estimate it from the data in the fit.
            source: a description kept in `record.source`.

        Raises:
            ImportError when pandas is not installed; ValueError naming the
            column and the 0-based row position of a missing (NaN), infinite
            or non-numeric value, repeated or decreasing times, a missing column.
        """
        try:
            import pandas as pd
        except ImportError:
            raise ImportError(
                "Record.from_dataframe needs pandas (pip install pandas); without it, build the "
                "record from arrays: Record(t, {name: samples}, {name: samples})"
            ) from None
        where = source or "DataFrame"
        if not isinstance(df, pd.DataFrame):
            raise TypeError(f"Record.from_dataframe: df must be a pandas.DataFrame; got {type(df).__name__}")
        cols = [str(c) for c in df.columns]
        if len(set(cols)) != len(cols):
            dup = sorted({c for c in cols if cols.count(c) > 1})
            raise ValueError(f"{where}: repeated column name(s) {dup}")
        inputs = (inputs,) if isinstance(inputs, str) else tuple(inputs)
        if observed is None:
            observed = tuple(c for c in df.columns if c != time and c not in inputs)
        else:
            observed = (observed,) if isinstance(observed, str) else tuple(observed)
        if not observed:
            raise ValueError(f"{where}: no observed columns; pass observed=[...] (the DataFrame has {cols})")
        wanted = ((time,) if time is not None else ()) + observed + inputs
        missing = [c for c in wanted if c not in df.columns]
        if missing:
            raise ValueError(f"{where}: missing column(s) {missing}; the DataFrame has {cols}")

        def column(values, name):
            try:
                return np.asarray(values, dtype=float)
            except (TypeError, ValueError):
                arr = np.asarray(values, dtype=object)
                for i, v in enumerate(arr):
                    try:
                        float(v)
                    except (TypeError, ValueError):
                        raise ValueError(f"{where}: column {name!r}, sample {i}: {v!r} is not a number") from None
                raise

        t = column(df.index.to_numpy() if time is None else df[time].to_numpy(), "t" if time is None else time)
        ch = {str(c): column(df[c].to_numpy(), c) for c in observed}
        inp = {str(c): column(df[c].to_numpy(), c) for c in inputs}
        if isinstance(sigma, dict):
            sigma = {str(k): v for k, v in sigma.items()}
        return cls(t, ch, inp, where, sigma)


def _as_column(v, name, where) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: column {name!r} must be numbers; got {type(v).__name__}") from None
    if a.ndim != 1:
        raise ValueError(f"{where}: column {name!r} must be 1-D (one value per sample); got shape {a.shape}")
    return a


def _check_sigma(sigma, channels, where) -> dict:
    if isinstance(sigma, dict):
        unknown = [k for k in sigma if k not in channels]
        if unknown:
            raise ValueError(f"{where}: sigma given for {unknown}, which are not observed channels {list(channels)}")
        out = {k: sigma[k] for k in channels if k in sigma}
    else:
        out = {k: sigma for k in channels}
    for k, v in out.items():
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: sigma for {k!r} must be a number; got {v!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise ValueError(
                f"{where}: sigma for {k!r} must be finite and > 0 (a noise standard deviation); got {_num(v)}"
            )
        out[k] = v
    return out


def _check_columns(cols: dict, where: str, min_samples: int = MIN_SAMPLES, lines=None) -> None:
    """Shapes, finiteness, enough samples, strictly increasing time; `lines` maps
    sample index to the file's line number for messages (None: say sample index)."""
    t = cols["t"]
    if t.ndim != 1:
        raise ValueError(f"{where}: t must be 1-D; got shape {t.shape}")
    for name, v in cols.items():
        if v.shape != t.shape:
            raise ValueError(
                f"{where}: column {name!r} has {v.shape[0] if v.ndim else 'no'} samples, t has {t.shape[0]}"
            )
        bad = np.nonzero(~np.isfinite(v))[0]
        if bad.size:
            i = int(bad[0])
            ti = f"t = {_num(t[i])}" if np.isfinite(t[i]) else "t n/a"
            raise ValueError(
                f"{where}: column {name!r} has non-finite values (NaN or inf) at {bad.size} sample(s), "
                f"first at {_at(i, lines)} ({ti}); expected finite numbers everywhere — remove or fill those samples"
            )
    if t.shape[0] < min_samples:
        raise ValueError(f"{where}: too few samples: {t.shape[0]}; expected at least {min_samples}")
    with np.errstate(over="ignore", invalid="ignore"):
        dt = np.diff(t)
    bad = ~(np.isfinite(dt) & (dt > 0))
    if np.any(bad):
        i = int(np.nonzero(bad)[0][0])
        if not np.isfinite(dt[i]):
            raise ValueError(
                f"{where}: the time step between {_at(i, lines)} and {_at(i + 1, lines)} overflows "
                f"(t = {_num(t[i])}, {_num(t[i + 1])}); times must be in seconds of a finite range"
            )
        kind = "repeated" if dt[i] == 0 else "decreasing"
        raise ValueError(
            f"{where}: times must be strictly increasing; {kind} time at {_at(i, lines)} and {_at(i + 1, lines)} "
            f"(t = {_num(t[i])}, {_num(t[i + 1])})"
        )


def read_csv(
    path: str | os.PathLike[str],
    coordinates: Sequence[str] = ("phi1", "phi2"),
    inputs: Sequence[str] = ("M1", "M2"),
    min_samples: int = MIN_SAMPLES,
    max_samples: int | None = MAX_SAMPLES,
    every: int = 1,
    progress: Callable[[int, int], Any] | None = None,
) -> Record:
    """Read a measured record from a CSV file with a header row.

    Format: UTF-8 text (a byte-order mark is accepted), comma-separated, one
    header row, then one row per sample. Columns in any order, extra columns
    ignored; lines starting with `#` and blank lines are skipped. Needed:
    `t` (s), the coordinates (default `phi1, phi2`, rad) and the inputs
    (default `M1, M2`, N·m). Numbers are plain decimal or exponent notation
    (`-1.5`, `2e-3`; `nan`/`inf` are read and then refused as non-finite);
    Python-only spellings such as `1_000` or non-ASCII digits are refused.

    The file is read line by line into blocks of arrays, so memory stays
    proportional to the samples kept.

    Arguments:
        path: the file.
        coordinates, inputs: the column names to read.
        min_samples: fewer samples is an error.
        max_samples: more samples (after `every`) is an error, found as soon
            as the limit is passed, without reading the rest of the file
            (None: no limit).
        every: keep every k-th data row (1 = all), to thin a dense record.
        progress: optional callable `progress(bytes_read, total_bytes)`, called
            about once a second while reading.

    Raises:
        ValueError naming the file, the 1-based line number and the problem:
        not UTF-8 text, missing or repeated columns, a row with the wrong
        number of fields, a non-number, a value beyond the float range,
        non-finite values, repeated or decreasing times, too few or too many
        samples. OSError when the file cannot be opened.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a folder, not a CSV file")
    with open(path, "rb") as f:
        try:
            total = os.fstat(f.fileno()).st_size
        except OSError:
            total = 0
        return _parse_lines(
            _bounded_lines(f), path, tuple(coordinates), tuple(inputs), min_samples, max_samples, every, progress, total
        )


def _parse(
    text: str,
    where: str,
    coordinates: tuple,
    inputs: tuple,
    min_samples: int,
    max_samples: int | None = MAX_SAMPLES,
    every: int = 1,
) -> Record:
    """Parse CSV text (see `read_csv`)."""
    return _parse_lines(
        iter(text.encode("utf-8").splitlines(keepends=True)),
        where,
        coordinates,
        inputs,
        min_samples,
        max_samples,
        every,
        None,
        0,
    )


def _bounded_lines(f):
    """The file's lines (bytes), each at most `MAX_LINE_BYTES` long, else a
    sentinel that the parser turns into an error (no unbounded read)."""
    while True:
        raw = f.readline(MAX_LINE_BYTES + 1)
        if not raw:
            return
        yield raw


def _split(line: str) -> list:
    if '"' in line:
        return next(csv.reader([line], skipinitialspace=True))
    return line.split(",")


def _number(s: str, where: str, lineno: int, name: str) -> float:
    s = s.strip()
    try:
        if "_" in s or not s.isascii():
            raise ValueError
        x = float(s)
    except ValueError:
        hint = " (digit separators such as _ are not CSV numbers)" if "_" in s else ""
        raise ValueError(f"{where}: line {lineno}, column {name!r}: {s!r} is not a number{hint}") from None
    if math.isinf(x) and "inf" not in s.lower():
        raise ValueError(
            f"{where}: line {lineno}, column {name!r}: {s!r} is beyond the range of 64-bit floats (about ±1.8e308)"
        )
    return x


def _parse_lines(lines, where, coordinates, inputs, min_samples, max_samples, every, progress, total) -> Record:
    if not isinstance(every, (int, np.integer)) or isinstance(every, bool) or every < 1:
        raise ValueError(f"every: keep every k-th row with an integer k ≥ 1; got {every!r}")
    if max_samples is not None and max_samples < min_samples:
        raise ValueError(f"max_samples={max_samples} is below min_samples={min_samples}")
    wanted = ("t",) + tuple(coordinates) + tuple(inputs)
    if len(set(wanted)) != len(wanted):
        raise ValueError(f"{where}: the column names asked for repeat: {list(wanted)}")
    header: list | None = None
    idx: list = []
    blocks, block, line_blocks, line_block = [], [], [], []
    kept = data_rows = 0
    done_bytes = 0
    next_report = time.monotonic() + 1.0
    lineno = 0
    for raw in lines:
        lineno += 1
        done_bytes += len(raw)
        if len(raw) > MAX_LINE_BYTES:
            raise ValueError(
                f"{where}: line {lineno} is longer than {MAX_LINE_BYTES} bytes; expected a CSV file "
                "with one sample per line"
            )
        if progress is not None and time.monotonic() >= next_report:
            progress(done_bytes, total)
            next_report = time.monotonic() + 1.0
        try:
            line = raw.decode("utf-8-sig" if lineno == 1 else "utf-8")
        except UnicodeDecodeError as e:
            raise ValueError(
                f"{where}: line {lineno} is not UTF-8 text (byte {e.start + 1} of the line: "
                f"{raw[e.start : e.start + 1]!r}); expected a text CSV file"
            ) from None
        if "\x00" in line:
            raise ValueError(f"{where}: line {lineno} contains a NUL byte; expected a text CSV file")
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        try:
            fields = _split(line.rstrip("\r\n"))
        except csv.Error as e:
            raise ValueError(f"{where}: line {lineno} is not a CSV row ({e})") from None
        if header is None:
            header = [h.strip() for h in fields]
            counts = collections.Counter(header)
            dup = sorted(c for c in wanted if counts[c] > 1)
            if dup:
                raise ValueError(f"{where}: line {lineno}: column(s) {dup} appear more than once in the header")
            missing = [c for c in wanted if c not in header]
            if missing:
                hint = ""
                if len(header) == 1 and any(d in header[0] for d in ";\t|"):
                    hint = " — the separator must be a comma"
                elif not any(c in header for c in wanted) and all(_looks_numeric(h) for h in header):
                    hint = " — the first non-comment line must be a header naming the columns"
                raise ValueError(
                    f"{where}: missing column(s) {missing}; the header (line {lineno}) has {header}; "
                    f"expected {list(wanted)}{hint}"
                )
            idx = [header.index(c) for c in wanted]
            header_line = lineno
            continue
        if len(fields) != len(header):
            raise ValueError(
                f"{where}: line {lineno} has {len(fields)} fields; the header (line {header_line}) has {len(header)}"
            )
        data_rows += 1
        if (data_rows - 1) % every:
            continue
        block.append([_number(fields[j], where, lineno, c) for j, c in zip(idx, wanted)])
        line_block.append(lineno)
        kept += 1
        if max_samples is not None and kept > max_samples:
            raise ValueError(
                f"{where}: more than {max_samples} samples (reached at line {lineno}"
                + (f" of about {total / max(done_bytes / lineno, 1):.0f}" if total else "")
                + "); a fit's memory and time grow with the samples. Keep every k-th sample "
                "(`jaxnh fit --every K`, `read_csv(..., every=K)`), cut the record, or raise the limit "
                "(`--max-samples N`, `read_csv(..., max_samples=N)`)"
            )
        if len(block) == _CHUNK:
            blocks.append(np.asarray(block, dtype=float))
            line_blocks.append(np.asarray(line_block, dtype=np.int64))
            block, line_block = [], []
    if progress is not None and total:
        progress(done_bytes, total)
    if header is None:
        raise ValueError(f"{where}: no header row and no data (expected columns {', '.join(wanted)})")
    if block:
        blocks.append(np.asarray(block, dtype=float))
        line_blocks.append(np.asarray(line_block, dtype=np.int64))
    data = np.concatenate(blocks) if blocks else np.empty((0, len(wanted)))
    rows = np.concatenate(line_blocks) if line_blocks else np.empty(0, np.int64)
    cols = {c: np.ascontiguousarray(data[:, j]) for j, c in enumerate(wanted)}
    _check_columns(cols, where, min_samples, lines=rows)
    return Record(cols["t"], {c: cols[c] for c in coordinates}, {c: cols[c] for c in inputs}, where)


def _looks_numeric(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def write_csv(record: Record, path: str | os.PathLike[str], comments: Iterable[str] = ()) -> None:
    """Write `record` as CSV: comment lines, a header `t, channels..., inputs...`, rows.

    The file is written to a temporary name in the same folder and renamed
    into place, so an interrupted write never leaves a partial file.
    """
    names = ["t"] + list(record.channels) + list(record.inputs)
    cols = [record.t] + list(record.channels.values()) + list(record.inputs.values())
    with atomic_write(path, "w", newline="") as f:
        for c in comments:
            f.write(f"# {c}\n")
        f.write(",".join(names) + "\n")
        for row in zip(*cols):
            f.write(",".join(f"{x:.17g}" for x in row) + "\n")


def load_default() -> Record:
    """The embedded variator record (see `jaxnh/data/README.md` for how it was
    made and the true values): 6 s at 250 Hz, two quantised encoders, motor
    and load torques, a smooth change of the transmission ratio."""
    text = resources.files("jaxnh").joinpath("data", DEFAULT_DATA).read_text()
    return _parse(text, f"jaxnh/data/{DEFAULT_DATA}", ("phi1", "phi2"), ("M1", "M2"), MIN_SAMPLES)


def noise_level(y: ArrayInput, axis: int = 0) -> np.ndarray | jax.Array:
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
    xp = array_module(y)  # NumPy for concrete samples: nothing to compile
    d3 = xp.diff(xp.asarray(y), n=3, axis=axis)
    return xp.sqrt(xp.mean(d3**2, axis=axis) / 20.0)
