"""Data in and out: the CSV reader's checks and messages, Record.from_dataframe,
Solution → DataFrame, JSON-safe conversion, atomic writes, and plots that return
Figures without touching matplotlib's backend. No fitting here (see test_cli.py)."""

import json
import os
import re
import subprocess
import sys
import types

import numpy as np
import pytest

from jaxnh._base.atomic import atomic_write
from jaxnh._base.dataframe import json_safe, solution_to_dataframe
from jaxnh.identify import Record
from jaxnh.identify.data import MAX_LINE_BYTES, read_csv, write_csv


HEADER = "t,phi1,phi2,M1,M2"


def rows(n=25, dt=0.01):
    return "\n".join(f"{dt * i!r},{0.1 * i!r},{0.2 * i!r},0.1,-0.1" for i in range(n))


def write(tmp_path, text, name="d.csv"):
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text, encoding="utf-8")
    return p


# --- the reader ---------------------------------------------------------------------------------


def test_byte_order_mark_is_accepted(tmp_path):
    rec = read_csv(write(tmp_path, "\ufeff" + HEADER + "\n" + rows()))
    assert rec.n == 25 and set(rec.channels) == {"phi1", "phi2"}
    np.testing.assert_array_equal(rec.t, np.arange(25) * 0.01)


def test_spaces_quotes_crlf_comments_and_extra_columns(tmp_path):
    text = (
        "# a comment\r\n\r\n"
        + "t, phi1 ,phi2,M1,M2,extra\r\n"
        + "\r\n".join(f'{0.01 * i!r}, "{0.1 * i!r}",{0.2 * i!r},0.1,-0.1,x' for i in range(25))
        + "\r\n"
    )
    rec = read_csv(write(tmp_path, text))
    np.testing.assert_allclose(rec.channels["phi1"], 0.1 * np.arange(25))


BAD = [
    # (text, pattern) — every message names the file and the 1-based line number of the file
    (HEADER + "\n" + rows().replace("0.1,-0.1", "1_000,-0.1", 1), r"line 2, column 'M1': '1_000' is not a number"),
    (HEADER + "\n" + rows().replace("0.1,-0.1", "1e999,-0.1", 1), r"line 2, column 'M1': '1e999' is beyond the range"),
    (HEADER + "\n" + rows().replace("0.1,-0.1", "٣,-0.1", 1), r"line 2, column 'M1': '٣' is not a number"),
    (HEADER + "\n" + rows().replace("0.1,-0.1", "0x10,-0.1", 1), r"line 2, column 'M1': '0x10' is not a number"),
    (
        "# comment\n\n" + HEADER + "\n" + rows().replace("0.1,-0.1", "nan,-0.1", 1),
        r"column 'M1' has non-finite values .* first at line 4 \(t = 0.0\)",
    ),
    (HEADER + "\n" + rows().replace("0.1,-0.1", "-inf,-0.1", 1), r"non-finite values"),
    (
        "# c\n"
        + HEADER
        + "\n"
        + rows(10)
        + "\n0.09,0,0,0,0\n"
        + "\n".join(f"{0.01 * i},0,0,0,0" for i in range(10, 20)),
        r"repeated time at line 12 and line 13 \(t = 0.09, 0.09\)",
    ),
    (
        HEADER + "\n" + rows(10) + "\n0.05,0,0,0,0\n" + "\n".join(f"{0.01 * i},0,0,0,0" for i in range(11, 25)),
        r"decreasing time at line 11 and line 12 \(t = 0.09, 0.05\)",
    ),
    (HEADER + "\n" + rows(3) + "\n1,2,3\n", r"line 5 has 3 fields; the header \(line 1\) has 5"),
    (HEADER + ",t\n" + rows(), r"column\(s\) \['t'\] appear more than once"),
    ("t;phi1;phi2;M1;M2\n" + rows().replace(",", ";"), r"missing column.*separator must be a comma"),
    (rows(), r"missing column.*must be a header"),
    ("t,phi1,M1,M2\n" + "\n".join(f"{0.01 * i},0,0,0" for i in range(25)), r"missing column\(s\) \['phi2'\]"),
    ("", r"no header row and no data"),
    ("# only comments\n\n", r"no header row and no data"),
    (HEADER + "\n", r"too few samples: 0"),
    (HEADER + "\n" + rows(5), r"too few samples: 5; expected at least 20"),
    (b"\xff\xfe" + HEADER.encode("utf-16-le"), r"line 1 is not UTF-8 text"),
    ((HEADER + "\n" + rows(3) + "\n").encode() + b"0.5,\x80,0,0,0\n", r"line 5 is not UTF-8 text"),
    (
        HEADER + "\n1e307,0,0,0,0\n-1e307,0,0,0,0\n" + "\n".join(f"{i},0,0,0,0" for i in range(20)),
        r"decreasing time at line 2 and line 3 \(t = 1e\+307, -1e\+307\)",
    ),
    (
        HEADER + "\n-1.7e308,0,0,0,0\n1.7e308,0,0,0,0\n" + "\n".join(f"1.71e308,{i},0,0,0" for i in range(20)),
        r"time step between line 2 and line 3 overflows",
    ),
    (HEADER + "\n0,0,0,0,\x00\n", r"line 2 contains a NUL byte"),
]


@pytest.mark.parametrize("text,pattern", BAD)
def test_bad_records_are_refused_with_the_line(tmp_path, text, pattern):
    path = write(tmp_path, text)
    with pytest.raises(ValueError) as e:
        read_csv(path)
    msg = str(e.value)
    assert msg.startswith(str(path) + ": "), msg
    assert re.search(pattern, msg), msg
    assert "np.float64" not in msg and "\n" not in msg


def test_too_many_samples_stops_early_every_k_keeps_a_subsample(tmp_path):
    path = write(tmp_path, HEADER + "\n" + rows(1000) + "\n" + "garbage line that is never reached\n")
    with pytest.raises(ValueError, match=r"more than 100 samples \(reached at line 102 of about \d+\).*--every"):
        read_csv(path, max_samples=100)
    with pytest.raises(ValueError, match="line 1002 has 1 fields"):  # every line is still checked
        read_csv(path, max_samples=1000, every=10)
    path = write(tmp_path, HEADER + "\n" + rows(1000))
    rec = read_csv(path, every=10)
    assert rec.n == 100
    np.testing.assert_allclose(rec.t, np.arange(0, 1000, 10) * 0.01)
    with pytest.raises(ValueError, match="every"):
        read_csv(path, every=0)


def test_long_line_and_progress(tmp_path):
    path = write(tmp_path, HEADER + "\n" + "1" * (MAX_LINE_BYTES + 10) + "\n")
    with pytest.raises(ValueError, match=r"line 2 is longer than"):
        read_csv(path)
    seen = []
    rec = read_csv(write(tmp_path, HEADER + "\n" + rows()), progress=lambda done, total: seen.append((done, total)))
    assert rec.n == 25 and seen and seen[-1][0] == seen[-1][1] == os.path.getsize(tmp_path / "d.csv")


def test_folder_and_missing_file(tmp_path):
    with pytest.raises(ValueError, match="is a folder"):
        read_csv(tmp_path)
    with pytest.raises(FileNotFoundError):
        read_csv(tmp_path / "nope.csv")


def test_round_trip_is_exact_and_atomic(tmp_path):
    rec = read_csv(write(tmp_path, HEADER + "\n" + rows()))
    rec = Record(rec.t, {k: v + 1e-13 * np.pi for k, v in rec.channels.items()}, rec.inputs, "x")
    write_csv(rec, tmp_path / "x.csv", comments=["made by a test"])
    back = read_csv(tmp_path / "x.csv")
    for k in rec.channels:
        np.testing.assert_array_equal(back.channels[k], rec.channels[k])  # 17 digits: bit for bit
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left


def test_atomic_write_leaves_old_content_on_failure(tmp_path):
    p = tmp_path / "out.json"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(p) as f:
            f.write("partial")
            raise RuntimeError("interrupted")
    assert p.read_text() == "old"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out.json"]


# --- records in memory and from pandas --------------------------------------------------------------


def test_record_messages_use_the_sample_index():
    t = np.arange(25) * 0.01
    y = np.zeros(25)
    y[7] = np.nan
    with pytest.raises(ValueError, match=r"first at sample 7 \(t = 0.07\)"):
        Record(t, {"x": y})
    t2 = t.copy()
    t2[5] = t2[4]
    with pytest.raises(ValueError, match=r"repeated time at sample 4 and sample 5 \(t = 0.04, 0.04\)"):
        Record(t2, {"x": np.zeros(25)})
    with pytest.raises(ValueError, match="sigma for 'x' must be finite and > 0"):
        Record(t, {"x": np.zeros(25)}, sigma=0.0)
    with pytest.raises(ValueError, match="used twice"):
        Record(t, {"x": np.zeros(25)}, {"x": np.zeros(25)})


def test_from_dataframe():
    pd = pytest.importorskip("pandas")
    t = np.arange(30) * 0.02
    df = pd.DataFrame({"time": t, "a": np.sin(t), "b": np.cos(t), "F": 0.5 * np.ones(30), "note": ["x"] * 30})
    rec = Record.from_dataframe(df, time="time", observed=["a", "b"], inputs=["F"], sigma={"a": 1e-3, "b": 2e-3})
    assert rec.n == 30 and list(rec.channels) == ["a", "b"] and list(rec.inputs) == ["F"]
    np.testing.assert_array_equal(rec.channels["b"], np.cos(t))
    assert rec.sigma == {"a": 1e-3, "b": 2e-3}
    # time from the index; observed defaults to every other numeric column
    rec2 = Record.from_dataframe(df.drop(columns="note").set_index("time"), time=None, inputs="F", sigma=1e-3)
    assert list(rec2.channels) == ["a", "b"] and rec2.sigma == {"a": 1e-3, "b": 1e-3}
    bad = df.copy()
    bad.loc[12, "a"] = np.nan
    with pytest.raises(ValueError, match=r"column 'a' has non-finite values .* first at sample 12"):
        Record.from_dataframe(bad, time="time", observed=["a"])
    with pytest.raises(ValueError, match=r"column 'note', sample 0: 'x' is not a number"):
        Record.from_dataframe(df, time="time", observed=["note"])
    with pytest.raises(ValueError, match=r"missing column\(s\) \['c'\]"):
        Record.from_dataframe(df, time="time", observed=["c"])
    with pytest.raises(TypeError, match="must be a pandas.DataFrame"):
        Record.from_dataframe({"t": t}, time="t")


def test_from_dataframe_without_pandas(monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas → ImportError
    with pytest.raises(ImportError, match="needs pandas"):
        Record.from_dataframe(object())


# --- Solution → DataFrame ---------------------------------------------------------------------------


def fake_solution(batch=()):
    n, s = 5, 2
    ts = np.linspace(0, 1, n)
    q = np.broadcast_to(np.stack([ts, 2 * ts], axis=1), batch + (n, s)).copy()
    return types.SimpleNamespace(
        ts=np.broadcast_to(ts, batch + (n,)),
        q=q,
        qd=q + 1,
        energy=np.ones(batch + (n,)),
        multipliers=np.zeros(batch + (n, 1)),
        residual=None,
        names=("phi1", "phi2"),
        success=np.ones(batch, bool),
        status=np.zeros(batch, int),
        message="success",
    )


def test_solution_to_dataframe_single_and_batched():
    pd = pytest.importorskip("pandas")
    df = solution_to_dataframe(fake_solution())
    assert list(df.columns) == ["phi1", "phi2", "phi1_dot", "phi2_dot", "energy", "lambda_0"]
    assert df.index.name == "t" and len(df) == 5 and df.attrs["success"] and df.attrs["message"] == "success"
    np.testing.assert_array_equal(df["phi2"].to_numpy(), 2 * np.linspace(0, 1, 5))
    sol = fake_solution((2, 3))
    sol.success[1, 2] = False
    df = solution_to_dataframe(sol)
    assert df.index.names == ["batch", "t"] and len(df) == 6 * 5 and df.attrs["batch_shape"] == (2, 3)
    assert df.loc[5, "success"].eq(False).all() and df.loc[0, "success"].all() and not df.attrs["success"]
    sol.q[1, 1, :, 0] = np.arange(5) + 100.0  # member 4 in C order: its own rows, in report order
    df = solution_to_dataframe(sol)
    np.testing.assert_array_equal(df.loc[4, "phi1"].to_numpy(), np.arange(5) + 100.0)
    np.testing.assert_array_equal(df.loc[3, "phi1_dot"].to_numpy(), sol.qd[1, 0, :, 0])
    sol.speeds = np.full((2, 3, 5, 1), 7.0)  # a mechanism with `kinematics`: the speeds as u_<i>
    assert np.all(solution_to_dataframe(sol)["u_0"].to_numpy() == 7.0)
    assert isinstance(df, pd.DataFrame)
    with pytest.raises(ValueError, match="must be"):
        solution_to_dataframe(types.SimpleNamespace(q=np.zeros(3), qd=np.zeros(3), ts=np.zeros(3)))


def test_solution_to_dataframe_from_a_real_solve():
    pytest.importorskip("pandas")
    import jax.numpy as jnp

    import jaxnh as nh
    from jaxnh.models import variator as V

    p = V.default_params()
    ts = jnp.linspace(0.0, 1.0, 11)
    sol = nh.simulate(
        V.mechanism(), p, jnp.zeros(2), jnp.array([2.0, 2.0 * float(p.U21(0.0))]), ts, record=("energy", "residual")
    )
    df = solution_to_dataframe(sol)
    assert df.attrs["success"] and len(df) == 11
    assert {"phi1", "phi2", "phi1_dot", "phi2_dot", "energy", "residual_0"} <= set(df.columns)
    np.testing.assert_array_equal(df["phi2_dot"].to_numpy(), np.asarray(sol.qd[:, 1]))


# --- JSON ---------------------------------------------------------------------------------------------


def test_json_safe_never_gives_invalid_json():
    data = {
        "a": np.float64(np.inf),
        "b": [np.nan, 1.5, -np.inf],
        "c": np.arange(3),
        "d": np.array([[1.0, np.nan]]),
        "e": np.bool_(True),
        "f": (np.int32(3), None, "x"),
        4: np.float32(2.5),
    }
    out = json_safe(data)
    text = json.dumps(out, allow_nan=False)
    assert json.loads(text) == {
        "a": None,
        "b": [None, 1.5, None],
        "c": [0, 1, 2],
        "d": [[1.0, None]],
        "e": True,
        "f": [3, None, "x"],
        "4": 2.5,
    }
    with pytest.raises(TypeError):
        json_safe(object())


# --- plots: Figures, ax/fig, no backend change, optional matplotlib ----------------------------------


def test_library_imports_and_plots_without_touching_the_backend():
    code = (
        "import sys, matplotlib\n"
        "matplotlib.use('svg')\n"  # a user's choice that the library must keep
        "import jaxnh, jaxnh.identify.plots, jaxnh._cli.demo, jaxnh._cli.fit\n"
        "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot imported at library import'\n"
        "from matplotlib.figure import Figure\n"
        "import numpy as np, jax.numpy as jnp\n"
        "from types import SimpleNamespace as N\n"
        "ts = np.linspace(0, 1, 5); q = np.stack([ts, ts], 1)\n"
        "sols = {m: N(q=q, qd=q) for m in ('lagrange', 'appell', 'substituted')}\n"
        "E = {m: np.ones(5) for m in sols}\n"
        "fig = Figure()\n"
        "out = jaxnh._cli.demo.plot_methods(ts, q, q, sols, ts, E, fig=fig)\n"
        "assert out is fig and len(fig.axes) == 3\n"
        "f2 = jaxnh._cli.demo.plot_methods(ts, q, q, sols, ts, E)\n"
        "assert type(f2).__name__ == 'Figure'\n"
        "print(matplotlib.get_backend())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, JAXNH_CACHE_DIR="off"),
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "svg"


def test_library_imports_without_matplotlib():
    code = (
        "import sys\n"
        "sys.modules['matplotlib'] = None\n"  # as if not installed
        "import jaxnh, jaxnh.identify.plots, jaxnh._cli.demo, jaxnh._cli.fit\n"
        "from jaxnh.identify.plots import plot_fit\n"
        "try:\n"
        "    plot_fit(None)\n"
        "except ImportError as e:\n"
        "    print('ImportError', e)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, JAXNH_CACHE_DIR="off"),
    )
    assert out.returncode == 0, out.stderr
    assert "ImportError plots need matplotlib" in out.stdout


def test_no_matplotlib_use_in_the_library():
    import jaxnh

    root = os.path.dirname(jaxnh.__file__)
    offenders = []
    for folder, _, files in os.walk(root):
        for f in files:
            if f.endswith(".py") and os.path.basename(folder) != "_cli":  # the command line may pick Agg
                text = open(os.path.join(folder, f), encoding="utf-8").read()
                if "matplotlib.use(" in text or re.search(r"^import matplotlib", text, re.M):
                    offenders.append(os.path.join(folder, f))
    assert offenders == []
