"""Test-session settings shared by every test module."""

import os

# The command line turns on JAX's persistent compilation cache (jaxnh.cli.use_compilation_cache);
# tests that call jaxnh.cli.main in-process must not switch it on for the rest of the session
# or write to the user's cache folder.
os.environ.setdefault("JAXNH_CACHE_DIR", "off")
