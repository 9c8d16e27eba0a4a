"""The one place where jaxnh reads or sets anything that is not public API of JAX or equinox.

Each item here has a plain fallback: if a future release moves what it touches, jaxnh keeps
working, only a little slower or with less detailed messages (`tests/test_layers.py` checks
that no other module reaches into private names, and `tests/test_compat.py` runs each fallback).

* `status_code`, `status_messages`: equinox's `Enumeration` keeps an item's integer code and
  the table of messages in private attributes (`_value`, `_index_to_message`). jaxnh's statuses
  (`jaxnh.STATUS`) extend diffrax's `RESULTS` and must stay an equinox `Enumeration`, so that a
  diffrax result can be promoted to one inside a compiled program. Fallback: none is needed
  while equinox keeps these names; should they go, the test of this module fails first.
* `no_host_callbacks`: equinox's run-time checks (`eqx.error_if`, which diffrax uses on its
  inputs even with `throw=False`) become host callbacks; a program with host callbacks cannot be
  stored in JAX's persistent compilation cache. jaxnh checks those inputs itself (a failure is a
  `STATUS`), so while tracing its own solves it switches equinox's checks to the "nan" mode.
  equinox reads that mode from `equinox._errors.EQX_ON_ERROR` when a check is traced (the public
  switch is the environment variable `EQX_ON_ERROR`, read once at import). Fallback: when the
  attribute is missing, nothing is switched; programs are then compiled as usual but not cached.
"""

from __future__ import annotations

import contextlib
import importlib
from typing import Any, Iterator

import numpy as np


__all__ = ["status_code", "status_messages", "no_host_callbacks"]


def status_code(item: Any) -> Any:
    """The integer code (an int32 array, batched like the status) of an equinox `Enumeration` item."""
    return item._value


def status_messages(enumeration: Any) -> list[str]:
    """The message of each code of an equinox `Enumeration`, indexed by code."""
    table = enumeration._index_to_message
    return [table[i] for i in range(len(table))]


def status_code_int(item: Any) -> int:
    """`status_code` of a concrete, unbatched item as a Python int."""
    return int(np.asarray(status_code(item)))


def _equinox_errors() -> Any:
    try:
        return importlib.import_module("equinox._errors")
    except ImportError:  # a future equinox: the fallback
        return None


@contextlib.contextmanager
def no_host_callbacks() -> Iterator[None]:
    """While tracing inside this block, equinox's `error_if` gives NaN instead of a host callback."""
    errors = _equinox_errors()
    old = getattr(errors, "EQX_ON_ERROR", None)
    if errors is None or old != "raise":
        yield
        return
    setattr(errors, "EQX_ON_ERROR", "nan")
    try:
        yield
    finally:
        setattr(errors, "EQX_ON_ERROR", old)
