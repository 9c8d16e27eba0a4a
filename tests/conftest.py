"""Test-session settings shared by every test module.

The suite uses JAX's persistent compilation cache like any jaxnh user (in
`~/.cache/jaxnh`, or `$JAXNH_CACHE_DIR`): a second run of the suite loads its
compiled programs instead of compiling them again.
"""
