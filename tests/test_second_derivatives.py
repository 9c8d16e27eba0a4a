"""Second derivatives through `simulate`: right, or refused with a message naming the adjoint and
what works instead.

Which compositions of `jax.grad` and `jax.jacfwd` can go through a solve depends on the adjoint:
a loop that JAX differentiates in forward mode (diffrax's `ForwardMode`, and the sensitivity solve
inside `jaxnh.ForwardSensitivity`'s rule) cannot be transposed, and a backward loop (diffrax's
`RecursiveCheckpointAdjoint`) cannot be differentiated again in reverse mode. `DirectAdjoint`
differentiates the discretisation itself and takes every order and mode.

The answer is the variator without torques. With w = phi1' and I(t) = J1 + J2 U(t)², the reduced
equation (the seed paper's eq. 9) reads I w' = -J2 U U' w, so d(I w²)/dt = 0: the kinetic energy
T = ½ (J1 w² + J2 (U w)²) = ½ I w² is conserved and phi1'(t) = w0 sqrt(I(0) / I(t)). Its second
derivative in J2 is taken from that closed form by `jax.hessian` (exact to rounding).
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import variator as V
from jaxnh.profiles import Fourier


MECH = V.mechanism()
J1, J2_0, W0 = 0.02, 0.05, 2.0
U21 = Fourier(1.0, cos=[0.0], sin=[0.4], period=2.0)  # U = 1 + 0.4 sin(πt): 0.6 ... 1.4
TS = jnp.array([0.0, 0.5, 1.0, 1.5])  # U(1.5 s) = 0.6, its smallest value
RTOL, ATOL = 1e-8, 1e-10  # simulate's defaults
GROWTH = 2.0  # an error in phi1' grows at most by sqrt(I_max / I_min) = 1.76 over the run (see below)


def params(j2):
    return V.VariatorParams(J1=J1, J2=j2, U21=U21, M1=0.0, M2=0.0)


def closed(j2):
    """phi1'(1.5 s) = w0 sqrt(I(0) / I(1.5 s)), I = J1 + J2 U²."""
    i0, i1 = J1 + j2 * U21(0.0) ** 2, J1 + j2 * U21(TS[-1]) ** 2
    return W0 * jnp.sqrt(i0 / i1)


def solve(j2, **kw) -> nh.Solution:
    return nh.simulate(MECH, params(j2), jnp.zeros(2), jnp.array([W0, W0 * U21(0.0)]), TS, **kw)


def rate(j2, **kw):
    """phi1' at the last report, by simulate."""
    return solve(j2, **kw).qd[-1, 0]


def bound(steps: int) -> float:
    """Bound on the error of d²phi1'/dJ2² at rtol, atol after `steps` accepted steps.

    Each step's local error is held to rtol |y| + atol; the global error of phi1' is at most the
    sum over the steps (one more for the interpolation to the report), each amplified by at most
    GROWTH = 2 ≥ sqrt(I_max / I_min) = sqrt((0.02 + 0.05·1.4²) / (0.02 + 0.05·0.6²)) = 1.76
    (the homogeneous solutions are ∝ I^(-1/2)). That error, a smooth function of J2 varying on the
    scale of the solution, has a second derivative bounded alike with the scale
    S = |w| / J2² + |dw/dJ2| / J2 + |d²w/dJ2²| of the exact w and its derivatives.
    """
    w, dw, d2w = closed(J2_0), jax.grad(closed)(J2_0), jax.hessian(closed)(J2_0)
    scale = abs(float(w)) / J2_0**2 + abs(float(dw)) / J2_0 + abs(float(d2w))
    return GROWTH * (steps + 1) * (RTOL * scale + ATOL / J2_0**2)


def test_the_closed_form_solves_the_reduced_equation():
    """The closed form against eq. (9) integrated by SciPy at rtol 1e-12 (an independent check
    of the momentum argument above): agreement to 1e-9 relative, the integrator's tolerance with
    room for its accumulation."""
    scipy_integrate = pytest.importorskip("scipy.integrate")
    p = params(J2_0)

    def rhs(t, w):
        return [float(V.paper_eq9(w[0], t, p))]

    sol = scipy_integrate.solve_ivp(rhs, (0.0, float(TS[-1])), [W0], method="DOP853", rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sol.y[0, -1], float(closed(J2_0)), rtol=1e-9)


@pytest.mark.slow  # two programs of second derivatives (about 30 s each)
@pytest.mark.parametrize(
    "adjoint, transform",
    [
        (None, "jacfwd(grad)"),  # the default: ForwardSensitivity(), forward mode over it
        (None, "hessian"),  # jax.hessian is jacfwd(jacrev): the same
        (diffrax.DirectAdjoint(), "grad(grad)"),
    ],
    ids=["default-jacfwd_grad", "default-hessian", "direct-grad_grad"],
)
def test_second_derivatives_are_right(adjoint, transform):
    f = lambda j2: rate(j2, adjoint=adjoint)  # noqa: E731
    second = {
        "jacfwd(grad)": jax.jacfwd(jax.grad(f)),
        "hessian": jax.hessian(f),
        "grad(grad)": jax.grad(jax.grad(f)),
    }[transform]
    got = float(jax.jit(second)(J2_0))
    steps = int(solve(J2_0).stats["num_accepted_steps"])
    exact = float(jax.hessian(closed)(J2_0))
    assert abs(got - exact) <= bound(steps), (got, exact, bound(steps))


REFUSALS = {
    # adjoint, the composition, words the message must contain
    "default-grad_grad": (None, "grad(grad)", ("ForwardSensitivity()", "jax.jacfwd(jax.grad(f))", "DirectAdjoint")),
    "default-grad_jacfwd": (None, "grad(jacfwd)", ("ForwardSensitivity()", "jax.hessian(f)")),
    "recursive-grad_grad": (
        diffrax.RecursiveCheckpointAdjoint(),
        "grad(grad)",
        ("adjoint=diffrax.RecursiveCheckpointAdjoint()", "DirectAdjoint()", "jax.jacfwd(jax.grad(f))"),
    ),
    "forward_mode-grad_grad": (diffrax.ForwardMode(), "grad(grad)", ("adjoint=diffrax.ForwardMode()", "jax.jacfwd")),
    # (diffrax's continuous adjoint fails inside its own backward pass with equinox's "Unexpected
    # tangent"; jaxnh._base.modes.differentiated_once on the solve's inputs refuses it first)
    "backsolve-grad_grad": (
        diffrax.BacksolveAdjoint(),
        "grad(grad)",
        ("adjoint=diffrax.BacksolveAdjoint()", "first derivatives only", "DirectAdjoint()"),
    ),
}


@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=[] if n == "default-grad_grad" else [pytest.mark.slow]) for n in REFUSALS],
)
def test_second_derivatives_refused_by_name(name):
    """A composition no adjoint's loop can go through raises a TypeError naming the adjoint and
    the compositions that work (before anything is compiled: the refusal is a rule of the
    transposition). The default adjoint's case is in the quick tier."""
    adjoint, transform, words = REFUSALS[name]
    f = lambda j2: rate(j2, adjoint=adjoint)  # noqa: E731
    second = {"grad(grad)": jax.grad(jax.grad(f)), "grad(jacfwd)": jax.grad(jax.jacfwd(f))}[transform]
    with pytest.raises(TypeError) as info:
        second(J2_0)
    missing = [w for w in words if w not in str(info.value)]
    assert not missing, f"the message lacks {missing}: {info.value}"


@pytest.mark.extended
def test_backsolve_first_derivatives_unchanged_by_the_second_order_guard():
    """The guard that refuses a second derivative through BacksolveAdjoint leaves the first one as
    it was: jax.grad against the exact dphi1'/dJ2, and jax.vmap(jax.grad) against jax.grad.

    Bound: as `bound` one order lower: the forward solve's error, a smooth function of J2, has a
    first derivative within GROWTH (steps + 1) (RTOL S1 + ATOL / J2), S1 = |w| / J2 + |dw/dJ2|;
    the backward (adjoint) solve at the same tolerances adds as much again: twice that."""
    f = lambda j2: rate(j2, adjoint=diffrax.BacksolveAdjoint())  # noqa: E731
    got = float(jax.grad(f)(J2_0))
    exact = float(jax.grad(closed)(J2_0))
    steps = int(solve(J2_0).stats["num_accepted_steps"])
    s1 = abs(float(closed(J2_0))) / J2_0 + abs(exact)
    assert abs(got - exact) <= 2 * GROWTH * (steps + 1) * (RTOL * s1 + ATOL / J2_0), (got, exact)
    batch = jax.vmap(jax.grad(f))(jnp.array([J2_0, J2_0]))
    np.testing.assert_allclose(np.asarray(batch), got, rtol=1e3 * np.finfo(np.float64).eps)
