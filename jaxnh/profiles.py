"""Differentiable functions of time held in parameters.

A profile is an `eqx.Module` called as `profile(t)`; its array fields are
the trainable leaves, so `jax.grad` with respect to params reaches them, and
its time derivatives come from autodiff (`profile.derivative(t)`). Units are
those of the quantity it describes (a ratio is dimensionless, a torque N·m).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["Profile", "Constant", "Fourier"]


class Profile(eqx.Module):
    """A scalar function of time t (s)."""

    @abc.abstractmethod
    def __call__(self, t):
        """Value at time t."""

    def derivative(self, t):
        """d/dt of the profile at t, by automatic differentiation."""
        return jax.jvp(self.__call__, (t,), (jnp.ones_like(t),))[1]


class Constant(Profile):
    """A value that does not change with time."""

    value: Float[Array, ""]

    def __init__(self, value):
        self.value = jnp.asarray(value, dtype=jnp.result_type(float))

    def __call__(self, t):
        return self.value + 0 * t


class Fourier(Profile):
    """A truncated Fourier series of period `period` (s):

    `mean + Σ_k cos[k-1] cos(2π k t / period) + sin[k-1] sin(2π k t / period)`.
    """

    mean: Float[Array, ""]
    cos: Float[Array, " K"]
    sin: Float[Array, " K"]
    period: Float[Array, ""]

    def __init__(self, mean, cos=(), sin=(), period=1.0):
        f = jnp.result_type(float)
        self.mean = jnp.asarray(mean, dtype=f)
        c, s = jnp.atleast_1d(jnp.asarray(cos, dtype=f)), jnp.atleast_1d(jnp.asarray(sin, dtype=f))
        K = max(c.shape[0], s.shape[0])
        self.cos = jnp.zeros(K, f).at[: c.shape[0]].set(c)
        self.sin = jnp.zeros(K, f).at[: s.shape[0]].set(s)
        self.period = jnp.asarray(period, dtype=f)

    def __call__(self, t):
        k = jnp.arange(1, self.cos.shape[-1] + 1, dtype=self.mean.dtype)
        w = 2 * jnp.pi * k * t / self.period
        return self.mean + jnp.sum(self.cos * jnp.cos(w) + self.sin * jnp.sin(w))
