"""A user's own mechanism for `jaxnh fit --model tests/cli_model.py:coupled_shafts` (tests only).

Two shafts coupled by a fixed-ratio rolling contact, `K qd1 − qd2 = 0` (a
nonholonomic-form constraint, rad/s), T = ½ (J1 qd1² + J2 qd2²) (J), a
measured motor torque F(t) on shaft 1 (N·m, a `Sampled` input) and viscous
friction c·qd2 on shaft 2 (N·m·s). Along the constraint the motion obeys
(J1 + K² J2) qd1' = F − K² c qd1, so with J2 and K known J1 and c are
determined by the record. Not the variator: another mechanism, other names.
"""

import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.identify.spec import FitSpec
from jaxnh.profiles import Sampled


K = 1.5  # transmission ratio, 1
J2 = 0.03  # kg·m², known
TRUE = {"J1": 0.02, "c": 0.004}  # kg·m², N·m·s
START = {"J1": 0.026, "c": 0.003}


def kinetic(q, qd, t, p):
    return 0.5 * (p["J1"] * qd[0] ** 2 + p["J2"] * qd[1] ** 2)


def rolling(q, qd, t, p):
    return jnp.stack([K * qd[0] - qd[1]])


def torques(q, qd, t, p):
    return jnp.stack([p["F"](t), -p["c"] * qd[1]])


MECH = nh.Mechanism(kinetic, constraints=rolling, forces=torques, names=("a", "b"))


def params(record, J1=START["J1"], c=START["c"]):
    """Starting params with the record's torque column F as a Sampled input."""
    return {"J1": J1, "J2": J2, "c": c, "F": Sampled(record.t, record.inputs["F"])}


def coupled_shafts():
    """The FitSpec: J1 and c free and positive, both angles observed, input column F."""
    return FitSpec(
        mechanism=MECH,
        params=params,
        free=("J1", "c"),
        positive=("J1", "c"),
        observed=("a", "b"),
        inputs=("F",),
        options={"rtol": 1e-8},
    )


def coupled_shafts_dict():
    """The same contract as a plain dict."""
    return {
        "mechanism": MECH,
        "params": params,
        "free": ["J1", "c"],
        "positive": ["J1", "c"],
        "observed": ["a", "b"],
        "inputs": ["F"],
    }


def not_a_spec():
    return 42


def raises():
    raise RuntimeError("the user's model is broken")


def record_text(n=40, duration=2.0, noise=2e-4, seed=0, scale=1.0):
    """A CSV record made by the model itself at the true parameters (closed form, see the docstring)."""
    t = np.linspace(0.0, duration, n)
    F = 0.05 * np.ones(n)  # constant torque: the closed form below is exact
    Jeff, ceff = TRUE["J1"] + K**2 * J2, K**2 * TRUE["c"]
    w0 = 2.0
    w_inf = F[0] / ceff
    tau = Jeff / ceff
    a = w_inf * t + (w0 - w_inf) * tau * (1 - np.exp(-t / tau))
    rng = np.random.default_rng(seed)
    y = np.stack([a, K * a], axis=1) + noise * rng.standard_normal((n, 2))
    y *= scale
    lines = ["t,a,b,F"] + [",".join(repr(float(x)) for x in (ti, ya, yb, f)) for ti, (ya, yb), f in zip(t, y, F)]
    return "\n".join(lines) + "\n"
