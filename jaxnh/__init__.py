"""jaxnh — equations of motion of mechanisms with nonholonomic constraints, in JAX.

Write the kinetic energy T (and optionally the acceleration energy S) as
plain JAX functions; jaxnh derives Lagrange's equations with multipliers or
Appell's equations by automatic differentiation, integrates them with
diffrax, and everything works under `jit`, `vmap` and `grad`.

Precision: importing jaxnh turns on JAX's 64-bit mode
(`jax_enable_x64`), because accuracy is the product. Set the environment
variable `JAXNH_X64=0` before the import to leave JAX's setting alone; to run
in float32 with 64-bit mode on, pass float32 arrays (q0, qd0, ts and the
params leaves) — the library keeps the dtype it is given.
"""

import os

import jax

if os.environ.get("JAXNH_X64", "1") != "0":
    jax.config.update("jax_enable_x64", True)

from . import linalg, models, profiles, rigid  # noqa: E402
from ._consistent import consistent_velocities  # noqa: E402
from .equations import METHODS, accelerations, choose_independent  # noqa: E402
from ._holonomic import HolonomicMechanism  # noqa: E402
from ._linearize import Linearization, linearize  # noqa: E402
from ._mechanism import Mechanism  # noqa: E402
from ._sensitivity import FORWARD_MAX_PARAMETERS, ForwardSensitivity  # noqa: E402
from ._simulate import RECORDABLE, STABILIZATIONS, STATUS, Solution, default_solver, simulate  # noqa: E402
from . import design, identify, solvers  # noqa: E402
from .identify import fit  # noqa: E402
from ._sweep import sweep  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Mechanism", "ForwardSensitivity", "FORWARD_MAX_PARAMETERS", "HolonomicMechanism", "Linearization", "linearize", "rigid", "Solution", "accelerations", "choose_independent", "consistent_velocities",
    "simulate", "fit", "sweep", "design", "identify", "solvers", "default_solver", "METHODS", "RECORDABLE", "STABILIZATIONS", "STATUS", "models", "profiles", "linalg",
]
