"""The command line, in-process (`jaxnh.cli.main([...])`): every check happens before
fitting, with exit status 2 and a one-line message; outputs are whole or absent;
`--model module:function` fits a user's own mechanism (tests/cli_model.py, not the
variator); JSON has null and a failure status where numbers are not finite.

The fits use a 40-sample record of a two-shaft mechanism and share one compiled
Levenberg–Marquardt solve (same shapes and options, `--quiet`): the first
compiles, the others reuse it.
"""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from jaxnh.cli import main


HERE = os.path.dirname(os.path.abspath(__file__))
MODEL = os.path.join(HERE, "cli_model.py") + ":coupled_shafts"
sys.path.insert(0, HERE)
import cli_model  # noqa: E402


HEADER = "t,phi1,phi2,M1,M2"


def rows(n=25, dt=0.01):
    return "\n".join(f"{dt * i!r},{0.1 * i!r},{0.2 * i!r},0.1,-0.1" for i in range(n))


def run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def listing(folder):
    return sorted(p.name for p in folder.iterdir())


def assert_bad_input(code, err, pattern):
    assert code == 2, err
    assert err.startswith("jaxnh fit: ") or err.startswith("usage:"), err
    assert "Traceback" not in err and "np.float64" not in err, err
    assert re.search(pattern, err), err


@pytest.fixture
def no_fit(monkeypatch):
    """Fail loudly if a test reaches the fit: the checks must come first."""
    import jaxnh._cli.fit as cli

    def boom(*a, **k):
        raise AssertionError("the fit was started before the input was checked")

    monkeypatch.setattr(cli, "_fit", boom)


# --- checks before fitting (no compilation) -------------------------------------------------------


@pytest.mark.parametrize(
    "kind", ["missing folder", "is a folder", "out is a file", "out parent missing", "json is the data"]
)
def test_output_paths_are_checked_before_fitting(tmp_path, capsys, no_fit, kind):
    data = tmp_path / "d.csv"
    data.write_text(HEADER + "\n" + rows())
    args = ["fit", str(data), "--quiet"]
    if kind == "missing folder":
        args += ["--json", str(tmp_path / "nope" / "fit.json")]
        pattern = r"--json .*the folder .*nope does not exist"
    elif kind == "is a folder":
        args += ["--json", str(tmp_path)]
        pattern = r"--json .*is a folder"
    elif kind == "out is a file":
        args += ["--out", str(data)]
        pattern = r"--out .*exists and is not a folder"
    elif kind == "out parent missing":
        args += ["--out", str(tmp_path / "a" / "b")]
        pattern = r"--out .*parent folder .* does not exist"
    else:
        args += ["--json", str(data)]
        pattern = r"--json .*is the input file"
    before = listing(tmp_path)
    code, out, err = run(args, capsys)
    assert_bad_input(code, err, pattern)
    assert listing(tmp_path) == before
    assert data.read_text().startswith(HEADER)


def _unwritable_folder(tmp_path):
    """A folder the current user cannot write into: a read-only one of our own, or for root (whom
    permissions do not stop) a process folder of /proc, where nobody can create files."""
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        os.chmod(ro, 0o500)
        return ro
    if os.path.isdir("/proc/self") and not os.access("/proc/self", os.W_OK):
        return "/proc/self"
    pytest.skip("running as root without /proc: no folder here is unwritable for this user")


def test_unwritable_json_folder(tmp_path, capsys, no_fit):
    ro = _unwritable_folder(tmp_path)
    code, out, err = run(["fit", "--json", os.path.join(ro, "f.json")], capsys)
    assert_bad_input(code, err, "not writable")


BAD_CSV = [
    (HEADER + "\n" + rows().replace("0.1,-0.1", "1_000,-0.1", 1), r"line 2, column 'M1': '1_000' is not a number"),
    (HEADER + "\n" + rows().replace("0.1,-0.1", "1e999,-0.1", 1), r"line 2, column 'M1': '1e999' is beyond"),
    ("# c\n" + HEADER + "\n" + rows().replace("0.1,-0.1", "nan,-0.1", 1), r"non-finite .* first at line 3 \(t = 0.0\)"),
    (
        HEADER + "\n" + rows(10) + "\n0.05,0,0,0,0\n" + "\n".join(f"{0.01 * i},0,0,0,0" for i in range(11, 25)),
        r"decreasing time at line 11 and line 12 \(t = 0.09, 0.05\)",
    ),
    ("t,phi1,M1,M2\n" + rows(), r"missing column\(s\) \['phi2'\]"),
    (b"\x00\xff\xfe garbage \x81", r"not UTF-8 text"),
    ("", r"no header row"),
    (HEADER + "\n" + rows(5), r"too few samples: 5"),
]


@pytest.mark.parametrize("text,pattern", BAD_CSV)
def test_bad_records_exit_2_and_write_nothing(tmp_path, capsys, no_fit, text, pattern):
    data = tmp_path / "d.csv"
    data.write_bytes(text if isinstance(text, bytes) else text.encode())
    code, out, err = run(
        ["fit", str(data), "--quiet", "--json", str(tmp_path / "o.json"), "--out", str(tmp_path / "figs")], capsys
    )
    assert_bad_input(code, err, pattern)
    assert str(data) in err
    assert listing(tmp_path) == ["d.csv"]


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--knots", "1000"], r"--knots: 1000 is out of range: expected 2 ≤ value ≤ 200"),
        (["--knots", "1_0"], r"--knots: '1_0' is not an integer"),
        (["--knots", "30"], r"--knots 30: more knots than the 25 samples"),
        (["--knots", "22", "--observe", "phi1"], r"--knots 22: 26 unknowns but only 25 samples × 1 channel"),
        (["--noise", "0"], r"--noise: '0': expected a finite number > 0"),
        (["--noise", "nan"], r"--noise: 'nan': expected a finite number > 0"),
        (["--noise", "1", "2", "3"], r"--noise: give 1 or 2 values"),
        (["--observe", "phi3"], r"--observe: expected phi1 and/or phi2"),
        (["--shooting", "5"], r"--shooting 5: segments of 6 samples are too short"),
        (["--max-iterations", "0"], r"--max-iterations: 0 is out of range"),
        (["--max-samples", "20"], r"more than 20 samples \(reached at line 22"),
        (["--every", "2"], r"too few samples: 13"),
        (["--knots", "3", "--model", MODEL], r"--knots applies to --model variator only"),
    ],
)
def test_parameter_counts_and_options_are_checked(tmp_path, capsys, no_fit, args, pattern):
    data = tmp_path / "d.csv"
    data.write_text(HEADER + "\n" + rows())
    code, out, err = run(["fit", str(data), "--quiet", *args], capsys)
    assert_bad_input(code, err, pattern)


@pytest.mark.parametrize(
    "ref,pattern",
    [
        ("no_such_module_xyz:f", r"no module named 'no_such_module_xyz'"),
        ("variator2", r"expected 'variator' or 'module:function'"),
        (MODEL.replace("coupled_shafts", "missing"), r"has no attribute 'missing'"),
        (MODEL.replace("coupled_shafts", "not_a_spec"), r"must return a jaxnh.identify.spec.FitSpec .* got int"),
        (
            MODEL.replace("coupled_shafts", "raises"),
            r"calling raises\(\) raised RuntimeError: the user's model is "
            r"broken \(at .*cli_model.py:\d+\)",
        ),
        ("/nonexistent/m.py:f", r"no file /nonexistent/m.py"),
    ],
)
def test_bad_model_references(tmp_path, capsys, no_fit, ref, pattern):
    data = tmp_path / "d.csv"
    data.write_text(cli_model.record_text())
    code, out, err = run(["fit", str(data), "--model", ref, "--quiet"], capsys)
    assert_bad_input(code, err, pattern)


def test_model_columns_are_the_mechanisms_names(tmp_path, capsys, no_fit):
    data = tmp_path / "d.csv"
    data.write_text(HEADER + "\n" + rows())
    code, out, err = run(["fit", str(data), "--model", MODEL, "--quiet"], capsys)
    assert_bad_input(code, err, r"missing column\(s\) \['a', 'b', 'F'\]")


def test_model_by_module_name(monkeypatch):
    from jaxnh.identify.spec import load_model

    monkeypatch.chdir(HERE)  # like `python -m`: modules in the current folder are found
    spec = load_model("cli_model:coupled_shafts_dict")
    assert spec.free == ("J1", "c") and spec.observed == ("a", "b") and spec.inputs == ("F",)


def test_missing_file_and_help(tmp_path, capsys):
    code, out, err = run(["fit", str(tmp_path / "no.csv")], capsys)
    assert_bad_input(code, err, r"No such file")
    code, out, err = run(["fit", "--help"], capsys)
    assert code == 0
    text = " ".join(out.split())
    for s in (
        "exit status: 0 fitted",
        "1 the fit failed",
        "2 bad input",
        "module:function",
        "FitSpec",
        "1-based line numbers",
    ):
        assert s in text, s
    code, out, err = run(["fit", "--bogus"], capsys)
    assert code == 2 and "unrecognized arguments" in err


def test_a_crash_in_the_fit_is_a_failure_with_valid_json(tmp_path, capsys, monkeypatch):
    import jaxnh._cli.fit as cli

    def crash(*a, **k):
        raise FloatingPointError("overflow in the solver\nsecond line")

    monkeypatch.setattr(cli, "_fit", crash)
    data = tmp_path / "d.csv"
    data.write_text(HEADER + "\n" + rows())
    code, out, err = run(["fit", str(data), "--quiet", "--json", str(tmp_path / "o.json")], capsys)
    assert code == 1 and "Traceback" not in err
    assert "the fit failed: FloatingPointError: overflow in the solver" in err
    rep = json.loads((tmp_path / "o.json").read_text())
    assert rep["status"] == "error" and rep["ok"] is False
    assert listing(tmp_path) == ["d.csv", "o.json"]


# --- fits with a user's own mechanism (one compilation, shared) -----------------------------------------


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """`jaxnh fit DATA --model tests/cli_model.py:coupled_shafts --json --out` once for the module."""
    d = tmp_path_factory.mktemp("fit")
    data = d / "d.csv"
    data.write_bytes(b"\xef\xbb\xbf" + cli_model.record_text().encode())  # with a UTF-8 byte-order mark
    code = main(
        ["fit", str(data), "--model", MODEL, "--json", str(d / "fit.json"), "--out", str(d / "figs"), "--quiet"]
    )
    return d, code


@pytest.mark.slow
def test_users_mechanism_is_fitted(fitted):
    d, code = fitted
    assert code == 0
    rep = json.loads((d / "fit.json").read_text())
    assert rep["status"] == "fitted" and rep["ok"] and rep["model"] == MODEL
    # the record was made at TRUE with noise 2e-4 rad: the truth lies within 3 standard errors
    for k, true in cli_model.TRUE.items():
        v, s = rep["parameters"][k]["value"], rep["parameters"][k]["std"]
        assert abs(v - true) <= 3 * s, (k, v, s, true)
        assert s / v < 0.1
    assert set(rep["initial_state"]) == {"a(t0)", "b(t0)", "b'(t0)"}
    assert (d / "figs" / "fit_data.png").stat().st_size > 10_000
    assert sorted(os.listdir(d)) == ["d.csv", "figs", "fit.json"]  # no temporary files left
    assert sorted(os.listdir(d / "figs")) == ["fit_data.png"]


@pytest.mark.slow
def test_dict_spec_and_to_dict(fitted, tmp_path):
    """The same fit through the dict form of the contract and through jaxnh.fit directly."""
    import jaxnh as nh
    from jaxnh.identify import read_csv

    pd = pytest.importorskip("pandas")
    from jaxnh.identify import Record

    d, _ = fitted
    rec = Record.from_dataframe(
        pd.read_csv(d / "d.csv", encoding="utf-8-sig"), time="t", observed=["a", "b"], inputs=["F"]
    )
    np.testing.assert_array_equal(rec.t, read_csv(d / "d.csv", coordinates=("a", "b"), inputs=("F",)).t)
    kw: dict = dict(
        free=("J1", "c"),
        positive=("J1", "c"),
        observe=("a", "b"),
        rtol=1e-8,
        shooting=1,
        max_iterations=100,
        progress=False,
    )
    r = nh.fit(cli_model.MECH, cli_model.params(rec), rec, **kw)
    dd = r.to_dict(arrays=True)
    text = json.dumps(dd, allow_nan=False)
    back = json.loads(text)
    rep = json.loads((d / "fit.json").read_text())
    assert back["status"] == "fitted"
    np.testing.assert_allclose(back["parameters"]["J1"]["value"], rep["parameters"]["J1"]["value"], rtol=1e-9)
    assert len(back["fitted"]) == rec.n and len(back["covariance"]) == 5
    assert "FitResult(converged, identifiable" in repr(r) and len(repr(r)) < 400
    assert str(r) == r.summary()
    # a result with non-finite numbers: null in JSON, and a status that says so
    import dataclasses

    bad = dataclasses.replace(r, values=np.r_[np.nan, r.values[1:]], std=np.r_[np.inf, r.std[1:]])
    dd = json.loads(json.dumps(bad.to_dict(), allow_nan=False))
    assert dd["status"] == "non_finite" and dd["ok"] is False
    assert dd["values"][0] is None and dd["std"][0] is None
    # the record's own noise levels are used when fit gets no noise=
    rec_s = Record.from_dataframe(
        pd.read_csv(d / "d.csv", encoding="utf-8-sig"), time="t", observed=["a", "b"], inputs=["F"], sigma=2e-4
    )
    r2 = nh.fit(cli_model.MECH, cli_model.params(rec_s), rec_s, **kw)
    assert r2.noise == {"a": 2e-4, "b": 2e-4} and r2.converged
    # plots draw into a given Figure and return it
    from matplotlib.figure import Figure

    from jaxnh.identify.plots import plot_fit

    fig = Figure()
    assert plot_fit(r, rec, fig=fig) is fig and len(fig.axes) == 4  # angles, 2 residual panels, the input


def test_overflowing_record_is_bad_input(tmp_path, capsys, no_fit):
    data = tmp_path / "d.csv"
    data.write_text(cli_model.record_text(scale=1e300))
    code, out, err = run(["fit", str(data), "--model", MODEL, "--json", str(tmp_path / "o.json"), "--quiet"], capsys)
    assert_bad_input(code, err, r"column 'a' has values up to \d\.\d+e\+300 in magnitude; .* other units")
    assert listing(tmp_path) == ["d.csv"]


@pytest.mark.slow
def test_no_torque_is_not_identifiable_exit_1(tmp_path, capsys, fitted):
    # F = 0: (J1 + K² J2) a'' = −K² c a' determines only c / (J1 + K² J2)
    data = tmp_path / "d.csv"
    data.write_text(cli_model.record_text().replace(",0.05\n", ",0.0\n"))
    code, out, err = run(
        [
            "fit",
            str(data),
            "--model",
            MODEL.replace("coupled_shafts", "coupled_shafts_dict"),
            "--json",
            str(tmp_path / "o.json"),
            "--quiet",
        ],
        capsys,
    )
    rep = json.loads((tmp_path / "o.json").read_text())
    assert code == 1, (out, err)
    assert rep["status"] in ("not_identifiable", "not_converged") and not rep["ok"]
    assert "exit status 1" in out


# --- what a user meets first: --version, exit statuses in --help, figures optional ------------------------------

# runs `jaxnh ARGS` in a fresh process in which matplotlib cannot be imported, as if it were not installed
WITHOUT_MATPLOTLIB = (
    "import sys\nsys.modules['matplotlib'] = None\nfrom jaxnh.cli import main\nsys.exit(main(sys.argv[1:]))\n"
)


def run_without_matplotlib(args, cwd, timeout):
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    return subprocess.run(
        [sys.executable, "-c", WITHOUT_MATPLOTLIB, *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_version(capsys):
    from importlib import metadata

    import jaxnh

    code, out, err = run(["--version"], capsys)
    assert code == 0 and err == ""
    assert out == f"jaxnh {jaxnh.__version__}\n"
    assert jaxnh.__version__ == metadata.version("jaxnh")  # pyproject reads the version from jaxnh/__init__.py


@pytest.mark.parametrize("command", [[], ["demo"], ["fit"], ["design"]])
def test_every_help_documents_the_exit_statuses(capsys, command):
    code, out, err = run([*command, "--help"], capsys)
    assert code == 0, err
    text = out[out.index("exit status") :]
    for status in ("0", "1", "2", "130"):
        assert re.search(rf"(^|\s){status}\s", text), (command, status, text)
    assert "matplotlib" in text  # what happens without it


def test_plotting_note_without_matplotlib(monkeypatch, capsys):
    from jaxnh._cli.common import plotting_available

    assert plotting_available("fit", "no figures")
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if not installed
    monkeypatch.delitem(sys.modules, "matplotlib.pyplot", raising=False)
    assert not plotting_available("fit", "no figures are drawn")
    err = capsys.readouterr().err
    assert err.startswith("jaxnh fit: matplotlib is not installed: no figures are drawn (pip install matplotlib")
    assert "jaxnh[plot]" in err and "Traceback" not in err


def test_design_leaves_out_only_the_figure_without_matplotlib(tmp_path, monkeypatch, capsys):
    """The set-up before the (long) design itself: the figure is dropped from the outputs, with a note."""
    import jaxnh._cli.design as design

    seen = {}

    def fake_run(args, files):
        seen.update(files)
        return 0

    monkeypatch.setattr(design, "_run", fake_run)
    monkeypatch.setenv("MPLBACKEND", "Agg")  # main() sets it when matplotlib is not imported: restored after
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.delitem(sys.modules, "matplotlib.pyplot", raising=False)
    code, out, err = run(["design", "--out", str(tmp_path / "d")], capsys)
    assert code == 0
    assert sorted(os.path.basename(f) for f in seen.values()) == ["design.json", "designed_input.csv"]
    assert "jaxnh design: matplotlib is not installed: design.png is not drawn" in err


def test_fit_without_matplotlib_writes_json_and_exits_0(tmp_path):
    data = tmp_path / "d.csv"
    data.write_text(cli_model.record_text())
    proc = run_without_matplotlib(
        ["fit", str(data), "--model", MODEL, "--json", "fit.json", "--out", "figs", "--quiet"], tmp_path, 600
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    assert "jaxnh fit: matplotlib is not installed: no figures are drawn into --out figs" in proc.stderr
    assert json.loads((tmp_path / "fit.json").read_text())["status"] == "fitted"
    assert sorted(os.listdir(tmp_path)) == ["d.csv", "fit.json"]  # no figures folder, no temporary files


@pytest.mark.extended
def test_design_without_matplotlib_writes_csv_and_json(tmp_path):
    """The issue's case: the design ran, wrote its CSV and JSON, then died importing matplotlib (exit 1).
    Smallest settings: the embedded record's set-up is fixed, so most of the time is compilation
    (3–5 minutes on 2 busy cores with an empty compilation cache, half a minute with a warm one)."""
    proc = run_without_matplotlib(
        ["design", "--out", "d", "--starts", "1", "--steps", "1", "--harmonics", "1"], tmp_path, 1800
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    rep = json.loads((tmp_path / "d" / "design.json").read_text())
    assert proc.returncode == (0 if rep["check"]["feasible"] else 1), proc.stdout + proc.stderr
    assert sorted(os.listdir(tmp_path / "d")) == ["design.json", "designed_input.csv"]
    assert "jaxnh design: matplotlib is not installed: design.png is not drawn" in proc.stderr
    # progress before the long compilations, on stderr (stdout keeps the results)
    assert "jaxnh design: compiling the experiment's simulation and its sensitivities (a first run" in proc.stderr
    assert "jaxnh design: compiling the design criterion and its gradient" in proc.stderr
    assert "compiling" not in proc.stdout


# --- output folders are checked before any work, for every command --------------------------------


@pytest.fixture
def no_demo(monkeypatch):
    """Fail loudly if `jaxnh demo` starts its work: the output checks must come first."""
    import jaxnh._cli.main as cli_main

    def boom(*a, **k):
        raise AssertionError("the demo started before --out was checked")

    monkeypatch.setattr(cli_main, "run", boom)


def _assert_refused(code, err, command, pattern):
    assert code == 2, err
    assert err.startswith(f"jaxnh {command}: "), err
    assert "Traceback" not in err, err
    assert re.search(pattern, err), err


@pytest.mark.parametrize("sub", [False, True])
def test_demo_unwritable_out_exits_2_before_any_work(tmp_path, capsys, no_demo, sub):
    ro = _unwritable_folder(tmp_path)
    out = os.path.join(ro, "sub") if sub else str(ro)
    code, _, err = run(["demo", "--out", out, "--no-fit"], capsys)
    _assert_refused(code, err, "demo", r"--out .*not writable")


@pytest.mark.parametrize("command", ["demo", "fit"])
def test_a_folder_refusing_files_despite_its_permissions_exits_2(
    tmp_path, capsys, no_demo, no_fit, monkeypatch, command
):
    """Permission bits pass (root, or a read-only file system): creating a file is what tells."""
    import errno
    import tempfile

    def refuse(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    code, _, err = run([command, "--out", str(tmp_path / "o"), *(["--no-fit"] if command == "demo" else [])], capsys)
    _assert_refused(code, err, command, r"--out .*cannot create a file in .*Read-only file system")
    assert listing(tmp_path) == []


def test_fit_unwritable_out_exits_2_before_fitting(tmp_path, capsys, no_fit):
    ro = _unwritable_folder(tmp_path)
    code, _, err = run(["fit", "--out", os.path.join(ro, "figs"), "--quiet"], capsys)
    assert_bad_input(code, err, r"--out .*not writable")


@pytest.mark.parametrize("command,name", [("demo", "variator_methods.png"), ("fit", "fit_ratio.png")])
def test_an_output_file_taken_by_a_folder_exits_2(tmp_path, capsys, no_demo, no_fit, command, name):
    (tmp_path / name).mkdir()
    code, _, err = run([command, "--out", str(tmp_path), *(["--no-fit"] if command == "demo" else [])], capsys)
    _assert_refused(code, err, command, rf"--out: .*{re.escape(name)} is a folder")


def test_an_infeasible_design_names_the_limit_and_by_how_much():
    from jaxnh._cli.design import broken_limits

    check = {"status": 0, "criterion": 1.0, "stick": 1.25, "energy": 0.5, "std": 1.1}
    text = broken_limits(check, "|F| ≤ μs N = 0.3 × 40 N (roller r = 0.05 m)")
    assert (
        "the friction cone (|F| ≤ μs N = 0.3 × 40 N (roller r = 0.05 m)): reaches 1.25 × the limit (25 % over)" in text
    )
    assert "J2 and the U21 knots no less precise" in text and "1.1 × the limit (10 % over)" in text
    assert "energy" not in text  # within its limit
    assert "cannot be simulated" in broken_limits({"status": 3, "stick": 0.5}, "")
