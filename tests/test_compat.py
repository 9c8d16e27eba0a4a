"""What `jaxnh/_base/compat.py` provides, and that jaxnh leaves equinox's behaviour alone.

* `status_code`, `status_messages`, `status_code_int` read private attributes of equinox's
  `Enumeration`: they are checked against what equinox's public API says about the same items
  (`STATUS[item]` is an item's message, `==` compares items, `STATUS.where` and `STATUS.promote`
  make traced and promoted items), so that an equinox release that moves those attributes fails
  here first.
* A user's own `eqx.error_if`, traced while a jaxnh solve is traced (in the user's forces or an
  event's condition), keeps equinox's configured behaviour (`EQX_ON_ERROR`, "raise" unless the
  user set it): jaxnh no longer switches equinox to "nan" while it traces a solve.
* No module of jaxnh imports `equinox.internal` or a private `equinox._` module (the scanner is
  checked on sources that do).
* `jaxnh.solvers.UnrolledTsit5` uses diffrax's public Tsit5 tableau, and its step equals
  `diffrax.Tsit5`'s to rounding.
"""

from __future__ import annotations

import ast
import pathlib
import threading

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh._base.compat import status_code, status_code_int, status_messages
from jaxnh._solve import rk


PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "jaxnh"

# Items from both halves of STATUS: diffrax's own results and jaxnh's additions.
NAMES = ["successful", "max_steps_reached", "singular", "non_finite_input", "bad_report_times", "singular_split"]


# --- status codes and messages -----------------------------------------------------------------


def test_codes_and_messages_agree_with_equinox_public_api():
    messages = status_messages(nh.STATUS)
    assert len(messages) == len(nh.STATUS)
    items = [getattr(nh.STATUS, n) for n in NAMES]
    codes = [status_code_int(i) for i in items]
    assert codes[0] == 0  # `successful` is code 0 in equinox's enumerations (diffrax tests `== 0`)
    assert len(set(codes)) == len(codes), codes  # distinct items, distinct codes
    for name, item, code in zip(NAMES, items, codes):
        assert 0 <= code < len(messages), name
        assert messages[code] == nh.STATUS[item], name  # the public lookup of an item's message
    for a, ca in zip(items, codes):  # equal codes exactly when equinox calls the items equal
        for b, cb in zip(items, codes):
            assert bool(a == b) == (ca == cb)


def test_a_promoted_diffrax_result_keeps_its_message():
    item = nh.STATUS.promote(diffrax.RESULTS.max_steps_reached)
    assert status_messages(nh.STATUS)[status_code_int(item)] == diffrax.RESULTS[diffrax.RESULTS.max_steps_reached]
    assert status_code_int(item) == status_code_int(nh.STATUS.max_steps_reached)


def test_codes_of_traced_and_batched_items():
    a, b = nh.STATUS.non_finite_input, nh.STATUS.bad_report_times

    def pick(flag):
        return status_code(nh.STATUS.where(flag, b, a))

    flags = jnp.asarray([False, True, True, False])
    want = [status_code_int(b) if f else status_code_int(a) for f in np.asarray(flags)]
    batched = jax.vmap(pick)(flags)
    assert batched.shape == (4,) and jnp.issubdtype(batched.dtype, jnp.integer)
    np.testing.assert_array_equal(np.asarray(batched), want)
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(pick))(flags)), want)


# --- a user's eqx.error_if inside a solve ------------------------------------------------------


def T(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def rolling(q, qd, t, p):
    return jnp.stack([(1.0 + 0.4 * jnp.sin(jnp.pi * t)) * qd[0] - qd[1]])


USER_MESSAGE = "user check: motor torque M1 above 1 N·m after t = 0.5 s"


def user_check(x, t, p):
    """The user's own run-time check. It can fail only after t = 0.5 s, so only inside the solve
    (jaxnh's checks of the initial state evaluate the forces at t0 = 0, where it holds)."""
    return eqx.error_if(x, (t > 0.5) & (p["M1"] > 1.0), USER_MESSAGE)


def checked_torques(q, qd, t, p):
    return user_check(jnp.stack([p["M1"], p["M2"]]), t, p)


def torques(q, qd, t, p):
    return jnp.stack([p["M1"], p["M2"]])


def far_event(t, y, args, **kwargs):
    """An event condition that never crosses zero in the run, with the user's check in it."""
    return user_check(t - 100.0, t, args)


TS = jnp.linspace(0.0, 1.0, 11)
CASES = {
    # the check in the forces: traced in the solve, and also (for the solver's choice) outside it
    "forces": (nh.Mechanism(T, constraints=rolling, forces=checked_torques), None),
    # the check in an event's condition: traced only while the solve is traced
    "event": (nh.Mechanism(T, constraints=rolling, forces=torques), diffrax.Event(far_event)),
}


def solve(where, m1):
    mech, event = CASES[where]
    p = {"J1": 0.02, "J2": 0.05, "M1": m1, "M2": -0.1}
    return nh.simulate(mech, p, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, method="appell", event=event, throw=False)


def test_default_mode_is_raise():
    """The behaviour the next test expects is equinox's default: this test process did not set
    EQX_ON_ERROR (equinox reads it once, at import)."""
    with pytest.raises(Exception, match="outside the solve"):
        jax.block_until_ready(jax.jit(lambda x: eqx.error_if(x, x > 0, "outside the solve"))(jnp.asarray(1.0)))


@pytest.mark.parametrize(("where", "transform"), [("forces", "eager"), ("event", "jit")])
def test_users_error_if_inside_a_solve_still_raises(where, transform):
    """The user's check, traced as part of the solve, raises with the user's message when it fails
    (and the solve runs as usual when it holds)."""
    run = (lambda m1: solve(where, m1)) if transform == "eager" else jax.jit(lambda m1: solve(where, m1))
    sol = run(0.3)
    assert status_code_int(sol.status) == 0, sol.message
    assert np.all(np.isfinite(np.asarray(sol.q)))
    with pytest.raises(Exception, match=USER_MESSAGE):
        jax.block_until_ready(run(2.0).q)


def test_users_error_if_traced_in_another_thread_during_a_solve_still_raises():
    """jaxnh used to set equinox's process-wide mode to "nan" for as long as it traced a solve, so a
    check the user traced meanwhile, in another thread, returned NaN instead of raising. One thread
    traces and compiles a solve (a new mechanism: nothing cached) while this one traces and runs
    fresh checks (a new message each, so equinox traces each anew) until the solve is done: every
    one must raise. With the old switch most of them returned NaN (the solve's tracing is most of
    its time); this test failed on it."""

    def kinetic(q, qd, t, p):  # a mechanism of this test's own, so the solve is traced anew
        return 0.5 * (p["J1"] * qd[0] ** 2 + 1.5 * p["J2"] * qd[1] ** 2)

    mech = nh.Mechanism(kinetic, constraints=rolling, forces=torques)
    p = {"J1": 0.02, "J2": 0.05, "M1": 0.3, "M2": -0.1}
    results = []
    worker = threading.Thread(
        target=lambda: results.append(nh.simulate(mech, p, jnp.zeros(2), jnp.array([2.0, 2.0]), TS, throw=False))
    )
    outcomes = []
    worker.start()
    while worker.is_alive() or not outcomes:
        message = f"user check number {len(outcomes)}"
        try:
            out = jax.jit(lambda x: eqx.error_if(x, x > 0, message))(jnp.asarray(1.0))
            outcomes.append(f"returned {float(out)}")
        except Exception as e:  # what equinox raises: its own error or JAX's, carrying the message
            outcomes.append("raised" if message in str(e) else f"raised another error: {e}")
    worker.join()
    assert results and status_code_int(results[0].status) == 0, "the solve in the other thread failed"
    assert set(outcomes) == {"raised"}, [o for o in outcomes if o != "raised"][:5]


# --- no private equinox imports ----------------------------------------------------------------


def _private(module: str) -> bool:
    parts = module.split(".")
    return parts[0] == "equinox" and len(parts) > 1 and (parts[1] == "internal" or parts[1].startswith("_"))


def private_equinox_uses(source: str) -> list[str]:
    """Each use of `equinox.internal` or of a private `equinox._…` module in `source`: imports
    (`import`, `from … import`, including `from equinox import internal`), `importlib.import_module`
    or `__import__` of such a name, and attribute access through an alias of equinox."""
    found = []
    aliases = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "equinox":
                    aliases.add(a.asname or "equinox")
                if _private(a.name):
                    found.append(f"import {a.name}")
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if _private(node.module):
                found.append(f"from {node.module} import ...")
            elif node.module == "equinox":
                found += [f"from equinox import {a.name}" for a in node.names if _private(f"equinox.{a.name}")]
        elif isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
            if name in ("import_module", "__import__"):
                for arg in node.args[:1]:
                    if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and _private(arg.value):
                        found.append(f"{name}({arg.value!r})")
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
            if _private(f"equinox.{node.attr}"):
                found.append(f"{node.value.id}.{node.attr}")
    return found


@pytest.mark.parametrize(
    "source",
    [
        "import equinox.internal as eqxi",
        "import equinox._errors",
        "from equinox.internal import unvmap_any",
        "from equinox._enum import Enumeration",
        "from equinox import internal",
        "import importlib\nimportlib.import_module('equinox._errors')",
        "import equinox as eqx\nx = eqx.internal.unvmap_any",
        "import equinox\nequinox._errors.EQX_ON_ERROR = 'nan'",
    ],
)
def test_the_scanner_finds_private_equinox_uses(source):
    assert private_equinox_uses(source), source


def test_the_scanner_passes_public_uses():
    source = "import equinox as eqx\nfrom equinox import Module, error_if\nx = eqx.filter_jit\n# equinox.internal"
    assert private_equinox_uses(source) == []


def test_jaxnh_uses_no_private_equinox_module():
    paths = sorted(PACKAGE.rglob("*.py"))
    assert PACKAGE / "_solve" / "rk.py" in paths and len(paths) > 20
    found = {str(p.relative_to(PACKAGE)): private_equinox_uses(p.read_text()) for p in paths}
    assert {k: v for k, v in found.items() if v} == {}


# --- the unrolled Tsit5 ------------------------------------------------------------------------


def test_unrolled_tsit5_tableau_is_diffrax_tsit5_tableau():
    """The coefficients the unrolled stages use, laid out as diffrax's Butcher tableau, equal
    `diffrax.Tsit5.tableau` exactly (including its zero entries)."""
    tab = diffrax.Tsit5.tableau
    assert rk._T5_C[0] == 0.0 and len(rk._T5_C) == tab.num_stages == 7
    np.testing.assert_array_equal(np.asarray(rk._T5_C[1:]), tab.c)
    for i in range(2, 7):
        row = np.array([rk._T5_A[i].get(j, 0.0) for j in range(1, i)])
        np.testing.assert_array_equal(row, tab.a_lower[i - 2], err_msg=f"row {i}")
    b = np.array([rk._T5_B.get(j, 0.0) for j in range(1, 8)])
    np.testing.assert_array_equal(b, tab.b_sol)
    np.testing.assert_array_equal(tab.a_lower[5], tab.b_sol[:6])  # stage 7 is f(t1, y1): FSAL
    assert tab.fsal
    np.testing.assert_array_equal(np.array([rk._T5_E.get(j, 0.0) for j in range(1, 8)]), tab.b_error)


def test_unrolled_tsit5_step_equals_diffrax_tsit5():
    """One step of each solver on y' = A y + sin(t) (3 states, float64): same y1, error estimate
    and dense output to rounding. The coefficients are equal; the stages are summed in another
    order (diffrax: a product with the stacked stages; here: a chain of multiply-adds). Each sum
    has at most 7 terms, so each differs by at most about 7 eps · Σ|a_ij k_j|; the largest
    coefficients are about 13 and |k_j| ≤ h max|f| ≈ 0.1 · 4, and stage errors pass through at
    most 6 more such sums: 1e3 eps (2e-13) on values of order 1 is a bound with margin, far below
    any coefficient error (a coefficient wrong in its 8th digit changes y1 by ~1e-9)."""
    A = jnp.array([[-1.0, 2.0, 0.0], [-2.0, -1.0, 0.5], [0.0, -0.5, -0.3]])
    term = diffrax.ODETerm(lambda t, y, args: A @ y + jnp.sin(t))
    y0 = jnp.array([1.0, -0.5, 0.25])
    t0, t1 = 0.3, 0.4
    outs = []
    for solver in (rk.UnrolledTsit5(), diffrax.Tsit5()):
        state = solver.init(term, t0, t1, y0, None)
        y1, err, dense, _, result = solver.step(term, t0, t1, y0, None, state, False)
        interp = solver.interpolation_cls(t0=t0, t1=t1, **dense)
        outs.append((y1, err, interp.evaluate(0.37)))
        assert result == diffrax.RESULTS.successful
    tol = 1e3 * np.finfo(np.float64).eps
    for name, a, b in zip(("y1", "error estimate", "dense output"), *outs):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=tol, err_msg=name)
    assert float(jnp.max(jnp.abs(outs[0][1]))) > 1e3 * tol  # the error estimates compared are not rounding noise
