"""Scalar objectives over a batch of closed-loop rollouts, and a stability penalty for DFS.

Per scenario, the loss is a weighted sum of terms, each divided by its mean over the training
batch under the paper's gains (so the paper's gains score exactly ``sum(weights)`` on the
training batch and every term is dimensionless):

* ``tip_ise``: integral of the squared elastic tip deflection;
* ``hub_ise``: integral of the squared hub angle (the hub-angle error; set-point 0);
* ``effort``: integral of the squared torque;
* ``vibration``: energy of the tip deflection near the modal frequencies: the squared
  magnitude of its Hann-windowed Fourier transform at each natural frequency of the nominal
  model, summed over modes (``RunMetrics.modal_energy``, streamed in the rollout).

The batch is combined by its mean, its CVaR (the mean of the worst ``1 - level`` fraction),
or a smooth worst case ``T logsumexp(l / T) - T log B``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import fileio
from jaxflex.plant import DiscretePlant
from jaxflex.rollout import RunMetrics

TERMS = ("tip_ise", "hub_ise", "effort", "vibration")
REDUCTIONS = ("mean", "cvar", "worst")


@dataclasses.dataclass(frozen=True)
class ObjectiveSpec:
    """How per-scenario losses are built and combined (see the module docstring).

    Attributes:
      tip_ise, hub_ise, effort, vibration: non-negative weights of the terms (not all 0).
      reduction: "mean", "cvar" or "worst".
      cvar_level: CVaR level in [0, 1): 0.9 averages the worst 10 % of scenarios.
      worst_temperature: temperature of the smooth worst case (> 0, in units of the
        normalised loss).
      stability_weight: weight of the DFS stability penalty (>= 0).
      min_decay_rate: the penalty acts when the slowest non-structural mode of the sampled
        loop decays slower than this rate (1/s, >= 0).
    """

    tip_ise: float = 1.0
    hub_ise: float = 0.0
    effort: float = 0.0
    vibration: float = 0.0
    reduction: str = "mean"
    cvar_level: float = 0.9
    worst_temperature: float = 0.1
    stability_weight: float = 10.0
    min_decay_rate: float = 0.05

    def __post_init__(self) -> None:
        for name in TERMS + ("stability_weight", "min_decay_rate"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"objective {name} must be a finite number >= 0; got {v!r}")
        if not any(getattr(self, t) > 0 for t in TERMS):
            raise ValueError(f"at least one objective weight among {TERMS} must be > 0")
        if self.reduction not in REDUCTIONS:
            raise ValueError(f"objective reduction must be one of {REDUCTIONS}; got {self.reduction!r}")
        if not (0 <= self.cvar_level < 1):
            raise ValueError(f"objective cvar_level must be in [0, 1); got {self.cvar_level}")
        if not (math.isfinite(self.worst_temperature) and self.worst_temperature > 0):
            raise ValueError(f"objective worst_temperature must be finite and > 0; got {self.worst_temperature}")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "ObjectiveSpec":
        fileio.check_keys(values, [f.name for f in dataclasses.fields(cls)], "objective")
        return cls(**dict(values))


class Terms(NamedTuple):
    """Unweighted, unnormalised terms of one scenario (each shape ())."""

    tip_ise: jax.Array
    hub_ise: jax.Array
    effort: jax.Array
    vibration: jax.Array


def terms_from_metrics(m: RunMetrics) -> Terms:
    """The terms of one scenario from its running metrics (modal energies summed over modes)."""
    return Terms(m.tip_ise, m.hub_ise, m.control_effort, jnp.sum(m.modal_energy))


def reference_scales(terms: Terms) -> Terms:
    """Batch means of each term (under the paper's gains), floored so no division by 0."""
    return Terms(*(jnp.maximum(jnp.mean(t), jnp.finfo(t.dtype).tiny) for t in terms))


def scenario_losses(terms: Terms, scales: Terms, spec: ObjectiveSpec) -> jax.Array:
    """[B] weighted, normalised per-scenario losses."""
    total = 0.0
    for name in TERMS:
        weight = getattr(spec, name)
        if weight > 0:
            total = total + weight * getattr(terms, name) / getattr(scales, name)
    return total


def reduce_losses(losses: jax.Array, spec: ObjectiveSpec) -> jax.Array:
    """Combine [B] losses into one scalar (mean, CVaR or smooth worst case)."""
    if spec.reduction == "mean":
        return jnp.mean(losses)
    if spec.reduction == "cvar":
        count = max(1, int(math.ceil((1 - spec.cvar_level) * losses.shape[0])))
        return jnp.mean(jax.lax.top_k(losses, count)[0])
    temp = spec.worst_temperature
    return temp * (jax.nn.logsumexp(losses / temp) - jnp.log(losses.shape[0]))


def dfs_loop_matrix(plant: DiscretePlant, k: jax.Array, tau_s: jax.Array, capacity: int) -> jax.Array:
    """Transition matrix of the sampled DFS loop with a linearly interpolated delay line.

    State ``[x_k, theta_{k-1}, ..., theta_{k-capacity}]``; exactly the jaxflex rollout with
    ``dfs(dt, capacity, interpolation="linear")`` and no noise or force.
    """
    n_x = plant.Ad.shape[0]
    dtype = plant.Ad.dtype
    d = jnp.clip(tau_s / plant.dt, 0.0, capacity)
    whole = jnp.minimum(jnp.floor(d), capacity - 1)
    frac = d - whole
    lags = jnp.arange(capacity + 1, dtype=dtype)
    weights = (1 - frac) * (lags == whole) + frac * (lags == whole + 1)  # on theta_{k-j}, j = 0..capacity
    # u_k = -k (theta_k - sum_j w_j theta_{k-j})
    gain_theta = -k * (1 - weights[0])
    gain_hist = k * weights[1:]  # [capacity]
    top = plant.Ad + gain_theta * plant.Bd @ plant.C[:1]
    top = jnp.concatenate([top, plant.Bd * gain_hist[None, :]], axis=1)
    shift = jnp.zeros((capacity, n_x + capacity), dtype)
    shift = shift.at[0, 0].set(1.0)
    shift = shift.at[1:, n_x : n_x + capacity - 1].set(jnp.eye(capacity - 1, dtype=dtype))
    return jnp.concatenate([top, shift], axis=0)


def deflate_structural(loop: jax.Array, n_x: int) -> jax.Array:
    """The loop matrix with the structural z = 1 removed exactly (one size smaller).

    DFS has no position action: a constant hub angle with a matching history,
    ``v = [e_0, 1, ..., 1]``, is an exact eigenvector with eigenvalue 1. With
    ``T = I + (v - e_0) e_0^T`` (whose inverse is ``I - (v - e_0) e_0^T``), ``T^-1 M T`` has
    first column ``e_0``, so its trailing block holds the other eigenvalues.
    """
    size = loop.shape[0]
    e0 = jnp.zeros((size,), loop.dtype).at[0].set(1.0)
    v = e0.at[n_x:].set(1.0)
    t = jnp.eye(size, dtype=loop.dtype) + jnp.outer(v - e0, e0)
    t_inv = jnp.eye(size, dtype=loop.dtype) - jnp.outer(v - e0, e0)
    return (t_inv @ loop @ t)[1:, 1:]


def spectral_radius(matrix: jax.Array) -> jax.Array:
    """Largest |eigenvalue| (exact, for reporting; its gradient is NaN at repeated eigenvalues)."""
    return jnp.max(jnp.abs(jnp.linalg.eigvals(matrix)))


def log_spectral_radius_smooth(matrix: jax.Array, squarings: int = 24) -> jax.Array:
    """Differentiable estimate of log(spectral radius): log ||M^N|| / N with N = 2^squarings.

    Gelfand's formula by normalised repeated squaring; it approaches log rho from above with
    an error of about log(cond) / N. Unlike ``eigvals`` its gradient is finite when the
    matrix has repeated eigenvalues (the unused tail of the delay line is a nilpotent block).
    """

    def body(carry, _):
        b, log_norm = carry
        sq = b @ b
        n = jnp.linalg.norm(sq)
        return (sq / n, 2 * log_norm + jnp.log(n)), None

    n0 = jnp.linalg.norm(matrix)
    (_, log_norm), _ = jax.lax.scan(body, (matrix / n0, jnp.log(n0)), None, length=squarings)
    return log_norm / 2.0**squarings


def stability_penalty(log_radius: jax.Array, dt: float, spec: ObjectiveSpec) -> jax.Array:
    """``weight * relu(decay_min - decay)^2`` with ``decay = -log(radius) / dt`` (1/s)."""
    decay = -log_radius / dt
    return spec.stability_weight * jax.nn.relu(spec.min_decay_rate - decay) ** 2
