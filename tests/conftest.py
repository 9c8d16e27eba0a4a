"""Test-session settings shared by every test module.

JAX's persistent compilation cache stays off in every test process. It is opt-in in jaxnh
(`jaxnh.enable_compilation_cache()`), but the command line turns it on for its own process, and
several tests call the command line's `main` in-process. Without this setting the first such call
would leave the cache on, in the user's ~/.cache/jaxnh, for every later test of that worker:
both xdist workers would then read and write one shared folder beside any other process of the
machine, and what a test compiles would depend on what ran before it. `JAXNH_CACHE_DIR=off` makes
`enable_compilation_cache` change nothing; tests/test_cache.py passes its own folders explicitly.

Compiled functions are shared within a module by module-level caches and fixtures.
"""

import os


os.environ["JAXNH_CACHE_DIR"] = "off"
