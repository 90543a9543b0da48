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

from jaxflex import fileio
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


def spectral_radius(matrix: jax.Array) -> jax.Array:
    """Largest |eigenvalue| (exact, for reporting; its gradient is NaN at repeated eigenvalues)."""
    return jnp.max(jnp.abs(jnp.linalg.eigvals(matrix)))


def log_spectral_radius_smooth(matrix: jax.Array, squarings: int = 24) -> jax.Array:
    """Differentiable estimate of log(spectral radius): log ||M^N|| / N with N = 2^squarings.

    Gelfand's formula by normalised repeated squaring; it approaches log rho from above with
    an error of about log(cond) / N. Unlike ``eigvals`` its gradient is finite when the
    matrix has repeated eigenvalues (the zero eigenvalues of the unused tail of the delay line).
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
