"""The seed paper's friction variator, three ways.

Run:  python examples/variator.py
Prints phi1' at t = 5 s from Lagrange's equations with multipliers, from
Appell's equations, from the paper's naive substitution, and from the
closed form; the first two agree with the closed form, the third does not.
"""

import jax.numpy as jnp

import jaxnh as nh
from jaxnh.models import variator


mech = variator.mechanism()  # T, constraint U21(t) phi1' - phi2' = 0, torques
p = variator.default_params()  # J1, J2 [kg m²], U21(t), M1, M2 [N m]
ts = jnp.linspace(0.0, 5.0, 51)  # report times, s
w0 = 2.0  # initial phi1', rad/s
qd0 = jnp.array([w0, p.U21(0.0) * w0])  # phi2' from the constraint

q_exact, qd_exact = variator.closed_form(p, ts, w0=w0)
print(f"closed form   phi1'(5 s) = {float(qd_exact[-1, 0]):.10f} rad/s")
for method in ("lagrange", "appell", "substituted"):
    sol = nh.simulate(mech, p, jnp.zeros(2), qd0, ts, method=method, rtol=1e-10, atol=1e-12)
    print(f"{method:<13} phi1'(5 s) = {float(sol.qd[-1, 0]):.10f} rad/s   ({int(sol.stats['num_steps'])} steps)")

# the contact multiplier (tangential force × roller radius, N·m) along the motion
sol = nh.simulate(mech, p, jnp.zeros(2), qd0, ts, record=("multipliers",))
print(f"multiplier at t = 5 s: {float(sol.multipliers[-1, 0]):.6f} N·m")
