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

import gc
import os

import jax
import pytest


os.environ["JAXNH_CACHE_DIR"] = "off"


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop every compiled program when a test module ends.

    Each program XLA compiles for the CPU holds about three memory mappings of its own, freed only
    when the program is. A worker that keeps all programs of the whole suite reaches Linux's default
    limit of 65 530 mappings per process (`vm.max_map_count`: 58 508 counted in one worker near the
    end of the suite), and XLA's next compilation then aborts the worker. Modules share compiled
    functions between their own tests only, so nothing of use is dropped.
    """
    yield
    jax.clear_caches()
    gc.collect()
