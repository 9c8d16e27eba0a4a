"""Checks of an initial state, inside the compiled program.

Each check gives a `STATUS` instead of raising, so that the same outcome is
reported eagerly and under `jit`, `vmap` (per batch member) and `grad`:

* the mass matrix ∂²T/∂qd² is finite and positive definite (judged on its
  Jacobi-scaled form D^-½ M D^-½, because Cholesky's accuracy does not
  depend on the scaling of the coordinates: J1/J2 = 1e6 is fine, a
  near-singular coupling is not);
* every constraint involves the velocities (a zero row of ∂c/∂qd is a
  holonomic constraint written as a nonholonomic one);
* constraints declared linear in the velocities are (∂²c/∂qd² = 0);
* the constraint rows are either independent or dependent to rounding, not
  nearly dependent (`nearly_dependent`: no singular value of the
  row-normalised ∂c/∂qd between `DEPENDENT_BELOW` eps and `independent_above`
  of the largest (1e-5 in float64); in between, which constraints bind is decided by rounding
  and a change of a coefficient in its 10th digit can lock or free a motion);
* qd0 satisfies each constraint k to √eps relative to its velocity scale
  `‖A_k‖·‖qd0 over the coordinates it involves‖ + |c_k(q0, 0, t0)|`
  (`constraint_scale`; an absolute test would pass a 50 % violation of tiny
  velocities, and the norm of all of qd0 would let a large velocity
  elsewhere hide a violation), and the smallest correction that meets all
  constraints is no longer than `DISTANCE_FACTOR` times those allowances
  (`consistent`: with ill-conditioned rows a small residual can hide a
  velocity far from the constraint manifold);
* the formulation's own checks (Appell's: a regular dependent-velocity block), joined to
  these in `jaxnh._solve.diagnose.initial_checks`.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from jaxnh._base.linalg import pick, pivot_rtol, value_and_jacfwd
from jaxnh._base.status import STATUS


__all__ = [
    "mass_matrix_check",
    "constraint_scale",
    "consistency_tolerance",
    "scaled_norm",
    "nearly_dependent",
    "consistent",
    "singular_rows",
    "RowChecks",
    "constraint_row_checks",
]


def mass_matrix_check(mech, q, qd, t, params) -> tuple[jax.Array, jax.Array]:
    """(whether ∂²T/∂qd² at the state is finite and positive definite (Jacobi-scaled test), the
    matrix's diagonal: the inertias, in kg·m² or kg)."""
    eps = jnp.finfo(q.dtype).eps
    tiny = jnp.finfo(q.dtype).tiny
    M = jax.hessian(lambda v: mech.kinetic(q, v, t, params))(qd)
    d = jnp.diag(M)
    # D^-½ M D^-½ one factor at a time: the product of two inertias near 1e±300 over/underflows
    r = jnp.sqrt(jnp.abs(d))
    r = jnp.where(r > 0, r, jnp.sqrt(tiny))
    Ms = (0.5 * (M + M.T) / r[:, None]) / r[None, :]
    Ms = jnp.where(jnp.isfinite(Ms), Ms, 0.0)
    # The smallest eigenvalue of the unit-diagonal matrix, > 1e3 eps. A symmetric eigensolver is
    # backward stable (each computed eigenvalue is within ~n eps ‖Ms‖ ≤ n² eps of one of the matrix
    # as computed), so a matrix singular up to the rounding of its own entries (λ_min of order
    # eps, of either sign) cannot pass. Cholesky pivots only bound the
    # smallest eigenvalue from above: after a small pivot, the next carries its rounding noise
    # amplified (a mass matrix singular to rounding, written in speeds, had pivots 1, 1e-4 and
    # 8.5e-13 > 1e3 eps, and stalled at max_steps instead of being refused here).
    lam = jnp.linalg.eigvalsh(jax.lax.stop_gradient(Ms))
    ok = jnp.all(jnp.isfinite(M)) & jnp.all(d > 0) & jnp.all(jnp.isfinite(lam)) & (jnp.min(lam) > 1e3 * eps)
    return ok, d


def constraints_affine(mech, q, qd, t, params, A=None, a=None):
    """Whether constraints declared linear in the velocities are (True when declared nonlinear).

    An affine c has a zero second difference c(qd + e) − 2 c(qd) + c(qd − e) in any
    direction e (no derivatives needed); e is a fixed direction, not along qd, on
    the scale of qd. `A = ∂c/∂qd` and `a = c(q, 0, t)` are computed when not given.

    The threshold is √eps of the constraint's scale `|A| (|qd| + |e|) + |a|`: rounding in
    the three evaluations of an affine c leaves a few eps of that scale, and a c that is
    nonlinear on the scale of e leaves a second difference of the order of the scale
    itself, so √eps is far from both (1.5e-8 in float64, 3.5e-4 in float32).
    """
    if mech.nonlinear_constraints or mech.constraints is None:
        return jnp.asarray(True)

    def c(v):
        return mech.constraint(q, v, t, params)

    A = jax.jacfwd(c)(qd) if A is None else A
    a = c(jnp.zeros_like(qd)) if a is None else a
    e = _probe(qd)
    return _affine(c(qd + e) - 2 * c(qd) + c(qd - e), A, a, qd, e)


def _probe(qd):
    """The direction of `constraints_affine`'s second difference: fixed, not along qd, on qd's scale."""
    k = jnp.arange(qd.shape[0], dtype=qd.dtype)
    return (1.0 + jnp.max(jnp.abs(qd))) * jnp.cos(1.0 + 2.3 * k)


def _affine(second, A, a, qd, e):
    tiny = jnp.finfo(qd.dtype).tiny
    tol = jnp.sqrt(jnp.finfo(qd.dtype).eps)
    return jnp.all(jnp.abs(second) <= tol * (jnp.abs(A) @ (jnp.abs(qd) + jnp.abs(e)) + jnp.abs(a) + tiny))


def scaled_norm(x, axis=None):
    """Euclidean norm that neither underflows nor overflows: max|x| · ‖x / max|x|‖
    (the squares of velocities below ≈ 1e-154 underflow to 0 in a plain norm)."""
    m = jnp.max(jnp.abs(x), axis=axis, keepdims=True)
    safe = jnp.where(m > 0, m, 1.0)
    return jnp.squeeze(m, axis=axis) * jnp.linalg.norm(x / safe, axis=axis)


def constraint_scale(A, qd, a):
    """The velocity scale of each constraint `c_k = A_k qd + a_k` (m,), against which
    its residual is judged: `‖A_k‖ · ‖qd over the coordinates row k involves‖ + |a_k|`.

    A Cauchy–Schwarz bound of the row's own terms: velocities of coordinates the
    constraint does not involve do not enter (a large one would otherwise hide a
    violation), and it does not vanish where the terms cancel (|A_k ⊙ qd| entrywise
    can all be 0 while the constraint is met only to rounding). Norms scaled, so
    tiny or huge velocities neither underflow nor overflow.
    """
    involved = A != 0
    qd_k = jnp.where(involved, qd[None, :], 0.0)
    return scaled_norm(A, axis=1) * scaled_norm(qd_k, axis=1) + jnp.abs(a)


ROUNDING_FLOOR = 1e3
"""The consistency test also allows ROUNDING_FLOOR · eps · ‖A_k‖ · ‖qd0‖: the rounding of a
constraint evaluated in floating point scales with every quantity it is computed from, and a
rolling disc's c(q0, 0, t0) came out 1e-17 where its involved velocities are exactly zero."""


def consistency_tolerance(A, qd, a):
    """How far each constraint may miss zero at (q0, qd0) (m,): √eps of its own velocity
    scale (`constraint_scale`) plus a rounding floor (`ROUNDING_FLOOR` · eps on the scale of
    all velocities: far below any real violation, 3.5e-6 at a free speed of 1e7)."""
    eps = jnp.finfo(qd.dtype).eps
    floor = ROUNDING_FLOOR * eps * scaled_norm(A, axis=1) * scaled_norm(qd)
    return jnp.sqrt(eps) * constraint_scale(A, qd, a) + floor + jnp.finfo(qd.dtype).tiny


def singular_rows(A, qd, a):
    """Whether a constraint's row of ∂c/∂qd vanishes to within √eps of its scale: the velocity
    part `‖A_k‖·‖qd over the coordinates row k involves‖` of `constraint_scale` below √eps times
    the whole (a fold of a constraint nonlinear in the velocities, c_k = 0 at a double root).

    Judged after `consistent`: a row that qd does not meet is reported as inconsistent (a driven
    mechanism started at rest has a velocity part of 0 against its drive). A met linear row never
    qualifies: `A_k qd = −a_k` makes its velocity part at least |a_k| (to the tolerance). A row at
    rest with a_k = 0 does not either (0 is not below 0); a row of exact zeros is
    `velocity_free`, reported first.
    """
    velocity_part = constraint_scale(A, qd, jnp.zeros_like(a))
    return jnp.any(velocity_part < jnp.sqrt(jnp.finfo(qd.dtype).eps) * (velocity_part + jnp.abs(a)))


DEPENDENT_BELOW = 1e2
"""Singular values of the row-normalised constraint matrix below DEPENDENT_BELOW · eps of the
largest are rows that repeat others to rounding (redundant constraints: 'lagrange' drops them)."""
INDEPENDENT_ABOVE = 1e-5
"""Singular values above INDEPENDENT_ABOVE of the largest (float64; see `independent_above`) are
independent constraints, enforced."""


def independent_above(dtype) -> float:
    """The ratio above which rows count as independent in `dtype`: INDEPENDENT_ABOVE, or more
    where 'lagrange' would drop the row (its multiplier pivot, about the square of twice this
    ratio, below `linalg.pivot_rtol`: 7e-6 in float64, 0.017 in float32), with a margin of 5."""
    return max(INDEPENDENT_ABOVE, 5 * 0.5 * float(pivot_rtol(dtype)) ** 0.5)


DISTANCE_FACTOR = 10.0
"""The smallest velocity correction onto the constraints may be this many times the per-row
allowances (√eps of each row's scale over ‖A_k‖); a well-conditioned set needs a factor ≤ 1/σ_min."""


def _normalised_rows(A):
    """(A with unit rows, the row norms); a zero row stays zero."""
    n = scaled_norm(A, axis=1)
    return A / jnp.where(n > 0, n, 1.0)[:, None], n


def _row_svd(A):
    """(row-normalised A, its row norms, U, S, Vt): the one SVD that `nearly_dependent` and
    `consistent` share (no derivative flows through either check)."""
    As, n = _normalised_rows(A)
    U, S, Vt = jnp.linalg.svd(jax.lax.stop_gradient(As), full_matrices=False)
    return As, n, U, S, Vt


def nearly_dependent(A, svd=None):
    """Whether the constraint rows are nearly, but not exactly, dependent: a singular value of
    the row-normalised A in (DEPENDENT_BELOW · eps, `independent_above`) × the largest. Rows that
    are dependent to rounding (a constraint written twice) and independent rows both pass.
    Rows beyond the number of coordinates must depend on the others (they add singular values of
    exactly zero, which pass). `svd`: `_row_svd(A)`, when the caller has it."""
    if A.shape[0] < 2:
        return jnp.asarray(False)
    eps = jnp.finfo(A.dtype).eps
    S = (_row_svd(A) if svd is None else svd)[3]
    r = S / jnp.where(S[0] > 0, S[0], 1.0)
    return jnp.any((r > DEPENDENT_BELOW * eps) & (r < independent_above(A.dtype)))


def consistent(A, c, qd, a, svd=None):
    """Whether qd meets the constraints `c = A qd + a` (m,) at their tolerance: each residual
    within `consistency_tolerance`, and the minimum-norm correction δ (A δ = c over the
    independent rows) within DISTANCE_FACTOR × the per-row allowances in velocity units.
    `svd`: `_row_svd(A)`, when the caller has it."""
    tol = consistency_tolerance(A, qd, a)
    rows = jnp.all(jnp.isfinite(c)) & jnp.all(jnp.abs(c) <= tol)
    if A.shape[0] < 2:
        return rows
    eps = jnp.finfo(A.dtype).eps
    _, n, U, S, Vt = _row_svd(A) if svd is None else svd
    safe = jnp.where(n > 0, n, 1.0)
    keep = S > DEPENDENT_BELOW * eps * S[0]
    Sinv = jnp.where(keep, 1.0 / jnp.where(keep, S, 1.0), 0.0)
    cs = jax.lax.stop_gradient(c) / safe
    delta = Vt.T @ (Sinv * (U.T @ cs))
    allowed = DISTANCE_FACTOR * scaled_norm(jax.lax.stop_gradient(tol) / safe)
    return rows & (scaled_norm(delta) <= allowed)


class RowChecks(NamedTuple):
    """The checks of the constraint rows at an initial state, in the order a failure is reported.

    `leading` (finite, every row involves a velocity, declared-linear rows are linear, rows not
    nearly dependent) come before a solver's own checks, `trailing` (qd0 meets the rows, no row at
    a fold) after them; each is a tuple of (passed, STATUS of its failure). `A` = ∂c/∂qd (m, s)."""

    A: jax.Array
    leading: tuple
    trailing: tuple


def constraint_row_checks(mech, q, qd, t, params, held: Optional[tuple] = None) -> RowChecks:
    """The checks of the constraint rows at (q, qd, t), sharing one evaluation of ∂c/∂qd, one
    batched evaluation of c (at qd = 0 and the two points of `constraints_affine`'s second
    difference) and one SVD. `held`: the rows qd must meet (default all; a friction solve's
    sliding contacts are not held)."""

    def c(v):
        return mech.constraint(q, v, t, params)

    c0, A = value_and_jacfwd(c, qd)
    linear = not (mech.nonlinear_constraints or mech.constraints is None)
    e = _probe(qd)
    points = jnp.stack([jnp.zeros_like(qd), qd + e, qd - e] if linear else [jnp.zeros_like(qd)])
    values = jax.vmap(c)(points)
    a = values[0]
    linear_ok = _affine(values[1] - 2 * c0 + values[2], A, a, qd, e) if linear else jnp.asarray(True)
    finite = jnp.all(jnp.isfinite(A)) & jnp.all(jnp.isfinite(c0)) & jnp.all(jnp.isfinite(a))
    velocity_free = jnp.any(jnp.sum(A * A, axis=1) == 0)
    m = A.shape[0]
    svd = _row_svd(A) if m >= 2 else None
    near = nearly_dependent(A, svd)
    if held is None or held == tuple(range(m)):
        on_manifold = consistent(A, c0, qd, a, svd)
    elif held:
        on_manifold = consistent(jnp.stack([A[i] for i in held]), pick(c0, held), qd, pick(a, held))
    else:
        on_manifold = jnp.asarray(True)
    leading = (
        (finite, STATUS.constraints_not_finite),
        (~velocity_free, STATUS.velocity_free_constraint),
        (linear_ok, STATUS.constraints_nonlinear),
        (~near, STATUS.constraints_nearly_dependent),
    )
    trailing = (
        (on_manifold, STATUS.inconsistent_velocities),
        (~singular_rows(A, qd, a), STATUS.constraint_jacobian_singular),  # (met, but at a fold)
    )
    return RowChecks(A, leading, trailing)
