"""`Solution`: a simulated motion, and its dense output."""

from __future__ import annotations

from typing import Any, Optional

import equinox as eqx
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxnh._base.compat import status_code, status_code_int
from jaxnh._base.dataframe import solution_to_dataframe, solution_to_xarray
from jaxnh._base.status import describe, STATUS


__all__ = ["Solution", "DenseMotion"]


class DenseMotion(eqx.Module):
    """The motion between report times, from the solver's dense output.

    `motion.evaluate(t)` gives `(q (s,), qd (s,))` at any time t (s) in the
    integrated interval; under `jax.vmap` over t for many times.
    """

    interpolation: Any
    form: Any
    params: Any
    expand: Optional["Expansion"] = None

    def evaluate(self, t: Float[Array, ""] | float) -> tuple[Float[Array, " s"], Float[Array, " s"]]:
        """Coordinates and velocities `(q, qd)` at time t, s."""
        y = self.interpolation.evaluate(t)
        q, qd = self.form.unpack(y, t, self.params)
        if self.expand is not None:
            q, qd, _ = self.expand(q, qd, t, self.params)
        if self.form.bound_mech.has_speeds:  # (q, dq/dt), as the reports; `speeds` gives u
            return q, self.form.rate(q, qd, t, self.params)
        return q, qd

    def speeds(self, t: Float[Array, ""] | float) -> Float[Array, " k"]:
        """The speeds u at time t (the velocities qd for a mechanism without `kinematics`)."""
        y = self.interpolation.evaluate(t)
        q, u = self.form.unpack(y, t, self.params)
        if self.expand is not None:
            q, u, _ = self.expand(q, u, t, self.params)
        return u


class Expansion(eqx.Module):
    """All s coordinates from a solve in the independent ones of a mechanism with `dependent`.

    Such a solve integrates `full.reduced_from_start(s)` with `(params, start)` for params,
    `start` being q0's dependent coordinates (Newton's method starts there unless the
    mechanism has a `guess`). Called with (q_I, qd_I, t, (params, start)), it returns
    (q, qd, params): all coordinates and the user's own params.
    """

    full: Any

    def __call__(self, q, qd, t, run):
        params, start = run
        return (*self.full.full_state(q, qd, t, params, self.full.newton_start(start)), params)


class Solution(eqx.Module):
    """A simulated motion, reported at the requested times.

    Attributes:
        ts: report times (n,), s (with an event that stopped the run early,
            the times after the stop are inf).
        q: coordinates (n, s) at `ts`.
        qd: velocities dq/dt (n, s) at `ts` (dependent ones from the constraints for
            "appell"/"substituted").
        u: the speeds (n, k) at `ts` for a mechanism with `kinematics` (the
            integrated quasi-velocities, e.g. body angular velocities, rad/s);
            the same array as `qd` otherwise.
        multipliers: constraint multipliers λ (n, m), when recorded: the
            constraint forces are `Aᵀ λ` with `A = ∂c/∂qd` (for the variator
            λ is the tangential contact force times the roller radius, N·m).
        energy: T + V (n,), J, when recorded.
        residual: constraint values c(q, qd, t) (n, m), when recorded; zero
            for an exact solution.
        stats: dict with `num_steps` (attempted), `num_accepted_steps`,
            `num_rejected_steps`, `rhs_evaluations` (vector-field calls:
            stages per step times attempted steps), `max_steps`, and for
            explicit solvers whose sensitivities are not in the error
            control `stiffness` (mean step × spectral radius of the field's
            Jacobian, dimensionless; above 1.5 the status is `stiff`). It
            concerns derivatives only (the values of such a solve are right),
            so it is measured where the solve is differentiated (`grad`,
            `jacfwd`, `jvp`, also of a jitted function) and is NaN otherwise.
            Counts and diagnostics: they carry no derivatives.
        status: `jaxnh.STATUS` item (diffrax's `RESULTS` extended):
            `STATUS.successful`, or why the solve failed. After a failure the
            values past the failure time are NaN or inf, never a
            plausible-looking answer, and derivatives are NaN.
        dense: with `saveat=diffrax.SaveAt(..., dense=True)`, a `DenseMotion`
            (`sol.evaluate(t)`), else None.
        event_mask: with `event=`, which event stopped the run (diffrax's
            convention), else None.
        names: coordinate names.
        slipping: for a mechanism with friction contacts
            (`Mechanism(contacts=...)`), whether each contact slips at each
            report time, bool (n, number of contacts); else None.
        contacts: for a mechanism with friction contacts, the per-contact
            diagnostics (`jaxnh.ContactDiagnostics`: transition times and
            kinds, slip intervals and time, peak ‖λ‖/(μs N) while rolling,
            smallest stick margin, slip distance, energy dissipated by
            slip); else None.
    """

    ts: Float[Array, " n"]
    q: Float[Array, "n s"]
    qd: Float[Array, "n s"]
    multipliers: Optional[Float[Array, "n m"]]
    energy: Optional[Float[Array, " n"]]
    residual: Optional[Float[Array, "n m"]]
    stats: dict
    status: STATUS
    names: tuple = eqx.field(static=True)
    dense: Optional[DenseMotion] = None
    event_mask: Any = None
    slipping: Optional[Bool[Array, "n c"]] = None
    contacts: Any = None  # a jaxnh.ContactDiagnostics (defined with the friction solve)
    speeds: Optional[Float[Array, "n k"]] = None  # (`u`; None: u is qd)

    @property
    def u(self) -> Float[Array, "n k"]:
        """The speeds at `ts`: the integrated quasi-velocities with `kinematics`, else `qd`."""
        return self.qd if self.speeds is None else self.speeds

    @property
    def success(self) -> Bool[Array, "..."]:
        """Boolean (array under vmap): did the solve reach its end."""
        return self.status == STATUS.successful

    def evaluate(self, t: Float[Array, ""] | float) -> tuple[Float[Array, " s"], Float[Array, " s"]]:
        """`(q, qd)` at any time t (s) from the dense output (needs `saveat=SaveAt(dense=True)`)."""
        if self.dense is None:
            raise ValueError(
                "Solution.evaluate needs dense output: pass saveat=diffrax.SaveAt(ts=ts, dense=True) to simulate"
            )
        return self.dense.evaluate(t)

    @property
    def messages(self) -> list:
        """One message per batch member ("success" or why it failed), for batched solutions."""
        return [describe(int(c)) for c in np.asarray(status_code(self.status)).ravel()]

    @property
    def message(self) -> str:
        """'success', or why the solve failed; for a batch, a count of each outcome."""
        codes = np.asarray(status_code(self.status))
        if codes.ndim == 0:
            if self.contacts is not None:  # a friction solve names the time and the contact of its stop
                return self.contacts.annotate(describe(self.status), self.status)
            return describe(self.status)
        if np.all(codes == status_code_int(STATUS.successful)):
            return f"success ({codes.size} of {codes.size})"
        values, counts = np.unique(codes, return_counts=True)
        parts = [f"{n} × {describe(int(v))}" for v, n in zip(values, counts)]
        n_failed = codes.size - int(np.sum(codes == status_code_int(STATUS.successful)))
        return f"{n_failed} of {codes.size} failed: " + "; ".join(parts)

    def to_dataframe(self) -> Any:
        """The motion as a pandas DataFrame (needs pandas)."""
        return solution_to_dataframe(self)

    def to_xarray(self) -> Any:
        """The motion as an `xarray.Dataset` (needs xarray: the `data` extra).

        Dimensions "t" (the report times `ts`, s) and "coordinate" (labelled by
        `names`, e.g. "phi1", "phi2"); data variables `q` and `qd` ("t",
        "coordinate"), and when recorded `energy` ("t", J), `multipliers` and
        `residual` ("t", "constraint"), each equal to the Solution's array of the
        same name; `success`, whether the solve reached its end. Each variable's
        `attrs` hold a `long_name` and its `units` ("s" for t, "J" for energy; the
        coordinates keep each mechanism's own units, which the attribute
        describes). `ds.attrs["message"]` is `sol.message`. After a failed solve
        the values past the failure are NaN, as in the Solution.

        A batched Solution (from `jax.vmap` or `jaxnh.sweep`: arrays with leading
        batch axes) gets a leading "batch" dimension that counts the batch
        elements in C order (as `to_dataframe` does; `ds.attrs["batch_shape"]`
        holds the batch axes), `success` per element. Its elements must share
        their report times: if `ts` differs between them (an event stopped some
        runs early), there is no common "t" axis and a ValueError says so.

        Raises:
            ImportError: xarray is not installed (the message names the `data` extra).
            ValueError: the Solution is traced (inside jit) or inconsistent, or its
                batch elements were reported at different times.
        """
        return solution_to_xarray(self)
