"""jaxnh — equations of motion of mechanisms with nonholonomic constraints, in JAX.

Write the kinetic energy T (and optionally the acceleration energy S) as
plain JAX functions; jaxnh derives Lagrange's equations with multipliers or
Appell's equations by automatic differentiation, integrates them with
diffrax, and everything works under `jit`, `vmap` and `grad`.

Precision: importing jaxnh turns on JAX's 64-bit mode (`jax_enable_x64`),
because accuracy is the product — unless the user has chosen: the import
changes nothing when JAX's own environment variable `JAX_ENABLE_X64` is set
(to any value: "0" keeps float32), when `JAXNH_X64=0` is set, or when the flag
is already on. JAX keeps no record of a value set equal to its default, so
`jax.config.update("jax_enable_x64", False)` before the import cannot be told
from no choice: set the flag after `import jaxnh` (jaxnh never changes it
later) or use the environment variable. To run in float32 with 64-bit mode on,
pass float32 arrays (q0, qd0, ts and the params leaves) — the library keeps the
dtype it is given.

Importing jaxnh changes no other JAX setting. `jaxnh.enable_compilation_cache()`
turns on JAX's persistent compilation cache in the user's cache folder, so that
later processes load compiled programs instead of compiling them again.
"""

import importlib
import os
from typing import Any, TYPE_CHECKING

import jax


def _user_chose_precision() -> bool:
    """Whether the user has chosen JAX's precision before importing jaxnh, by a public signal:
    JAX's environment variable `JAX_ENABLE_X64` set (JAX reads it when it defines the flag; any
    value is a choice, "0" for float32), jaxnh's own `JAXNH_X64=0` ("leave JAX alone"), or the
    flag already on (`jax.config.update("jax_enable_x64", True)`, a command-line flag, or
    `with jax.enable_x64(True)` around the import). An update to False before the import leaves
    no trace JAX exposes (it equals JAX's default) and is not seen."""
    if "JAX_ENABLE_X64" in os.environ or os.environ.get("JAXNH_X64", "1") == "0":
        return True
    return bool(jax.config.jax_enable_x64)  # pyright: ignore[reportAttributeAccessIssue, reportUnknownArgumentType, reportUnknownMemberType] (JAX sets it at run time)


if not _user_chose_precision():  # float64 for a user who has not chosen: jaxnh's accuracy needs it
    jax.config.update("jax_enable_x64", True)  # pyright: ignore[reportUnknownMemberType] (JAX leaves it unannotated)

from jaxnh import equations, linalg, profiles, rigid, solvers  # noqa: E402
from jaxnh._analysis.friction_margin import stick_margin, StickMargin  # noqa: E402
from jaxnh._analysis.linearize import Linearization, linearize  # noqa: E402
from jaxnh._analysis.sweep import sweep  # noqa: E402
from jaxnh._base.cache import enable_compilation_cache  # noqa: E402
from jaxnh._base.compile import COMPILER_OPTIONS  # noqa: E402
from jaxnh._base.status import InvalidInitialState, SimulationError, STATUS  # noqa: E402
from jaxnh._equations import (  # noqa: E402
    accelerations,
    Appell,
    choose_independent,
    Formulation,
    Lagrange,
    METHODS,
    Substituted,
)
from jaxnh._equations.consistent import consistent_velocities  # noqa: E402
from jaxnh._equations.step_maps import StepMaps  # noqa: E402
from jaxnh._model.contacts import ContactLaw, Coulomb, FrictionContact, Multiplier, Stribeck, Viscous  # noqa: E402
from jaxnh._model.mechanism import Mechanism  # noqa: E402
from jaxnh._solve.friction import ContactDiagnostics  # noqa: E402
from jaxnh._solve.ode import ODE, ode  # noqa: E402
from jaxnh._solve.sensitivity import choose_adjoint, FORWARD_MAX_PARAMETERS, ForwardSensitivity  # noqa: E402
from jaxnh._solve.simulate import default_solver, RECORDABLE, simulate, STABILIZATIONS  # noqa: E402
from jaxnh._solve.solution import DenseMotion, Solution  # noqa: E402
from jaxnh._solve.stepping import MappedSolver  # noqa: E402


# Identification and design (optax, plotting helpers) and the built-in models are imported on first
# use: a script that only simulates does not pay for them (0.1 s of the import).
if TYPE_CHECKING:
    from jaxnh import design, identify, models
    from jaxnh.identify import fit, FitResult, Record
    from jaxnh.identify.spec import FitSpec

_LAZY = {
    "models": ("jaxnh.models", None),  # the built-in models: 25 ms of the import
    "design": ("jaxnh.design", None),
    "identify": ("jaxnh.identify", None),
    "fit": ("jaxnh.identify", "fit"),
    "FitResult": ("jaxnh.identify", "FitResult"),
    "Record": ("jaxnh.identify", "Record"),
    "FitSpec": ("jaxnh.identify.spec", "FitSpec"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = importlib.import_module(module)
        value = value if attr is None else getattr(value, attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxnh' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__ + ["__version__"])


__version__ = "0.1.0"

__all__ = [
    "Mechanism",
    "FrictionContact",
    "ContactLaw",
    "Coulomb",
    "Viscous",
    "Multiplier",
    "Stribeck",
    "ContactDiagnostics",
    "stick_margin",
    "StickMargin",
    "enable_compilation_cache",
    "COMPILER_OPTIONS",
    "Appell",
    "Lagrange",
    "Substituted",
    "Formulation",
    "METHODS",
    "simulate",
    "ode",
    "ODE",
    "Solution",
    "DenseMotion",
    "STATUS",
    "SimulationError",
    "InvalidInitialState",
    "RECORDABLE",
    "STABILIZATIONS",
    "default_solver",
    "ForwardSensitivity",
    "FORWARD_MAX_PARAMETERS",
    "choose_adjoint",
    "StepMaps",
    "MappedSolver",
    "accelerations",
    "consistent_velocities",
    "choose_independent",
    "linearize",
    "Linearization",
    "fit",
    "FitResult",
    "FitSpec",
    "Record",
    "sweep",
    "design",
    "equations",
    "identify",
    "solvers",
    "models",
    "profiles",
    "rigid",
    "linalg",
]
