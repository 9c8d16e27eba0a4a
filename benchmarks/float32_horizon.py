"""float32 over a long horizon (issue 46): what sets the error of a 1000 s run.

Run:  python -m benchmarks.float32_horizon        (about a minute on a 2-core machine)

The variator (`jaxnh.models.variator`, default parameters: torques on, so the speed grows to about
3000 rad/s) over 1000 s, in float32 at the user's defaults (Lagrange's form, the default solver and
atol) and rtol 1e-5 and 3e-6, against the same run in float64 at rtol 1e-12. Reported: the largest
relative error of φ1' over 101 report times, for three ratio profiles U21(t) = 1 + a sin(2πt/P):
the default (a = 0.4, P = 2 s), a slow one (P = 2000 s) and a constant one (a = 0); and, for the
default profile at rtol 1e-5, the spread of that error across 1-ulp changes of the initial speed;
and two float64 runs at rtol 1e-5, one plain and one whose ratio alone is computed in float32 from
the time rounded to float32 (`Float32Time`): the experiment that isolates the cause.

What it shows (2026-12-02, this machine): 6.2e-3 at rtol 1e-5 and 4.1e-3 at rtol 3e-6 for the
default profile, 1.5e-5 for the slow one, 3.6e-7 for the constant one; 3.7e-3 to 8.1e-3 across ten
ulp changes. Tightening rtol barely helps the fast profile, so its error is not the tolerance's.
The float64 run at rtol 1e-5 is off by 2.9e-4; the same run with only the ratio computed from a
float32 time by 4.3e-3, as much as float32 throughout. At t = 1000 s a float32 time is resolved to
ulp(1000) = 6.1e-5 s and the profile's phase 2πt/P, 3142 rad, to 3.7e-4 rad, so the ratio the
equations see is off by up to 0.4 × 3.7e-4 = 1.5e-4 late in the run. A fast-varying input over a
long run needs float64.
"""

from __future__ import annotations

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnh as nh  # noqa: E402
from jaxnh.models import variator as V  # noqa: E402
from jaxnh.profiles import Fourier  # noqa: E402


T_END = 1000.0
TS = jnp.linspace(0.0, T_END, 101)
W0 = np.float32(2.0)
PROFILES = {
    "P = 2 s (default)": Fourier(1.0, cos=[0.0], sin=[0.4], period=2.0),
    "P = 2000 s": Fourier(1.0, cos=[0.0], sin=[0.4], period=2000.0),
    "constant": Fourier(1.0, cos=[0.0], sin=[0.0], period=2.0),
}


class Float32Time(eqx.Module):
    """A profile evaluated in float32 at the time rounded to float32, returned in float64."""

    inner: Fourier

    def __call__(self, t):
        return to32(self.inner)(jnp.asarray(t, jnp.float32)).astype(jnp.float64)

    def derivative(self, t):
        return to32(self.inner).derivative(jnp.asarray(t, jnp.float32)).astype(jnp.float64)


def to32(tree):
    """Every floating array leaf cast to float32."""
    return jax.tree.map(
        lambda x: x.astype(jnp.float32) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x, tree
    )


def error(p64, w0: np.float32, rtol: float) -> tuple[float, int]:
    """(largest relative error of φ1' at TS against float64, accepted float32 steps)."""
    qd0 = jnp.array([w0, w0 * np.float32(p64.U21(0.0))], dtype=jnp.float32)
    ref = nh.simulate(
        V.mechanism(), p64, jnp.zeros(2), qd0.astype(jnp.float64), TS, rtol=1e-12, atol=1e-12, max_steps=10**6
    )
    sol = nh.simulate(
        V.mechanism(), to32(p64), jnp.zeros(2, jnp.float32), qd0, TS.astype(jnp.float32), rtol=rtol, max_steps=10**6
    )
    assert sol.message == "success", sol.message
    w, w_ref = np.asarray(sol.qd[:, 0], np.float64), np.asarray(ref.qd[:, 0])
    return float(np.max(np.abs(w - w_ref) / np.abs(w_ref))), int(sol.stats["num_accepted_steps"])


def main() -> None:
    print(f"variator, float32 against float64, {T_END:.0f} s, largest relative error of phi1'")
    for label, U in PROFILES.items():
        p64 = eqx.tree_at(lambda p: p.U21, V.default_params(), U)
        for rtol in (1e-5, 3e-6):
            e, n = error(p64, W0, rtol)
            print(f"  ratio {label:18s} rtol {rtol:.0e}: {e:.2e}  ({n} steps)")
    p64 = V.default_params()
    spread = [error(p64, W0 + np.float32(k) * np.spacing(W0), 1e-5)[0] for k in range(10)]
    print(f"  default ratio, rtol 1e-5, 10 one-ulp changes of phi1'(0): {min(spread):.2e} to {max(spread):.2e}")
    qd0 = jnp.array([2.0, 2.0 * float(p64.U21(0.0))])
    ref = nh.simulate(V.mechanism(), p64, jnp.zeros(2), qd0, TS, rtol=1e-12, atol=1e-12, max_steps=10**6)
    for label, p in (
        ("plain", p64),
        ("ratio from float32 time", eqx.tree_at(lambda p: p.U21, p64, Float32Time(p64.U21))),
    ):
        sol = nh.simulate(V.mechanism(), p, jnp.zeros(2), qd0, TS, rtol=1e-5, max_steps=10**6)
        e = float(
            np.max(np.abs(np.asarray(sol.qd[:, 0]) - np.asarray(ref.qd[:, 0])) / np.abs(np.asarray(ref.qd[:, 0])))
        )
        print(f"  float64, rtol 1e-5, {label:24s}: {e:.2e}")


if __name__ == "__main__":
    main()
