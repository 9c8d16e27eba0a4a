"""The documentation's "fitting your own mechanism" page runs as printed and recovers the truth.

Acceptance test of issue 17: a user goes from a DataFrame of measurements for
their own mechanism (no variator-specific code) to a fitted table by
following one page. The page's python blocks are executed in order, in one
namespace, exactly as the docs build executes them.
"""

import math
import pathlib
import re

import pytest


pytest.importorskip("pandas")

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"


def _blocks(page: str) -> list[str]:
    return re.findall(r"```python[^\n]*\n(.*?)```", (DOCS / page).read_text(), re.S)


@pytest.mark.slow
def test_fitting_page_recovers_parameters(capsys):
    env: dict = {}
    for code in _blocks("fitting.md"):
        exec(compile(code, str(DOCS / "fitting.md"), "exec"), env)
    out = capsys.readouterr().out
    result, truth = env["result"], env["truth"]
    assert "parameter" in out and "converged" in out  # the summary table was printed
    assert result.converged, result.message
    assert result.identifiable
    # Synthetic data with known noise: each estimate within 4 standard errors of the truth (a 6e-5
    # two-sided chance per parameter for a correct fit), and the standard errors are finite and small.
    for name in ("m", "I_C", "a"):
        est = result.estimates[name]
        assert math.isfinite(est["std"]) and est["std"] < 0.2 * abs(est["value"]), (name, est)
        assert abs(est["value"] - float(truth[name])) < 4 * est["std"], (name, est, float(truth[name]))
    # The model is right and the noise known to the generator: s² near 1 (121 samples × 3 channels).
    assert 0.7 < result.chi2_dof < 1.4, result.chi2_dof


def test_the_site_may_point_only_inside_the_repository(tmp_path):
    """The check the docs build runs on every page (docs/standalone.py): Markdown files the
    repository holds and relative paths inside it pass; anything else fails the build."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("standalone", DOCS / "standalone.py")
    assert spec is not None and spec.loader is not None
    standalone = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(standalone)

    (tmp_path / "docs" / "api").mkdir(parents=True)
    (tmp_path / "README.md").write_text("x")
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "RESULTS.md").write_text("x")
    ok = "See README.md, [results](../benchmarks/RESULTS.md) and `benchmarks/RESULTS.md`."
    assert standalone.problem(ok, "faq.md", tmp_path) is None
    assert standalone.problem("[up](../../README.md)", "api/index.md", tmp_path) is None
    missing = standalone.problem("as the notes in PLAN.md say", "faq.md", tmp_path)
    assert missing is not None and "PLAN.md" in missing
    outside = standalone.problem("see ../../elsewhere/seed/paper.pdf", "faq.md", tmp_path)
    assert outside is not None and "outside the repository" in outside
    # the real site passes
    for page in sorted(DOCS.rglob("*.md")):
        assert standalone.problem(page.read_text(), str(page.relative_to(DOCS))) is None, page
