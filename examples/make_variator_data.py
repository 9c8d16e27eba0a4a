"""Make the embedded variator record `jaxnh/data/variator_record.csv`.

Run:  python examples/make_variator_data.py
A laboratory variator with known true values (TRUTH below, also written to
`jaxnh/data/variator_truth.json`) is simulated accurately; two incremental
encoders read the shafts at 250 Hz (quantised counts, plus a little
electrical/timing noise); the motor and load torques are the drive's
commands, recorded exactly. `truth()`, `clean_motion()` and `measure()` are
also used by `benchmarks/calibration.py` to draw further noise realisations.
"""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np

import jaxnh as nh
from jaxnh.identify.data import Record, write_csv
from jaxnh.models import variator as V
from jaxnh.profiles import CubicSpline, Fourier


HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, "..", "jaxnh", "data")

TRUTH = {
    "J1": 0.018,  # kg·m², shaft 1 with motor rotor
    "J2": 0.045,  # kg·m², shaft 2 with load
    # U21(t): natural cubic spline through these values at these knots (s)
    "U21_knots": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
    "U21_values": [0.80, 0.84, 0.98, 1.15, 1.30, 1.38, 1.40],
    "phi0": [0.0, 0.0],  # rad
    "w0": 4.0,  # phi1'(0), rad/s; phi2'(0) = U21(0) * w0
    "duration": 6.0,  # s
    "rate": 250.0,  # samples per second
    # M1(t) = 0.15 + 0.08 sin(2π 0.5 t) + 0.04 sin(2π 1.3 t + 0.4)      N·m (motor)
    # M2(t) = −0.06 − 0.03 (1 − cos(2π 0.35 t))                         N·m (load, braking)
    "counts_per_rev": [8192, 4096],  # encoder 1: 2048 lines ×4, encoder 2: 1024 lines ×4
    "jitter_std": [3e-4, 6e-4],  # rad, Gaussian noise (electrical, timing) added before quantisation
    # the encoders' count grids start at a random fraction of a count from the shaft angle
    "seed": 1,  # see jaxnh/data/README.md on the choice
}


def torques():
    """Motor and load torque laws as profiles (N·m)."""
    ph = 0.4
    M1 = Fourier(
        0.15,
        cos=[0.0] * 12 + [0.04 * np.sin(ph)],
        sin=[0, 0, 0, 0, 0.08] + [0.0] * 7 + [0.04 * np.cos(ph)],
        period=10.0,
    )  # harmonics 5 (0.5 Hz) and 13 (1.3 Hz) of a 10 s period
    M2 = Fourier(-0.09, cos=[0.0] * 6 + [0.03], period=20.0)  # harmonic 7 of 20 s = 0.35 Hz
    return M1, M2


def truth() -> V.VariatorParams:
    """The true variator: inertias, ratio spline, torque laws."""
    M1, M2 = torques()
    U = CubicSpline(TRUTH["U21_knots"], TRUTH["U21_values"])
    return V.VariatorParams(TRUTH["J1"], TRUTH["J2"], U, M1, M2)


def sample_times():
    n = int(round(TRUTH["duration"] * TRUTH["rate"])) + 1
    return np.arange(n) / TRUTH["rate"]


def clean_motion():
    """The true angles (n, 2), rad, at the sample times, integrated to rtol = atol = 1e-12."""
    p = truth()
    ts = jnp.asarray(sample_times())
    w0 = TRUTH["w0"]
    qd0 = jnp.array([w0, float(p.U21(0.0)) * w0])
    sol = nh.simulate(V.mechanism(), p, jnp.asarray(TRUTH["phi0"]), qd0, ts, rtol=1e-12, atol=1e-12)
    return np.asarray(sol.q)


def measure(q, key):
    """Encoder readings of the true angles q (n, 2), rad.

    Each encoder's count grid sits at a random angle relative to the shaft
    (where the code disc's edges happen to be when counting starts, uniform
    over one count), a little Gaussian jitter is added, and the reading is
    the whole number of counts passed. Works under `jax.vmap` over keys.
    """
    step = 2 * jnp.pi / jnp.asarray(TRUTH["counts_per_rev"], dtype=jnp.float64)
    k1, k2 = jax.random.split(key)
    phase = step * jax.random.uniform(k1, (q.shape[-1],), dtype=jnp.float64)
    jitter = jnp.asarray(TRUTH["jitter_std"], dtype=jnp.float64)
    noisy = q + phase + jitter * jax.random.normal(k2, q.shape, dtype=jnp.float64)
    return jnp.floor(noisy / step) * step


def noise_std():
    """Standard deviation of the reading error per encoder, rad: sqrt(jitter² + step²/12)."""
    step = 2 * np.pi / np.asarray(TRUTH["counts_per_rev"], float)
    return np.sqrt(np.asarray(TRUTH["jitter_std"]) ** 2 + step**2 / 12)


def main():
    t = sample_times()
    q = clean_motion()
    y = np.asarray(measure(jnp.asarray(q), jax.random.PRNGKey(TRUTH["seed"])))
    M1, M2 = torques()
    m1 = np.asarray(jax.vmap(M1)(jnp.asarray(t)))
    m2 = np.asarray(jax.vmap(M2)(jnp.asarray(t)))
    rec = Record(t, {"phi1": y[:, 0], "phi2": y[:, 1]}, {"M1": m1, "M2": m2}, "synthetic")
    os.makedirs(DATA, exist_ok=True)
    write_csv(
        rec,
        os.path.join(DATA, "variator_record.csv"),
        comments=[
            "jaxnh embedded variator record (synthetic; made by examples/make_variator_data.py).",
            "t [s], phi1 phi2 [rad] encoder angles, M1 M2 [N m] commanded motor and load torques.",
            "True values in variator_truth.json and README.md of this folder.",
        ],
    )
    truth_out = dict(
        TRUTH,
        noise_std=noise_std().tolist(),
        M1="0.15 + 0.08 sin(2 pi 0.5 t) + 0.04 sin(2 pi 1.3 t + 0.4)",
        M2="-0.06 - 0.03 (1 - cos(2 pi 0.35 t))",
    )
    with open(os.path.join(DATA, "variator_truth.json"), "w") as f:
        json.dump(truth_out, f, indent=2)
    print(
        f"wrote {len(t)} samples over {t[-1]:.1f} s; final angles {q[-1]} rad; "
        f"speeds phi1' from {TRUTH['w0']} rad/s; reading noise {noise_std()} rad"
    )


if __name__ == "__main__":
    main()
