"""Fuzzing the CSV reader and the command line's input checks (issue 15's fuzz suite, I/O part).

Hypothesis builds records that are valid or broken in one known way (a
missing column, NaN/inf, `1_000`, an overflowing number, garbage, a repeated
or decreasing time, a short row, too few rows), dressed with a byte-order
mark, CRLF, comments, blank lines, spaces, extra columns and any column
order. The oracle is the construction itself:

* a valid record parses, to exactly the numbers written;
* a broken one raises ValueError whose message names the file and the
  1-based line number of the broken row;
* random bytes give a Record or a ValueError, never another exception;
* the command line gives exit status 2, a one-line message, and leaves no
  file behind, for every broken record (the fit is never reached).

Derandomised (the same examples on every run): 20 records per fault class for the
reader, 6 per class for the command line, 200 random byte strings; about 10 s.
"""

import os
import re
import tempfile

import numpy as np
import pytest
from hypothesis import given, HealthCheck, settings, strategies as st

from jaxnh.identify import Record
from jaxnh.identify.data import read_csv


FUZZ = settings(
    derandomize=True,
    database=None,
    deadline=None,
    max_examples=20,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

REQUIRED = ("t", "phi1", "phi2", "M1", "M2")
FAULTS = (
    "none",
    "missing_column",
    "nan",
    "underscore",
    "overflow",
    "garbage",
    "repeated_time",
    "decreasing_time",
    "short_row",
    "few_rows",
)
GARBAGE = ("abc", "1.2.3", "--1", "0x10", "١٢", "1e", "e5", "nan?", "1 2", "∞", "Infinity5", "True")


@st.composite
def records(draw, fault=None):
    fault = draw(st.sampled_from(FAULTS)) if fault is None else fault
    n = draw(st.integers(2, 19)) if fault == "few_rows" else draw(st.integers(20, 45))
    dts = draw(st.lists(st.floats(1e-6, 1e3), min_size=n, max_size=n))
    t0 = draw(st.floats(-1e6, 1e6))
    t = t0 + np.cumsum(dts)
    t = np.array([float(x) for x in t])
    if np.any(np.diff(t) <= 0):  # rounding of a huge t0 with a tiny dt: make the times plainly increasing
        t = t0 + np.arange(1, n + 1, dtype=float) * max(1.0, abs(t0) * 1e-12)
    finite = st.floats(allow_nan=False, allow_infinity=False)
    cols = {"t": t.tolist()}
    for c in REQUIRED[1:]:
        cols[c] = draw(st.lists(finite, min_size=n, max_size=n))
    extras = draw(st.lists(st.sampled_from(["x", "note", "T2", "phi3"]), unique=True, max_size=2))
    order = draw(st.permutations(list(REQUIRED) + extras))
    cells = [
        [repr(float(cols[c][i])) if c in cols else draw(st.sampled_from(["", "n/a", "1", "q"])) for c in order]
        for i in range(n)
    ]
    header = list(order)
    bad_row = None  # index of the broken data row
    expect = None
    if fault == "missing_column":
        gone = draw(st.sampled_from(REQUIRED))
        j = header.index(gone)
        header.pop(j)
        for r in cells:
            r.pop(j)
        expect = rf"missing column\(s\) \['{gone}'\]"
    elif fault in ("nan", "underscore", "overflow", "garbage"):
        bad_row = draw(st.integers(0, n - 1))
        col = draw(st.sampled_from(REQUIRED))
        text = {
            "nan": draw(st.sampled_from(["nan", "NaN", "inf", "-inf", "+Infinity"])),
            "underscore": draw(st.sampled_from(["1_000", "0.1_5", "1e1_0", "_1"])),
            "overflow": draw(st.sampled_from(["1e999", "-2e308", "1.8e308"])),
            "garbage": draw(st.sampled_from(GARBAGE)),
        }[fault]
        cells[bad_row][header.index(col)] = text
        expect = {
            "nan": rf"column '{col}' has non-finite values .* first at line {{line}}",
            "underscore": rf"line {{line}}, column '{col}': .* is not a number",
            "overflow": rf"line {{line}}, column '{col}': .* beyond the range",
            "garbage": rf"line {{line}}, column '{col}': .* is not a number",
        }[fault]
    elif fault in ("repeated_time", "decreasing_time"):
        bad_row = draw(st.integers(1, n - 1))
        j = header.index("t")
        prev = float(cells[bad_row - 1][j])
        cells[bad_row][j] = repr(prev if fault == "repeated_time" else prev - draw(st.floats(1e-3, 1e3)))
        kind = "repeated" if fault == "repeated_time" else "decreasing"
        expect = rf"{kind} time at line {{prev}} and line {{line}}"
    elif fault == "short_row":
        bad_row = draw(st.integers(0, n - 1))
        cells[bad_row].pop(draw(st.integers(0, len(header) - 1)))
        expect = rf"line {{line}} has {len(header) - 1} fields; the header \(line {{header}}\) has {len(header)}"
    elif fault == "few_rows":
        expect = rf"too few samples: {n}; expected at least 20"
    # dress it: BOM, comments, blank lines, spaces, CRLF
    bom = draw(st.booleans())
    eol = draw(st.sampled_from(["\n", "\r\n"]))
    sep = draw(st.sampled_from([",", ", "]))
    lines, line_of = [], {}
    for _ in range(draw(st.integers(0, 2))):
        lines.append("# " + draw(st.text(st.characters(blacklist_categories=("Cs", "Cc")), max_size=10)))
    header_line = len(lines) + 1
    lines.append(sep.join(header))
    for i, r in enumerate(cells):
        if draw(st.integers(0, 9)) == 0:
            lines.append(draw(st.sampled_from(["", "# note", "   "])))
        lines.append(sep.join(r))
        line_of[i] = len(lines)
    text = ("\ufeff" if bom else "") + eol.join(lines) + eol
    if expect is not None:
        expect = (
            expect.replace("{line}", str(line_of.get(bad_row, -1)))
            .replace("{prev}", str(line_of.get((bad_row or 0) - 1, -1)))
            .replace("{header}", str(header_line))
        )
    return fault, text, cols, expect


def write(folder, text):
    path = os.path.join(folder, "d.csv")
    with open(path, "wb") as f:
        f.write(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


@pytest.mark.parametrize("fault", FAULTS)
@FUZZ
@given(data=st.data())
def test_reader_valid_exact_broken_named(fault, data):
    fault, text, cols, expect = data.draw(records(fault))
    with tempfile.TemporaryDirectory() as d:
        path = write(d, text)
        if fault == "none":
            r = read_csv(path)
            assert r.n == len(cols["t"])
            for c in REQUIRED:
                got = r.t if c == "t" else (r.channels[c] if c in r.channels else r.inputs[c])
                np.testing.assert_array_equal(got, np.asarray(cols[c]))  # bit for bit
            return
        with pytest.raises(ValueError) as e:
            read_csv(path)
        msg = str(e.value)
        assert msg.startswith(path + ": "), msg
        assert re.search(expect, msg), (expect, msg)
        assert "np.float64" not in msg and "\n" not in msg


@settings(FUZZ, max_examples=200)
@given(st.binary(max_size=400), st.booleans())
def test_reader_random_bytes(data, with_header):
    if with_header:
        data = b"t,phi1,phi2,M1,M2\n" + data
    with tempfile.TemporaryDirectory() as d:
        path = write(d, data)
        try:
            r = read_csv(path, min_samples=1)
        except ValueError as e:
            assert str(e).startswith(path + ": "), e
            return
        assert isinstance(r, Record)
        assert np.all(np.isfinite(r.t)) and np.all(np.diff(r.t) > 0)
        for v in list(r.channels.values()) + list(r.inputs.values()):
            assert np.all(np.isfinite(v))


@pytest.mark.parametrize("fault", [f for f in FAULTS if f != "none"])
@settings(FUZZ, max_examples=6)
@given(data=st.data(), figures=st.booleans())
def test_cli_refuses_broken_records_and_writes_nothing(monkeypatch, capsys, fault, data, figures):
    import jaxnh._cli.fit as cli
    from jaxnh.cli import main

    def reached(*a, **k):
        raise AssertionError("the fit was reached with a broken record")

    monkeypatch.setattr(cli, "_fit", reached)
    fault, text, cols, expect = data.draw(records(fault))
    with tempfile.TemporaryDirectory() as d:
        path = write(d, text)
        args = ["fit", path, "--quiet", "--json", os.path.join(d, "fit.json")]
        if figures:
            args += ["--out", os.path.join(d, "figs")]
        code = main(args)
        out, err = capsys.readouterr()
        assert code == 2, (fault, err)
        assert err.startswith("jaxnh fit: ") and err.count("\n") == 1 and "Traceback" not in err, err
        assert re.search(expect, err), (expect, err)
        assert sorted(os.listdir(d)) == ["d.csv"]
