"""The source distribution installs and carries its own tests.

Builds the sdist (and from it the wheel, as `python -m build` does) from a copy of this source
tree, installs the wheel into a fresh virtual environment, runs `jaxnh --version`,
`jaxnh demo --no-fit`, the README's example and `jaxnh design` without matplotlib (the smallest
design: minutes of compilation) there from a folder outside any source tree, and collects the
unpacked sdist's own tests with that environment's Python, with no collection error; two quick
tests run in the sdist too: its documentation points only at files the sdist holds, and its
package keeps its layers.

Nothing is downloaded but the build backend (setuptools, through pip's cache): the fresh
environment sees the dependencies of the environment running this test through a `.pth` file
naming a folder of links to them, with this tree's own jaxnh left out, so the import of jaxnh
there finds only the newly installed copy.
"""

import glob
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import time

import pytest


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COPY_IGNORE = shutil.ignore_patterns(
    ".git",
    ".venv*",
    ".hypothesis",
    ".pytest_cache",
    ".ruff_cache",
    "*.egg-info",
    "site",
    "build",
    "dist",
    "__pycache__",
    "jaxnh_out",
    "jaxnh_design",
)
# files a checkout has that the tests, the docs build or the Makefile need from the sdist
EXPECTED = [
    "pyproject.toml",
    "MANIFEST.in",
    "README.md",
    "LICENSE",
    "CITATION.cff",
    "Makefile",
    "mkdocs.yml",
    ".ci/min_pins.py",
    "jaxnh/py.typed",
    "jaxnh/data/variator_record.csv",
    "jaxnh/data/variator_truth.json",
    "tests/conftest.py",
    "tests/cli_model.py",
    "tests/test_install.py",
    "docs/index.md",
    "docs/hooks.py",
    "docs/standalone.py",
    "benchmarks/__init__.py",
    "benchmarks/reliability_cases.py",
    "benchmarks/RESULTS.md",
    "examples/make_variator_data.py",
]


def _run(cmd, cwd, env, timeout=300):
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, (
        f"{' '.join(map(str, cmd))} exited {out.returncode}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    )
    return out


def _dependencies_folder(folder):
    """A folder of links to this environment's installed packages, without jaxnh or any .pth file."""
    os.makedirs(folder)
    purelib = sysconfig.get_paths()["purelib"]
    for name in os.listdir(purelib):
        if name.endswith(".pth") or "jaxnh" in name.lower():  # the editable install's finder and metadata
            continue
        os.symlink(os.path.join(purelib, name), os.path.join(folder, name))
    return folder


@pytest.mark.extended
def test_sdist_installs_and_collects_its_own_tests(tmp_path):
    pytest.importorskip("build", reason="the test extra's `build` builds the sdist (pip install -e '.[test]')")
    started = time.perf_counter()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["JAXNH_CACHE_DIR"] = "off"

    # 1. sdist and wheel (built from the sdist) from a copy of the tree: no build files in the tree itself
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=COPY_IGNORE, symlinks=True)
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "build", "--outdir", str(dist), str(src)], tmp_path, env)
    (sdist,) = glob.glob(str(dist / "jaxnh-*.tar.gz"))
    (wheel,) = glob.glob(str(dist / "jaxnh-*.whl"))
    with tarfile.open(sdist) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
        missing = [f for f in EXPECTED if f not in names]
        assert not missing, f"the sdist lacks {missing} (MANIFEST.in)"
        assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
        tar.extractall(tmp_path / "unpacked", filter="data")
    (unpacked,) = (tmp_path / "unpacked").iterdir()

    # 2. a fresh environment: the dependencies come from this one, jaxnh only from the wheel
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path, env)
    python = str(venv / "bin" / "python")
    site = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path, env)
    deps = _dependencies_folder(str(tmp_path / "deps"))
    (tmp_path / "outside").mkdir()
    with open(os.path.join(site.stdout.strip(), "_test_install_dependencies.pth"), "w") as f:
        f.write(deps + "\n")
    _run([python, "-m", "pip", "install", "--no-index", "--no-input", "--quiet", wheel], tmp_path, env)

    # 3. the installed command, run outside any source tree
    out = _run([str(venv / "bin" / "jaxnh"), "--version"], tmp_path / "outside", env, timeout=120)
    version = re.search(r"jaxnh-([^-]+)\.tar\.gz$", sdist)
    assert version is not None, sdist
    assert out.stdout.strip() == f"jaxnh {version.group(1)}"
    probe = (
        "import jaxnh, sys; from jaxnh.identify.data import load_default; "
        "print(jaxnh.__file__); print(load_default().n)"
    )
    out = _run([python, "-P", "-c", probe], tmp_path / "outside", env, timeout=120)
    where, n = out.stdout.split()
    assert where.startswith(str(venv)), where  # the installed copy, not a source tree
    assert int(n) > 0  # the package data (the embedded record) was installed
    # the demo from the installed command: derivations and simulations on the embedded record,
    # its figures written (the fit, minutes of compilation, is the README's `make demo`)
    demo = tmp_path / "outside" / "demo"
    out = _run([str(venv / "bin" / "jaxnh"), "demo", "--no-fit", "--out", str(demo)], demo.parent, env, timeout=600)
    assert any(demo.glob("*.png")), out.stdout + out.stderr
    # the README's example, as a user pastes it into the installed environment
    example = re.findall(r"```python\n(.*?)```", open(os.path.join(ROOT, "README.md")).read(), re.S)[0]
    out = _run([python, "-P", "-c", example], tmp_path / "outside", env, timeout=600)
    assert "success" in out.stdout, out.stdout + out.stderr
    # `jaxnh design` without the plot extra (matplotlib made unimportable), smallest settings: it writes
    # its CSV and JSON, says that it draws no figure, and exits by its documented statuses
    no_plot = "import sys\nsys.modules['matplotlib'] = None\nfrom jaxnh.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    design = [python, "-P", "-c", no_plot, "design", "--out", "d", "--starts", "1", "--steps", "1", "--harmonics", "1"]
    proc = subprocess.run(design, cwd=tmp_path / "outside", env=env, capture_output=True, text=True, timeout=1800)
    assert "Traceback" not in proc.stderr, proc.stderr
    rep = json.loads((tmp_path / "outside" / "d" / "design.json").read_text())
    assert proc.returncode == (0 if rep["check"]["feasible"] else 1), proc.stdout + proc.stderr
    assert sorted(os.listdir(tmp_path / "outside" / "d")) == ["design.json", "designed_input.csv"]
    assert "matplotlib is not installed: design.png is not drawn" in proc.stderr

    # 4. the sdist's own tests: collected without error, with the installed jaxnh (-P: not the sdist's folder)
    pytest_cmd = [python, "-P", "-m", "pytest", "-o", "addopts=", "-p", "no:cacheprovider"]  # not the -n 2 of pyproject
    out = subprocess.run(
        [*pytest_cmd, "--collect-only", "-q"], cwd=unpacked, env=env, capture_output=True, text=True, timeout=300
    )
    tail = out.stdout[-3000:] + out.stderr[-3000:]
    assert out.returncode == 0, tail
    summary = out.stdout.strip().splitlines()[-1]
    assert re.fullmatch(r"\d+ tests collected in .*", summary), tail  # "N tests collected, M errors" otherwise
    assert int(summary.split()[0]) > 100, summary
    _run(
        [
            *pytest_cmd,
            "-q",
            "tests/test_docs.py::test_the_site_may_point_only_inside_the_repository",
            "tests/test_layers.py",
        ],
        unpacked,
        env,
    )
    print(f"sdist built, installed, {summary.split(' in ')[0]}: {time.perf_counter() - started:.0f} s")
