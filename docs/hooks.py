"""mkdocs hooks for the jaxnh site.

* The benchmark figures (benchmarks/figures/*.png) are added to the site
  under `figures/`, so the performance page shows the files `make bench`
  wrote, not copies that could go stale.
* Every name in `jaxnh.__all__` must be documented by an API page
  (`::: jaxnh.NAME` or `::: jaxnh.module`), else the build fails.
* Pages may name only Markdown files the repository holds and relative
  paths inside it (the site stands alone), else the build fails.
* Executed examples run with matplotlib's non-interactive backend.
* Formulas are turned into MathML while the site is built, so they show
  without MathJax or a network connection; a formula the converter cannot
  translate fails the build.
"""

from __future__ import annotations

import html
import logging
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import standalone  # docs/standalone.py (mkdocs puts the hooks' folder on the path)
from latex2mathml import commands as _tex_commands
from latex2mathml.converter import convert as _tex_to_mathml
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


# Formulas. With `generic: true`, pymdownx.arithmatex leaves each formula as LaTeX, HTML-escaped
# (& < > "), inside `<span class="arithmatex">\(...\)</span>` (inline) or
# `<div class="arithmatex">\[...\]</div>` (displayed) for a script to typeset in the browser.
# Here they become MathML instead, which Chromium (since 109), Firefox and Safari lay out
# natively (MathML Core): `<math>` is inline, `<math display="block">` displayed.
# latex2mathml lets some mistakes through silently (an unknown command becomes an identifier
# holding its name, an unknown environment is dropped, `&` outside a table is kept as a bare
# character), so the result is checked before it is used.
_FORMULA = re.compile(r'<(span|div) class="arithmatex">(.*?)</\1>', re.S)
_TAG = re.compile(r"\\tag(\*?)\s*\{([^{}]*)\}")
_ENVIRONMENT = re.compile(r"\\(?:begin|end)\s*\{([^{}]*)\}")
_TABLES = {name.lstrip("\\") for name in _tex_commands.MATRICES}
# Text arguments, left alone when the primes are rewritten.
_TEXT = re.compile(r"(\\(?:text\w*|mbox)\s*\{[^{}]*\})")
# A run of primes with an optional superscript after it: x'' and x'^2.
_PRIMES = re.compile(r"('+)(?:\^(\{(?:[^{}]|\{[^{}]*\})*\}|\\[A-Za-z]+|[^\s{}\\]))?")
_PRIME_NAMES = {1: r"\prime", 2: r"\dprime", 3: r"\trprime", 4: r"\qprime"}


def _prime_on_baseline(match: re.Match) -> str:
    n = len(match.group(1))
    primes = "{" + _PRIME_NAMES.get(n, r"\prime" * n) + "}"
    return primes + (f"^{match.group(2)}" if match.group(2) else "")


def _with_primes_on_baseline(tex: str) -> str:
    """Set primes after the symbol and its subscript, at full size: φ₁″ for `\\varphi_1''`.

    latex2mathml makes a prime a superscript, as TeX does, but the Unicode prime (U+2032) is a
    glyph already drawn small and raised, so in a superscript it comes out tiny and far above
    the symbol (Chromium, DejaVu Math TeX Gyre). It also stacks `\\varphi_1''` as φ₁′ with
    another ′ above it. A `^...` after the primes becomes their superscript: φ₁′² for
    `\\varphi_1'^2`.
    """
    parts = _TEXT.split(tex)
    parts[::2] = [_PRIMES.sub(_prime_on_baseline, part) for part in parts[::2]]
    return "".join(parts)


def _balanced(tex: str) -> bool:
    depth = 0
    for brace in re.findall(r"\\.|[{}]", tex):
        if brace in "{}":
            depth += 1 if brace == "{" else -1
            if depth < 0:
                return False
    return depth == 0


def _mathml(tex: str, display: bool) -> str:
    """MathML for the LaTeX formula `tex`; ValueError says what it cannot translate."""
    unknown = sorted({name for name in _ENVIRONMENT.findall(tex) if name not in _TABLES})
    if unknown:
        raise ValueError(f"unsupported environment {', '.join(unknown)} (supported: {', '.join(sorted(_TABLES))})")
    if not _balanced(tex):
        raise ValueError("unbalanced braces")
    try:
        mathml = _tex_to_mathml(_with_primes_on_baseline(tex), display="block" if display else "inline")
    except Exception as exc:  # latex2mathml raises bare StopIteration, IndexError, ... on bad input
        raise ValueError(f"latex2mathml failed: {type(exc).__name__} {exc}") from None
    try:
        ET.fromstring(mathml)
    except ET.ParseError:  # a bare &, as an alignment point outside a supported environment leaves
        raise ValueError("an & that belongs to no supported environment") from None
    # Symbols come out as character references (&#x0005C; for \backslash), so a backslash
    # written as such is the name of a command latex2mathml does not know.
    unknown = re.search(r">([^<]*\\[^<]*)<", mathml)
    if unknown:
        raise ValueError(f"unknown command {unknown.group(1).strip()}")
    return mathml


def _typeset(match: re.Match, where: str) -> str:
    display = match.group(1) == "div"
    source = html.unescape(match.group(2)).strip()
    opening, closing = (r"\[", r"\]") if display else (r"\(", r"\)")
    if not (source.startswith(opening) and source.endswith(closing)):
        raise PluginError(f"{where}: formula not delimited by {opening} {closing}: {source}")
    tex = source[2:-2]
    # \tag{n} prints (n) and \tag*{n} prints n at the right margin; MathML has no such thing, so
    # the number is taken out and set beside the formula (docs/assets/extra.css, .eq).
    tags = _TAG.findall(tex)
    if len(tags) > 1 or (tags and not display):
        raise PluginError(f"{where}: only a displayed formula may have a tag, and one: {source}")
    tex = _TAG.sub("", tex)
    try:
        mathml = _mathml(tex, display)
    except ValueError as exc:
        raise PluginError(f"{where}: cannot typeset {source}: {exc}") from None
    if not display:
        return mathml
    number = ""
    if tags:
        star, text = tags[0]
        number = html.escape(text.strip() if star else f"({text.strip()})")
    return f'<div class="eq">{mathml}<span class="eqno">{number}</span></div>'


def on_page_content(html_text, page, config, files):
    where = page.file.src_uri
    html_text = _FORMULA.sub(lambda match: _typeset(match, where), html_text)
    if 'class="arithmatex"' in html_text:
        raise PluginError(f"{where}: a formula was left as LaTeX")
    return html_text


def on_post_build(config):
    import jaxnh

    missing = []
    for name in jaxnh.__all__:
        full = f"jaxnh.{name}"
        if full not in _documented and not any(d.startswith(full + ".") for d in _documented):
            missing.append(name)
    if missing:
        raise PluginError(f"API reference: no page documents jaxnh.{{{', '.join(missing)}}} (add `::: jaxnh.NAME`)")
