"""mkdocs hooks for the jaxnh site.

* The benchmark figures (benchmarks/figures/*.png) are added to the site
  under `figures/`, so the performance page shows the files `make bench`
  wrote, not copies that could go stale.
* Every name in `jaxnh.__all__` must be documented by an API page
  (`::: jaxnh.NAME` or `::: jaxnh.module`), else the build fails.
* Pages may name only Markdown files the repository holds and relative
  paths inside it (the site stands alone), else the build fails.
* Executed examples run with matplotlib's non-interactive backend.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import standalone  # docs/standalone.py (mkdocs puts the hooks' folder on the path)
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File


ROOT = Path(__file__).resolve().parents[1]
_documented: set[str] = set()


class _FreeTextRaises(logging.Filter):
    """Let free-text "Raises:" sections through without a warning.

    Some docstrings describe the errors they raise in prose rather than as
    `ExceptionType: description` pairs; griffe renders the text but warns,
    which fails a strict build. Only that one message is let through.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        return "Failed to get 'exception: description' pair" not in record.getMessage()


def on_startup(command, dirty):
    os.environ.setdefault("MPLBACKEND", "Agg")
    logging.getLogger("mkdocs.plugins.griffe").addFilter(_FreeTextRaises())
    logging.getLogger("griffe").addFilter(_FreeTextRaises())


def on_files(files, config):
    for png in sorted((ROOT / "benchmarks" / "figures").glob("*.png")):
        files.append(File.generated(config, f"figures/{png.name}", abs_src_path=str(png)))
    return files


def on_page_markdown(markdown, page, config, files):
    for name in re.findall(r"^:::\s+([\w.]+)", markdown, flags=re.M):
        _documented.add(name)
    problem = standalone.problem(markdown, page.file.src_uri)
    if problem:
        raise PluginError(problem)
    return markdown


def on_post_build(config):
    import jaxnh

    missing = []
    for name in jaxnh.__all__:
        full = f"jaxnh.{name}"
        if full not in _documented and not any(d.startswith(full + ".") for d in _documented):
            missing.append(name)
    if missing:
        raise PluginError(f"API reference: no page documents jaxnh.{{{', '.join(missing)}}} (add `::: jaxnh.NAME`)")
