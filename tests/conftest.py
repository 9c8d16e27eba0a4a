"""Test-session settings shared by every test module.

None at present: each test process compiles its own programs (JAX's persistent
compilation cache is opt-in in jaxnh, `jaxnh.enable_compilation_cache()`, and the
suite does not turn it on). Compiled functions are shared within a module by
module-level caches and fixtures.
"""
