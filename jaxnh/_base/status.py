"""Why a simulation stopped: `STATUS`, and how a failure reaches the user.

A failure is data: the compiled program returns a `STATUS` item next to the
solution (jaxnh's own checks add no host callback; diffrax's checks of its
`SaveAt` do, so a solve's program is not stored in JAX's persistent
compilation cache unless the user sets `EQX_ON_ERROR=nan` before importing
equinox). `throw=True` turns a failure into
a `SimulationError` raised in Python right after the call; when `simulate` is
itself being traced (inside the user's `jit`, `vmap` or `grad`), the error is
raised from inside the program instead (`equinox.error_if`).
"""

from __future__ import annotations

import inspect
import warnings

import diffrax
import equinox as eqx
import jax
import jax.core
import numpy as np

from jaxnh._base.compat import status_code, status_code_int, status_messages


__all__ = ["STATUS", "SimulationError", "InvalidInitialState", "describe", "error_for", "is_traced"]


# `successful` gets a message of its own below (diffrax's is empty, so an item's repr, which equinox
# writes as `STATUS<message>`, was `STATUS<>`); equinox warns when a subclass gives an inherited item a
# new message, and that warning is silenced for this class definition (and its bare subclass below) only
_quiet = warnings.catch_warnings()
_quiet.__enter__()
warnings.filterwarnings("ignore", message="Enumeration has duplicate incompatible values for successful")


class STATUS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Why a simulation stopped: diffrax's results plus jaxnh's own.

    `sol.status` is one item, e.g. `STATUS.successful`; compare it with `==`, which gives a boolean
    array (`sol.status == STATUS.successful`, or `sol.success`). Under `jax.vmap` or `jaxnh.sweep` the
    item holds the whole batch: `sol.status == STATUS.successful` is then a boolean array of the
    batch's shape, `sol.message` counts each outcome and `sol.messages` gives one message per member
    (`np.asarray` of the item itself is a 0-dimensional object array, not the codes). `STATUS[item]`
    is an item's message (an array of messages for a batch). An item's repr shows its message,
    `jaxnh.STATUS<successful>` for a successful solve: equinox prints every item of an enumeration
    as `<message>` and gives a subclass no way to print its name instead.
    """

    __module__ = "jaxnh"  # the public name: an item's repr is `jaxnh.STATUS<message>`
    successful = "successful"
    non_finite_input = (
        "The initial state (q0, qd0), the report times or the parameters contain NaN or inf; "
        "nothing was integrated. Check the argument that holds them."
    )
    bad_report_times = (
        "ts must be strictly increasing (ts[0] is the start, ts[-1] the end of the run); nothing was integrated."
    )
    mass_matrix_not_positive_definite = (
        "The mass matrix ∂²T/∂qd² at the initial state is not positive definite (or is singular "
        "to working precision, judged on its Jacobi-scaled form): check the inertia parameters "
        "and the kinetic energy `kinetic`, or use float64."
    )
    inconsistent_velocities = (
        "qd0 violates the nonholonomic constraints by more than √eps relative to the velocity "
        "scale ‖A_k‖·‖the velocities constraint k involves‖ + |c_k(q0, 0, t0)| of each constraint k, "
        "or the smallest velocity change that meets them all is more than 10 times those allowances "
        "(ill-conditioned constraint rows). "
        "Use jaxnh.consistent_velocities(mech, q0, qd0, t0, params) to project qd0 onto the constraints."
    )
    velocity_free_constraint = (
        "A constraint does not depend on the velocities at the initial state (a row of "
        "∂c/∂qd is zero): a constraint on the coordinates alone is holonomic; pass it as "
        "Mechanism(holonomic=g) with g(q, t, params), not as `constraints`."
    )
    constraints_not_finite = (
        "The constraints c(q0, qd0, t0) or their velocity Jacobian ∂c/∂qd at the initial state "
        "contain NaN or inf although the inputs are finite: a constraint is not defined or not "
        "differentiable there (e.g. sqrt, abs or a division of a velocity at 0). Rewrite it in a form "
        "that is smooth at the initial state, or start from another state."
    )
    constraints_nonlinear = (
        "The constraints are nonlinear in the velocities (∂²c/∂qd² ≠ 0 at the initial state): "
        "pass nonlinear_constraints=True to Mechanism."
    )
    constraints_nearly_dependent = (
        "The constraint rows are nearly dependent at the initial state: a singular value of "
        "∂c/∂qd with unit rows lies between 1e2 eps and 1e-5 of the largest (0.09 in float32). Such rows are "
        "neither a constraint repeated (dependent to rounding, which method='lagrange' accepts) "
        "nor independent enough to be enforced reliably: whether the near-repeat binds, and so "
        "whether a motion is locked or free, is decided by rounding. If a constraint repeats "
        "another, write it identically or leave it out; if it is meant to be independent, "
        "rescale or reformulate the constraints so that their rows are well apart."
    )
    singular_split = (
        "The dependent-velocity block of the constraint matrix is singular: the constraints are "
        "redundant (rank of ∂c/∂qd < m), or the fixed choice `independent=` cannot be solved for "
        "the dependent velocities at the initial state or became singular during the run. Pass "
        "independent=None (the default), which chooses and re-chooses the partition during the "
        "run, or use method='lagrange' (which accepts redundant constraints)."
    )
    nonlinear_constraints_unsolved = (
        "The dependent velocities could not be solved from the constraints nonlinear in the "
        "velocities: Newton's method, started from zero, did not bring |c| to √eps of its scale "
        "(method='appell' and 'substituted', `linearize`, `consistent_velocities`). Write the "
        "constraints so that they can be solved for the dependent velocities near zero (linear "
        "in them where possible: qd2 − sqrt(qd0² + qd1²) rather than qd0² + qd1² − qd2²), fix "
        "`independent=` to velocities they can be solved for, or use method='lagrange', which "
        "integrates all velocities and needs no such solve."
    )
    nonlinear_branch = (
        "qd0's dependent velocities lie on another root of the constraints nonlinear in the "
        "velocities than the one method='appell' integrates: its state holds the independent "
        "velocities only, and the dependent ones are solved at every evaluation by Newton's method "
        "started from zero, which reaches a different root here (e.g. the negative root of a "
        "quadratic constraint). Use method='lagrange', which integrates all velocities and stays on "
        "qd0's root, or write the constraints so that qd0's root is the one nearest zero."
    )
    nonlinear_root_left = (
        "During the run, the dependent velocities that method='appell' solves for left the root of the "
        "constraints nonlinear in the velocities that the motion follows: its state holds the independent "
        "velocities only, and Newton's method started from zero reached another root (or none) at the "
        "end of a step, not the continuation of the root at its start. Use method='lagrange', which "
        "integrates all velocities and follows the motion's root, or write the constraints so that the "
        "motion's root is the one nearest zero throughout."
    )
    holonomic_violated = (
        "The initial coordinates q0 do not satisfy the holonomic constraints g(q0, t0) = 0 (to √eps of "
        "their scale). The holonomic constraints are imposed on the velocities, so a q0 off g = 0 "
        "stays off it. Pass a q0 on the constraints: solve g(q0) = 0 for the dependent coordinates "
        "(`mech.holonomic_residual(q0, t0, params)` tells how far off it is)."
    )
    holonomic_branch = (
        "Newton's method on g(q0, t0) = 0 does not return q0's own dependent coordinates: either "
        "the mechanism's `guess` leads to another solution (another branch of the constraints, "
        "e.g. the pendulum bob above its pivot instead of below), or ∂g/∂q_D is singular at q0, so "
        "the dependent coordinates cannot be solved for there. Give a `guess=` on q0's branch (or "
        "none: Newton's method then starts at q0's dependent coordinates), or choose as "
        "`dependent` coordinates whose block of ∂g/∂q is invertible along the motion."
    )
    acceleration_energy_mismatch = (
        "The acceleration energy S (`acceleration_energy`) disagrees with the kinetic energy T at "
        "the initial state. Appell's equations need ∂S/∂qdd = d/dt(∂T/∂qd) − ∂T/∂q, that is "
        "∂²S/∂qdd² = M (the mass matrix ∂²T/∂qd²) and ∂S/∂qdd at qdd = 0 equal to the velocity "
        "terms of Lagrange's equations, to √eps of their scale; they do not (a mass counted twice, "
        "a centripetal or Coriolis term left out, a sign). method='appell' would integrate S and "
        "method='lagrange' T: two different motions. Correct `acceleration_energy`, or leave it "
        "out (jaxnh then builds S from T)."
    )
    mass_matrix_became_singular = (
        "The solve stalled at a singular mass matrix: ∂²T/∂qd² at the last state reached is no "
        "longer positive definite, or an inertia on its diagonal has fallen to ~0 (below √eps of "
        "its initial value); the equations of motion break down there. Check the kinetic energy "
        "and the parameters along the motion; Appell's equations only need the reduced inertia "
        "Bᵀ M B to stay positive definite."
    )
    non_finite_output = (
        "The solve finished but a reported value (coordinates, velocities, multipliers, energy "
        "or constraint residual) is NaN or inf: an overflow, or the equations became singular "
        "(a mass matrix that lost positive definiteness during the run)."
    )
    stiff = (
        "The problem is stiff for an explicit solver: its steps were limited by stability, not "
        "accuracy (step × spectral radius of the Jacobian beyond the explicit stability bound). "
        "The values may look fine but derivatives through such a solve are unreliable. Use an "
        "implicit solver, e.g. solver=diffrax.Kvaerno5(root_finder=optimistix.Newton(rtol=rtol, "
        "atol=atol))."
    )
    # --- friction-held contacts (jaxnh._solve.friction) ---
    friction_values_invalid = (
        "A friction contact's values at the initial state are not physical: a normal force N < 0, "
        "μk < 0 or μs < μk (or one of them is not finite), or its law's slip force is NaN, inf or "
        "negative. Check the contact's normal_force, mu_static, mu_kinetic and law and the parameters "
        "they read."
    )
    friction_transitions_exceeded = (
        "The friction contacts changed between sticking and slipping more often than "
        "max_transitions allows (Zeno behaviour, or chattering at a contact held at the edge of its "
        "friction cone); the solve stopped there. sol.contacts.stopped_at and "
        "sol.contacts.stopped_contact give the time and the contact. Raise max_transitions, or "
        "check the contact: a normal force near 0, or μs = μk with a force that hovers at μs N."
    )
    contact_normal_force_lost = (
        "A friction contact's normal force N fell to zero during the run. Coulomb's law then "
        "holds nothing, and a negative N would make the friction force push the body: the model "
        "given has no lift-off (the normal direction is not one of the mechanism's coordinates; for a "
        "normal force taken from a constraint with Multiplier, the body would leave the surface "
        "there), so the solve stopped there. sol.contacts.stopped_at and sol.contacts.stopped_contact "
        "give the time and the contact. Check the contact's normal_force, or model the normal "
        "direction in the mechanism."
    )
    contact_value_invalid = (
        "A friction contact's value became unphysical during the run: its normal force, μs or μk "
        "is NaN or inf, μk < 0, or μs < μk, or its law's slip force is NaN, inf or negative. The "
        "solve stopped at the time it happened; sol.contacts.stopped_at, stopped_contact and "
        "stop_cause give the time, the contact and the value. Check the contact's normal_force, "
        "mu_static, mu_kinetic and law, and the parameters they read."
    )
    constraint_jacobian_singular = (
        "A constraint's velocity Jacobian ∂c_k/∂qd vanishes at the initial state to within √eps of "
        "the constraint's scale (‖∂c_k/∂qd‖·‖the velocities it involves‖ against |c_k(q0, 0, t0)|): "
        "a constraint nonlinear in the velocities starts at a fold, a double root of c_k = 0 in "
        "qd, where no unique motion starts. Start from a state where ∂c/∂qd has full rank."
    )
    # --- failures during the run diagnosed at the last state reached (jaxnh._solve.diagnose) ---
    forces_became_non_finite = (
        "The applied forces Q(q, qd, t, params) (`forces`) returned NaN or inf during the run, at the last "
        "state reached or just beyond it: diffrax rejected every step that met the non-finite value and shrank "
        "its step until max_steps. sol.stats['stopped_at'] is the time the solve stopped (eagerly the error "
        "gives it). Make `forces` finite along the motion (a division by a velocity or coordinate that reaches "
        "0, a log or sqrt of a negative number, a table read outside its range)."
    )
    potential_became_non_finite = (
        "The potential energy V(q, t, params) (`potential`) or its gradient ∂V/∂q became NaN or inf during "
        "the run, at the last state reached or just beyond it: diffrax rejected every step that met the "
        "non-finite value and shrank its step until max_steps. sol.stats['stopped_at'] is the time the solve "
        "stopped (eagerly the error gives it). Make `potential` finite and differentiable along the motion."
    )
    kinetic_energy_became_non_finite = (
        "The kinetic energy T(q, qd, t, params) (`kinetic`) or the derivatives the equations take of it (the "
        "mass matrix ∂²T/∂qd² and the velocity terms) became NaN or inf during the run, at the last state "
        "reached or just beyond it: diffrax rejected every step that met the non-finite value and shrank its "
        "step until max_steps. sol.stats['stopped_at'] is the time the solve stopped (eagerly the error gives "
        "it). Make `kinetic` finite and twice differentiable along the motion."
    )
    constraints_became_non_finite = (
        "The constraints c(q, qd, t, params) (`constraints`, with the rates ġ of `holonomic`) or their "
        "Jacobians became NaN or inf during the run, at the last state reached or just beyond it: diffrax "
        "rejected every step that met the non-finite value and shrank its step until max_steps. "
        "sol.stats['stopped_at'] is the time the solve stopped (eagerly the error gives it). Make the "
        "constraints finite and differentiable along the motion."
    )
    constraints_lost_rank = (
        "The constraint rows became dependent during the run (∂c/∂qd lost rank: its smallest singular value, "
        "rows scaled to unit length and columns by the inertias, fell below 1e-6 of the largest at the last "
        "state reached), so no set of dependent velocities can be solved from the constraints there and "
        "method='appell' (or 'substituted'), which integrates the independent velocities only, cannot continue: "
        "its steps shrank until the solve stalled. sol.stats['stopped_at'] is the time (eagerly the error gives "
        "it). Use method='lagrange', whose multipliers accept a constraint set that loses rank at an instant, "
        "or write the constraints so that they stay independent along the motion."
    )
    root_finder_failed = (
        "The implicit solver's root finder did not converge: from the last state reached, a trial step (of "
        "1 to 256 times the mean accepted step) failed in the solver's root finder, while a Newton root "
        "finder at the solve's tolerances converged on the same step with an error estimate the step-size "
        "control accepts. diffrax rejects a step whose root find failed and shrinks it (its result code does "
        "not show why), so the solve ran out of max_steps. Stiffness was not measured and is not the cause "
        "reported: an implicit solver is not held back by stability. Use a Newton root finder with the solve's "
        "tolerances, solver=diffrax.Kvaerno5(root_finder=optimistix.Newton(rtol=rtol, atol=atol)) (diffrax's "
        "default, VeryChord, reuses one Jacobian per step and diverges on steps where it changes fast)."
    )
    max_steps_step_bound = (
        "The maximum number of solver steps was reached because of the step-size bound: the largest step "
        "dtmax (the run's length over dtmax) and the times at which a step must end (step_ts, profiles' "
        "breakpoints, and for Kvaerno solvers the report times) force at least half of the steps taken. "
        "Raise max_steps, or raise dtmax or give fewer step_ts. sol.stats['stopped_at'] is the time the "
        "solve stopped."
    )
    speeds_incomplete = (
        "The mechanism's `kinematics` forbid velocities its coordinates have: the speeds' fields K_j "
        "(the columns of ∂q̇/∂u) do not close on themselves (a commutator of two of them leaves their "
        "span), which is a nonholonomic constraint written into q̇ = K u, e.g. a rolling or knife-edge "
        "condition. T in the speeds then does not determine the motion (the equations need T's "
        "derivatives along the forbidden velocities). Choose speeds that give every velocity of the "
        "coordinates (as many independent speeds as the coordinates have degrees of freedom; for a unit "
        "quaternion, three angular-velocity components) and write the constraint as `constraints=` in "
        "them (see jaxnh.models.disc_speeds)."
    )
    quaternion_not_unit = (
        "A group of q0 named in the mechanism's `quaternions` is not a unit quaternion: its norm differs "
        "from 1 by more than √eps. A rotation is a unit quaternion (w, x, y, z); divide the group by its "
        "norm (e.g. q0.at[3:7].set(e / jnp.linalg.norm(e))), or build it with "
        "jaxnh.rigid.quaternion_from_axis_angle."
    )


# `help(jaxnh.STATUS)` lists every item (diffrax's and jaxnh's) with its message: equinox writes that
# list as the docstring of an enumeration that has none, so it is taken from a bare subclass (which has
# the same items; its `successful` too differs from diffrax's) and put after STATUS's own text
STATUS.__doc__ = f"{inspect.cleandoc(STATUS.__doc__ or '')}\n\n{type(STATUS)('STATUS', (STATUS,), {}).__doc__}"  # pyright: ignore[reportCallIssue] (equinox types Enumeration as enum.Enum)
_quiet.__exit__(None, None, None)
del _quiet


MAX_STEPS_ADVICE = (
    " If the step count is large because the problem is stiff (strong damping, a large "
    "Baumgarte rate), use an implicit solver with a Newton root finder, e.g. "
    "solver=diffrax.Kvaerno5(root_finder=optimistix.Newton(rtol=rtol, atol=atol)); "
    "otherwise raise max_steps."
)


class SimulationError(RuntimeError):
    """A failed simulation with `throw=True`; `.status` holds the `STATUS` item."""

    def __init__(self, message: str, status: STATUS | None = None):
        super().__init__(message)
        self.status = status


class InvalidInitialState(SimulationError, ValueError):
    """A simulation refused because its input failed a check (non-finite values, a mass
    matrix that is not positive definite, inconsistent velocities, ...)."""


INPUT_FAILURES = (
    "holonomic_violated",
    "holonomic_branch",
    "nonlinear_constraints_unsolved",
    "nonlinear_branch",
    "non_finite_input",
    "bad_report_times",
    "mass_matrix_not_positive_definite",
    "inconsistent_velocities",
    "velocity_free_constraint",
    "constraint_jacobian_singular",
    "constraints_not_finite",
    "constraints_nonlinear",
    "constraints_nearly_dependent",
    "friction_values_invalid",
    "acceleration_energy_mismatch",
    "quaternion_not_unit",
    "speeds_incomplete",
)


def error_for(status) -> SimulationError:
    """The exception for a concrete failed status."""
    code = status_code_int(status)
    names = [n for n in INPUT_FAILURES if status_code_int(getattr(STATUS, n)) == code]
    return (InvalidInitialState if names else SimulationError)(describe(status), status)


def describe(status) -> str:
    """'success', or the failure in words, for a concrete (unbatched) status or its integer code."""
    code = status if isinstance(status, (int, np.integer)) else status_code_int(status)
    if code == status_code_int(STATUS.successful):
        return "success"
    msg = f"solve failed: {status_messages(STATUS)[code]}"
    if code in (status_code_int(STATUS.max_steps_reached), status_code_int(STATUS.max_steps_rejected)):
        msg += MAX_STEPS_ADVICE
    if code == status_code_int(STATUS.singular):
        msg += (
            " (a linear solve broke down: with jaxnh's formulations this means the mass matrix or the "
            "dependent-velocity block became singular during the run)"
        )
    return msg


def is_traced(*trees) -> bool:
    """Whether any array leaf is a tracer (simulate is inside jit/vmap/grad)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


def raise_in_graph(x, status):
    """`x`, with an error raised from inside the program when `status` is a failure."""
    failed = status != STATUS.successful
    return eqx.branched_error_if(x, failed, status_code(status), status_messages(STATUS))
