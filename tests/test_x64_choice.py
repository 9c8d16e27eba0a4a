"""Importing jaxnh turns on JAX's 64-bit mode only for a user who has not chosen a precision, each
case in a fresh interpreter (the flag is global to a process, and set at import).

A choice is seen when it leaves a public trace: JAX's environment variable `JAX_ENABLE_X64` set
(to anything), jaxnh's `JAXNH_X64=0`, or the flag already on. An update to False before the import
equals JAX's default and leaves no trace: it is the documented limit (docs/faq.md), shown as such.
With float32 in force, `simulate` runs in float32 and refuses a tolerance float32 cannot meet.
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest


REPORT = "import jax, json; print(json.dumps({'x64': bool(jax.config.jax_enable_x64)}))"


def _run(code: str, **env: str) -> dict:
    """Run `code` in a fresh interpreter with JAX's and jaxnh's precision variables cleared, then
    `env` set; the last line it prints is JSON."""
    environ = {k: v for k, v in os.environ.items() if k not in ("JAX_ENABLE_X64", "JAXNH_X64")}
    environ.update(env, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], env=environ, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_user_who_has_not_chosen_gets_64_bit_mode():
    assert _run("import jaxnh\n" + REPORT) == {"x64": True}
    # jax imported first, flag untouched: the same
    assert _run("import jax\nimport jaxnh\n" + REPORT) == {"x64": True}


@pytest.mark.parametrize("value", ["0", "false", "1"])
def test_jax_enable_x64_in_the_environment_is_left_alone(value):
    assert _run("import jaxnh\n" + REPORT, JAX_ENABLE_X64=value) == {"x64": value == "1"}


def test_jaxnh_x64_0_and_a_flag_set_on_before_the_import_are_left_alone():
    assert _run("import jaxnh\n" + REPORT, JAXNH_X64="0") == {"x64": False}
    code = "import jax\njax.config.update('jax_enable_x64', True)\nimport jaxnh\n" + REPORT
    assert _run(code) == {"x64": True}


def test_an_update_to_false_before_the_import_is_not_seen_and_one_after_it_holds():
    """JAX's default is False: setting it to False before the import cannot be told from not
    choosing, and jaxnh turns 64-bit mode on (the limit the FAQ states). Set after the import, the
    choice holds: jaxnh never touches the flag again (not when simulating either)."""
    before = "import jax\njax.config.update('jax_enable_x64', False)\nimport jaxnh\n" + REPORT
    assert _run(before) == {"x64": True}
    after = """
        import jax, json
        import jaxnh as nh
        jax.config.update("jax_enable_x64", False)
        from jaxnh.models import variator as V
        import jax.numpy as jnp
        p = V.default_params()
        nh.simulate(V.mechanism(), p, jnp.zeros(2), jnp.array([1.0, 1.0]), jnp.linspace(0.0, 1.0, 5), rtol=1e-5)
        print(json.dumps({"x64": bool(jax.config.jax_enable_x64)}))
    """
    assert _run(after) == {"x64": False}


def test_simulate_in_float32_when_the_user_chose_it():
    """With JAX_ENABLE_X64=0, Python floats are float32: simulate keeps float32 and meets its
    tolerance against the (float64, numpy) closed form; the default rtol 1e-8, below float32's
    resolution, is refused with an error naming rtol and the fix.

    Bound: each accepted step may leave √n (atol + rtol |y|) in one of the n = 2 components of the
    state (the RMS error norm of the controller), and the n_acc steps' errors add up with no
    cancellation assumed (the flow carries them with a gain of 1: the angles' error stays, it
    does not grow); plus float32's rounding of the angles themselves, eps |q| per step. A looser
    bound than the ones tests/test_float32.py derives in detail: this one tells a float32 run that
    works from one that does not."""
    code = """
        import json
        import numpy as np
        import jax.numpy as jnp
        import jaxnh as nh
        from jaxnh.models import variator as V
        p = V.default_params()
        ts = jnp.linspace(0.0, 3.0, 31)
        qd0 = jnp.array([1.0, float(p.U21(0.0))])
        try:
            nh.simulate(V.mechanism(), p, jnp.zeros(2), qd0, ts)
            refused = ""
        except ValueError as e:
            refused = str(e)
        sol = nh.simulate(V.mechanism(), p, jnp.zeros(2), qd0, ts, rtol=1e-5, atol=1e-7)
        q_ref, _ = V.closed_form(p, np.asarray(ts, np.float64), w0=1.0)
        err = float(np.max(np.abs(np.asarray(sol.q, np.float64) - np.asarray(q_ref, np.float64))))
        print(json.dumps({"dtype": str(sol.q.dtype), "message": sol.message, "err": err, "refused": refused,
                          "max_q": float(np.max(np.abs(np.asarray(q_ref)))),
                          "steps": int(sol.stats["num_accepted_steps"])}))
    """
    out = _run(code, JAX_ENABLE_X64="0")
    assert out["dtype"] == "float32" and out["message"] == "success"
    eps32 = 2.0**-23
    bound = out["steps"] * (2**0.5 * (1e-7 + 1e-5 * out["max_q"]) + eps32 * out["max_q"])
    assert 0 < out["err"] <= bound, out
    assert "rtol" in out["refused"] and "float64" in out["refused"], out["refused"]
