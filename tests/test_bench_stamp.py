"""The benchmarks' staleness stamp: `benchmarks.common.source_digest` hashes the executable code of
jaxnh/ (its syntax tree without docstrings and signature annotations), so that a record measured
on today's code stays current through edits to comments, docstrings and type hints, and goes
stale with any other edit (the docs' performance page and `make bench-stale` rely on it)."""

from __future__ import annotations

import os
import sys


sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository, for benchmarks/

from benchmarks.common import _executable, source_digest  # noqa: E402


BASE = '''
import dataclasses

@dataclasses.dataclass
class Field:
    """A field."""
    rate: float = 1.0

def step(x, h):
    return x + h * x
'''


def test_documentation_and_signature_hints_leave_the_digest():
    edited = '''
import dataclasses

@dataclasses.dataclass
class Field:
    """A field, in 1/s (reworded)."""
    rate: float = 1.0  # a comment

def step(x: float, h: float) -> float:
    """One explicit Euler step."""
    return x + h * x
'''
    assert _executable(edited) == _executable(BASE)
    # a docstring written under an assignment (an attribute's, as the API pages show it) is no code
    with_attribute_doc = BASE.replace("rate: float = 1.0", 'rate: float = 1.0\n    """Growth rate (1/s)."""')
    assert _executable(with_attribute_doc) == _executable(BASE)
    # ... and neither is one in a branch, alone in a body
    branch = "if a:\n    x = 1\n    'why'\nelse:\n    'nothing to do'\n"
    assert _executable(branch) == _executable("if a:\n    x = 1\n")


def test_code_and_field_annotations_change_the_digest():
    assert _executable(BASE.replace("h * x", "h * x * x")) != _executable(BASE)
    # a dataclass makes its fields from annotated assignments: their annotations are code
    assert _executable(BASE.replace("rate: float = 1.0", "rate = 1.0")) != _executable(BASE)
    # a string that is a value, not a statement of its own, is code
    assert _executable("x = 'a'\n") != _executable("x = 'b'\n")
    assert _executable("f('a')\n") != _executable("f('b')\n")


def test_the_digest_of_the_package_is_a_stable_hex_stamp():
    d = source_digest()
    assert len(d) == 16 and int(d, 16) >= 0 and d == source_digest()
