"""The one place where jaxnh reads anything that is not public API of JAX or equinox.

`tests/test_layers.py` checks that no other module reaches into private names, and
`tests/test_compat.py` checks what this module provides against equinox's public behaviour, so
that a release of equinox that moves these names fails there first.

* `status_code`, `status_messages`: equinox's `Enumeration` keeps an item's integer code and
  the table of messages in private attributes (`_value`, `_index_to_message`). jaxnh's statuses
  (`jaxnh.STATUS`) extend diffrax's `RESULTS` and must stay an equinox `Enumeration`, so that a
  diffrax result can be promoted to one inside a compiled program. Fallback: none is needed
  while equinox keeps these names; should they go, the test of this module fails first.

Nothing here writes to equinox or JAX. An earlier `no_host_callbacks` set equinox's private,
process-wide `equinox._errors.EQX_ON_ERROR` to "nan" while a solve was traced, so that diffrax's
two checks of `SaveAt(ts=...)` (increasing, within [t0, t1]; `throw=False` does not remove them;
jaxnh checks the report times itself) compiled without host callbacks, and JAX's persistent
compilation cache (opt-in: `jaxnh.enable_compilation_cache()`) could store the program. It also
switched any `eqx.error_if` of the user traced in that window, in the solve or in another thread,
and was not thread-safe. No public API of JAX, equinox or diffrax removes those checks, so it was
dropped. What that costs, measured on the README's variator (first `simulate` in a fresh
process, 3 interleaved runs each, 2 cores shared with other work): from a warm cache, with the
switch the solve's program was loaded (0.4–0.8 s) and the first call took 5.8–6.5 s; without it
the program is compiled again (7.1–8.5 s) and the first call takes 11.8–13.7 s. With the cache
off (the default) both compile it (3.6–7.1 s, no consistent difference). A user who wants the
program cached can set equinox's public environment variable `EQX_ON_ERROR=nan` before importing
equinox (it then applies to every check, the user's own included).
"""

from __future__ import annotations

from typing import Any

import numpy as np


__all__ = ["status_code", "status_messages", "status_code_int"]


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
