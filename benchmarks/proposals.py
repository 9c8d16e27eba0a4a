"""The library changes proposed in /tmp/issue4_core.patch, usable before they are applied.

Each name resolves to jaxnh's own implementation when the patch is in, and to
the copy kept in `benchmarks/` otherwise:

* `Tsit5` — Tsitouras 5(4) with unrolled stages (`jaxnh.solvers.Tsit5`).
* `ForwardSensitivity` — derivatives of `simulate` by forward sensitivities
  (`jaxnh.ForwardSensitivity`); `install()` routes it through `simulate` by
  wrapping the `diffrax.diffeqsolve` that `jaxnh.simulate` calls.
* `auto_adjoint(params, q0, qd0)` — the automatic choice of derivative mode.
* `default_solver(rtol)` — the proposed default solver.
* `install_split()` — dependent velocities, B and β from one elimination with
  an unrolled pivoted solve, and the initial-state checks compiled.
"""

from __future__ import annotations

import sys
import types

import diffrax

import jaxnh
import jaxnh.solvers

from . import _proposed_solvers, _proposed_split, _sensitivity

_sim = sys.modules["jaxnh.simulate"]

Tsit5 = getattr(jaxnh.solvers, "Tsit5", None) or _proposed_solvers.Tsit5
_native_sens = getattr(jaxnh, "ForwardSensitivity", None)
ForwardSensitivity = _native_sens or _sensitivity.ForwardSensitivity
auto_adjoint = getattr(sys.modules.get("jaxnh.sensitivity"), "auto_adjoint", None) or _sensitivity.auto_adjoint

DOP853_BELOW_RTOL = 1e-6
"""Proposed: DOP853 for rtol below this, the unrolled Tsit5 above (see RESULTS.md)."""


def default_solver(rtol: float):
    """The proposed `jaxnh.simulate.default_solver`."""
    return jaxnh.solvers.DOP853() if rtol < DOP853_BELOW_RTOL else Tsit5()


_native_split = hasattr(jaxnh.linalg, "solve_square")


def applied() -> dict:
    """Which proposals jaxnh carries natively, and which the benchmarks have patched in."""
    return {
        "native": {"Tsit5_unrolled": hasattr(jaxnh.solvers, "Tsit5"), "ForwardSensitivity": _native_sens is not None,
                   "split_solves": _native_split},
        "monkeypatched": sorted(_installed),
    }


_installed: set = set()


def install_sensitivity() -> None:
    """Let `simulate(adjoint=ForwardSensitivity())` work when jaxnh lacks it (idempotent)."""
    if "sensitivity" in _installed or _native_sens is not None:
        return
    proxy = types.ModuleType("diffrax_with_forward_sensitivity")
    proxy.__dict__.update({k: v for k, v in vars(diffrax).items() if not k.startswith("__")})
    proxy.diffeqsolve = _sensitivity.diffeqsolve
    _sim.diffrax = proxy
    _installed.add("sensitivity")


def install_split() -> None:
    """The proposed split.py/linalg.py changes: one elimination for qd, B, β; compiled checks."""
    if "split" in _installed or _native_split:
        return
    import jaxnh.equations as eqs
    import jaxnh.equations.split as sp

    orig = sp.VelocitySplit.velocities_and_rates

    def velocities_and_rates(self, q, v, t, params):
        if self.mech.nonlinear_constraints:
            return orig(self, q, v, t, params)
        return _proposed_split.velocities_and_rates_linear(self, q, v, t, params)

    sp.VelocitySplit.velocities_and_rates = velocities_and_rates
    jaxnh.Mechanism.check_shapes = _proposed_split.check_shapes_memoized(jaxnh.Mechanism.check_shapes)
    sp.solve_square = _proposed_split.solve_square
    for mod in (sp, eqs, jaxnh):
        if hasattr(mod, "choose_independent"):
            mod.choose_independent = _proposed_split.choose_independent
        if hasattr(mod, "check_split"):
            mod.check_split = _proposed_split.check_split
    _installed.add("split")


def install() -> None:
    """Every proposal that jaxnh does not carry yet."""
    install_sensitivity()
    install_split()
