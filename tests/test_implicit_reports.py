"""Implicit solvers at report times (issue 46): `diffrax.Kvaerno5` on the variator at rtol 1e-9,
its reports against the closed form, within a bound derived from the tolerances.

The hunt reported φ2(5 s) 4.6e-5 relative off with a success status. On this tree (and with the
same solve at every commit since the report-step fix 97719c6) the error is ≤ 2e-9 relative with
both root finders and both forms, so this file guards that figure; it does not reproduce a fault.

Why the reports can be held to a bound at all: Kvaerno5's dense output is a third-order Hermite
interpolant whose error no tolerance controls, so `simulate` ends a step at every report time
(`coarse_interpolant` in jaxnh/_solve/stepping.py): each report is a step end, where the error
control applies.

The bound, for φ2 at every report (rad):

* one accepted step: diffrax's PID control accepts a step when the RMS over the n = 4 state
  components (Lagrange's [q, qd]) of error / (atol + rtol |y_i|) is ≤ 1, so one component may
  carry √n (atol + rtol Y), Y the largest |y_i| along the run;
* carried to the end by the flow: a velocity error δw at s becomes √(I(s)/I(t)) δw at t (the
  closed form: √I w changes by a function of time only, I = J1 + J2 U21²), and an angle error
  gains at most (t − s) U21 max of that, so the gain on φ2 is G = 1 + T U_max √(I_max/I_min);
* accumulated over the N accepted steps with no cancellation assumed:
  |δφ2| ≤ N √n (atol + rtol Y) G.

It is a bound, not an estimate (the measured errors are 1e-4 of it); 4.6e-5 relative is beyond it.
"""

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
import pytest  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import variator as V  # noqa: E402


RTOL, ATOL = 1e-9, 1e-11
T, W0 = 5.0, 2.0
TS = jnp.linspace(0.0, T, 11)
N_ERR = 4  # components the error norm counts (Lagrange: 2 angles, 2 velocities)


def _gain(p) -> float:
    t = jnp.linspace(0.0, T, 2001)
    U = np.asarray(jax.vmap(p.U21)(t))
    inertia = float(p.J1) + float(p.J2) * U**2
    return 1.0 + T * U.max() * float(np.sqrt(inertia.max() / inertia.min()))


@pytest.mark.parametrize(
    "label,solver,method",
    [
        ("chord", diffrax.Kvaerno5(), "lagrange"),  # diffrax's default root finder (VeryChord)
        ("newton", diffrax.Kvaerno5(root_finder=optx.Newton(rtol=RTOL, atol=ATOL)), "lagrange"),
        ("newton", diffrax.Kvaerno5(root_finder=optx.Newton(rtol=RTOL, atol=ATOL)), "appell"),
    ],
)
def test_kvaerno5_reports_within_the_tolerance_bound(label, solver, method):
    p = V.default_params()
    q0 = jnp.zeros(2)
    qd0 = jnp.array([W0, W0 * float(p.U21(0.0))])
    sol = nh.simulate(V.mechanism(), p, q0, qd0, TS, method=method, solver=solver, rtol=RTOL, atol=ATOL)
    q_ref, qd_ref = (np.asarray(x) for x in V.closed_form(p, TS, w0=W0))
    Y = max(np.abs(q_ref).max(), np.abs(qd_ref).max())
    n = int(sol.stats["num_accepted_steps"])
    bound = n * np.sqrt(N_ERR) * (ATOL + RTOL * Y) * _gain(p)
    err = np.abs(np.asarray(sol.q)[:, 1] - q_ref[:, 1])
    print(f"{label} {method}: {n} steps, φ2 error {err.max():.2e} rad (bound {bound:.2e}), at 5 s {err[-1]:.2e}")
    assert err.max() <= bound
    # the hunt's figure, 4.6e-5 relative at 5 s, is above the bound in every case here
    assert 4.6e-5 * abs(q_ref[-1, 1]) > bound
