"""The documentation stands alone: a check used by the site build (docs/hooks.py) and the tests.

A page may name only Markdown files that the repository holds, and relative
paths that stay inside the repository: a reader of the site has nothing else.
No mkdocs import here, so the test suite can exercise the check directly.
"""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path
from typing import Optional


ROOT = Path(__file__).resolve().parents[1]
_SKIP_DIRS = {"site", "node_modules", "__pycache__"}


@functools.cache
def repository_markdown(root: Path = ROOT) -> frozenset[str]:
    """Names of the Markdown files under `root` (hidden folders, such as virtual environments,
    and the built site left out)."""
    names = set()
    for folder, dirs, filenames in os.walk(root):
        dirs[:] = [d for d in dirs if not d.startswith(".") and d not in _SKIP_DIRS]
        names.update(f for f in filenames if f.endswith(".md"))
    return frozenset(names)


def problem(markdown: str, src_uri: str, root: Path = ROOT) -> Optional[str]:
    """What in page `src_uri` (relative to docs/) points outside the repository, or None."""
    known = repository_markdown(root)
    for ref in sorted(set(re.findall(r"[\w./-]*\w\.md\b", markdown))):
        if Path(ref).name not in known:
            return f"{src_uri} refers to {ref}, which is not part of the repository"
    page_dir = (root / "docs" / src_uri).parent
    for ref in sorted(set(re.findall(r"(?:\.\./)+[\w.-][\w./-]*", markdown))):
        if root not in (page_dir / ref).resolve().parents:
            return f"{src_uri} refers to {ref}, which lies outside the repository"
    return None
