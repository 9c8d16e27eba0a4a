"""Test-session settings shared by every test module.

JAX's persistent compilation cache stays off in every test process. It is opt-in in jaxnh
(`jaxnh.enable_compilation_cache()`), but the command line turns it on for its own process, and
several tests call the command line's `main` in-process. Without this setting the first such call
would leave the cache on, in the user's ~/.cache/jaxnh, for every later test of that worker:
both xdist workers would then read and write one shared folder beside any other process of the
machine, and what a test compiles would depend on what ran before it. `JAXNH_CACHE_DIR=off` makes
`enable_compilation_cache` change nothing; tests/test_cache.py passes its own folders explicitly.

Compiled functions are shared within a module by module-level caches and fixtures.

Tiers: `make test-quick` runs the tests not marked `slow`; `make test` (what CI runs) adds the slow
ones except those marked `extended`; `make test-all` runs every test. An `extended` test is one
more case of a class a quicker test already guards (another formulation, frame or option pair, a
longer horizon), or a packaging check; it counts as slow too.
"""

import gc
import os

import jax
import pytest


os.environ["JAXNH_CACHE_DIR"] = "off"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """An `extended` test is slow as well, so `-m "not slow"` leaves it out."""
    for item in items:
        if item.get_closest_marker("extended") is not None:
            item.add_marker(pytest.mark.slow)


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
