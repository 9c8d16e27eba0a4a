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
* Executed examples are cached per page in .cache/docs-exec (see "Cache of
  executed examples" below); JAXNH_DOCS_CACHE=off runs them all.
"""

from __future__ import annotations

import hashlib
import html
import json
import logging
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from importlib import metadata
from pathlib import Path
from typing import Any

import markdown_exec
import standalone  # docs/standalone.py (mkdocs puts the hooks' folder on the path)
from latex2mathml import commands as _tex_commands
from latex2mathml.converter import convert as _tex_to_mathml
from markupsafe import Markup
from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File
from mkdocs.utils import CountHandler


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


# Cache of executed examples. markdown-exec's plugin sets its `formatter` (runs a block, returns
# its HTML) as the "format" of pymdownx.superfences custom fences in config.mdx_configs; on_config
# below runs after it (hooks follow `plugins:`; the priority says so too) and sets `_formatter`.
# A page's blocks are served from .cache/docs-exec all together, when the page's key matches: a
# hash of its Markdown (as on_page_markdown gets it: snippets not expanded) and `_build_digest`.
# Else they all run, and are stored (at the end of the build, if `_build_digest` has not changed)
# when the page logged no warning (a failing block logs one, so strict builds still fail) and
# does not depend on the rest of the build: markdown-exec numbers ids `exec-N--` over the whole
# build (a hit advances `MarkdownConverter.counter` as the run did), puts headings printed by
# blocks in the ToC (not replayed) and names their modules `_code_block_...`: see `_NOT_STORED`.
# Sessions are global, so pages sharing a session name are not cached, nor pages with snippets
# (`--8<--`, none today). Not replayed on a hit: process state a block leaves (jax.config...).
CACHE_DIR = ROOT / ".cache" / "docs-exec"
_KEYED = ["jaxnh", "examples", "benchmarks", "docs/*.py", "pyproject.toml", "mkdocs.yml"]
_NOT_STORED = re.compile(r"<h[1-6][\s>]|\bexec-\d+--|code_block_|&lt;code block: ")
_SESSION = re.compile(r"""\bsession=["']?([^"'\s}]+)""")
_log = logging.getLogger("mkdocs.hooks.exec_cache")
_cache: dict = {"digest": None, "shared": set(), "page": None, "reused": [], "ran": [], "pending": []}
_warnings = CountHandler(level=logging.WARNING)  # as `mkdocs build --strict` counts them


def _build_digest() -> str | None:
    """Hash of what, beyond a page's Markdown, can change its examples' output; None: no cache."""
    if os.environ.get("JAXNH_DOCS_CACHE", "on").strip().lower() in {"off", "0", "none", "", "no", "false"}:
        return None
    command = ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard", "--", *_KEYED]
    digest = hashlib.sha256(b"exec-cache 1\0")
    try:
        listed = subprocess.run(command, cwd=ROOT, capture_output=True, check=True).stdout.decode()
        for name in sorted(set(listed.split("\0")) - {""}):
            path = ROOT / name
            digest.update(name.encode() + (hashlib.sha256(path.read_bytes()).digest() if path.is_file() else b"-"))
    except (OSError, subprocess.CalledProcessError):  # no git, or a file it lists cannot be read
        return None
    # a set: a distribution found twice (the checkout's jaxnh.egg-info once mkdocstrings puts "." on
    # sys.path, and the installed one) must not change the key during the build
    versions = sorted({f"{dist.metadata['Name']}=={dist.version}" for dist in metadata.distributions()})
    env = [f"{k}={v}" for k, v in sorted(os.environ.items()) if k.startswith(("JAX", "XLA", "MPL", "PYTHON"))]
    env = [item for item in env if not item.startswith("JAXNH_DOCS_CACHE=")]
    where = os.path.relpath(os.getcwd(), ROOT)  # blocks open files relative to the working directory
    digest.update(json.dumps([sys.version, where, versions, env]).encode())
    return digest.hexdigest()


@event_priority(-100)
def on_config(config):
    _cache.update(digest=_build_digest(), page=None, reused=[], ran=[], pending=[])
    if _cache["digest"] is not None:
        for fence in config.mdx_configs.get("pymdownx.superfences", {}).get("custom_fences", []):
            if fence.get("format") is markdown_exec.formatter:
                fence["format"] = _formatter
        logging.getLogger("mkdocs").addHandler(_warnings)
    return config


def _formatter(source, language, css_class, options, md, **kwargs):
    page = _cache["page"]
    block = hashlib.sha256(repr((language, source, sorted(options.items()))).encode()).hexdigest()
    if page is not None and page["stored"] is not None:
        if page["stored"] and page["stored"][0][0] == block:
            _, output, ids = page["stored"].pop(0)
            page["served"] += 1
            markdown_exec.MarkdownConverter.counter += ids
            return Markup(output)
        if page["served"]:  # a corrupt entry, found too late to run the whole page: a strict build fails
            _log.warning(f"{page['uri']}: cached examples do not match the page; delete {CACHE_DIR}")
        page["stored"] = None
    before = markdown_exec.MarkdownConverter.counter
    output = markdown_exec.formatter(source, language, css_class, options, md, **kwargs)
    if page is not None:
        page["ran"].append([block, str(output), markdown_exec.MarkdownConverter.counter - before])
    return output


def _start_page(markdown: str, uri: str) -> None:
    _cache["page"] = None
    if _cache["digest"] is None:
        return
    key = hashlib.sha256(json.dumps([_cache["digest"], uri, markdown]).encode()).hexdigest()
    storable = "--8<--" not in markdown and not set(_SESSION.findall(markdown)) & _cache["shared"]
    page: dict[str, Any] = dict(uri=uri, path=CACHE_DIR / f"{uri.replace('/', '__')}.json", key=key)
    page.update(storable=storable, stored=None, served=0, ran=[], warned=_warnings.get_counts())
    try:
        entry = json.loads(page["path"].read_text(encoding="utf-8"))
        valid = all([type(x) for x in block] == [str, str, int] for block in entry["blocks"])
        page["stored"] = entry["blocks"] if storable and entry["key"] == key and entry["blocks"] and valid else None
    except Exception:  # no entry, unreadable or corrupt: the examples run
        pass
    _cache["page"] = page


def _finish_page() -> None:
    page, _cache["page"] = _cache["page"], None
    if page is None or not (page["ran"] or page["stored"] is not None):
        return  # no executed blocks
    _cache["ran" if page["ran"] else "reused"].append(page["uri"])
    clean = _warnings.get_counts() == page["warned"] and _log.isEnabledFor(logging.WARNING)  # not with -q
    if page["ran"] and page["storable"] and clean and not any(_NOT_STORED.search(b[1]) for b in page["ran"]):
        _cache["pending"].append((page["path"], {"key": page["key"], "blocks": page["ran"]}))


def _write_pending() -> None:
    """Store the pages run, unless a keyed file changed during the build (their outputs may mix)."""
    if _cache["pending"] and _build_digest() != _cache["digest"]:
        return _log.info("Executed examples not cached: sources changed during the build")
    from jaxnh._base.atomic import atomic_write  # (the project's one atomic writer; jaxnh is imported late)

    for path, entry in _cache["pending"]:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(path, "w", encoding="utf-8") as out:
                json.dump(entry, out)
        except OSError as error:
            _log.info(f"Cannot write the cache of executed examples {path}: {error}")


def on_files(files, config):
    for png in sorted((ROOT / "benchmarks" / "figures").glob("*.png")):
        files.append(File.generated(config, f"figures/{png.name}", abs_src_path=str(png)))
    sessions = Counter(n for f in files.documentation_pages() for n in set(_SESSION.findall(f.content_string)))
    _cache["shared"] = {name for name, count in sessions.items() if count > 1}
    return files


def on_page_markdown(markdown, page, config, files):
    for name in re.findall(r"^:::\s+([\w.]+)", markdown, flags=re.M):
        _documented.add(name)
    problem = standalone.problem(markdown, page.file.src_uri)
    if problem:
        raise PluginError(problem)
    _start_page(markdown, page.file.src_uri)
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
    _finish_page()
    where = page.file.src_uri
    html_text = _FORMULA.sub(lambda match: _typeset(match, where), html_text)
    if 'class="arithmatex"' in html_text:
        raise PluginError(f"{where}: a formula was left as LaTeX")
    return html_text


def on_post_build(config):
    logging.getLogger("mkdocs").removeHandler(_warnings)
    if _cache["digest"] is not None:
        ran = ", ".join(_cache["ran"]) or "none"
        _log.info(f"Executed examples: {len(_cache['reused'])} pages reused from {CACHE_DIR}, run: {ran}")
        _write_pending()
    import jaxnh

    missing = []
    for name in jaxnh.__all__:
        full = f"jaxnh.{name}"
        if full not in _documented and not any(d.startswith(full + ".") for d in _documented):
            missing.append(name)
    if missing:
        raise PluginError(f"API reference: no page documents jaxnh.{{{', '.join(missing)}}} (add `::: jaxnh.NAME`)")
