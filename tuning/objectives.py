"""Scalar objectives over a batch of closed-loop rollouts, and a stability penalty for DFS.

Per scenario, the loss is a weighted sum of terms, each divided by its mean over the training
batch under the reference gains (``TuneConfig.reference``: the paper's by default, or the
``[initial]`` ones), so every term is dimensionless and the reference gains score exactly
``sum(weights)`` on the training batch under the mean (the CVaR and the worst case score them
higher):

* ``tip_ise``: integral of the squared elastic tip deflection;
* ``hub_ise``: integral of the squared hub angle (the hub-angle error; set-point 0);
* ``effort``: integral of the squared torque;
* ``vibration``: energy of the tip deflection near the modal frequencies: the squared
  magnitude of its Hann-windowed Fourier transform at each natural frequency of the arm the
  scenario runs on (its plant perturbation included), summed over modes
  (``RunMetrics.modal_energy``, streamed in the rollout).

The batch is combined by its mean, its CVaR (the mean of the worst ``1 - level`` fraction),
or a smooth worst case ``T logsumexp(l / T) - T log B``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import checks, fileio
from jaxflex.controllers.base import is_concrete
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
      stability_weight: weight of the DFS stability penalty (>= 0); it acts on the
        controller "dfs" only (a dfs+fuzzy loop is nonlinear: no loop matrix, no penalty).
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
            object.__setattr__(self, name, checks.number(f"objective {name}", getattr(self, name)))
        if not any(getattr(self, t) > 0 for t in TERMS):
            raise ValueError(f"at least one objective weight among {TERMS} must be > 0")
        if self.reduction not in REDUCTIONS:
            raise ValueError(f"objective reduction must be one of {REDUCTIONS}; got {self.reduction!r}")
        level = self.cvar_level
        if isinstance(level, bool) or not isinstance(level, numbers.Real) or not (0 <= level < 1):
            raise ValueError(f"objective cvar_level must be a number in [0, 1); got {level!r}")
        object.__setattr__(self, "cvar_level", float(level))
        object.__setattr__(self, "worst_temperature", checks.number("objective worst_temperature", self.worst_temperature, strict=True))

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
    """Batch means of each term (under the reference gains: the paper's or the initial ones), floored so no division by 0."""
    return Terms(*(jnp.maximum(jnp.mean(t), jnp.finfo(t.dtype).tiny) for t in terms))


def scenario_losses(terms: Terms, scales: Terms, spec: ObjectiveSpec) -> jax.Array:
    """[B] weighted, normalised per-scenario losses."""
    total = 0.0
    for name in TERMS:
        weight = getattr(spec, name)
        if weight > 0:
            total = total + weight * getattr(terms, name) / getattr(scales, name)
    return total


def _cvar_count(level: float, batch: int) -> int:
    """How many of ``batch`` losses the CVaR at ``level`` averages: ``ceil((1 - level) batch)``,
    at least 1. The product is rounded to 9 decimals first, so that a whole number computed
    in floating point (``(1 - 0.7) * 10 = 3.0000000000000004``) is not rounded up past."""
    return max(1, math.ceil(round((1 - level) * batch, 9)))


def reduce_losses(losses: jax.Array, spec: ObjectiveSpec) -> jax.Array:
    """Combine [B] losses into one scalar (mean, CVaR or smooth worst case)."""
    if spec.reduction == "mean":
        return jnp.mean(losses)
    if spec.reduction == "cvar":
        count = _cvar_count(spec.cvar_level, losses.shape[0])
        return jnp.mean(jax.lax.top_k(losses, count)[0])
    temp = spec.worst_temperature
    return temp * (jax.nn.logsumexp(losses / temp) - jnp.log(losses.shape[0]))


@jax.custom_jvp
def log_spectral_radius(matrix: jax.Array) -> jax.Array:
    """log of the largest |eigenvalue| of a real square matrix, differentiable.

    The derivative is that of the dominant eigenvalue alone, ``Re(dlam / lam)`` with
    ``dlam = w^T dM v / (w^T v)`` from its right eigenvector ``v`` (``M v = lam v``) and left
    eigenvector ``w`` (``w^T M = lam w^T``). It stays finite where other eigenvalues repeat
    (the defective zero eigenvalues of the unused tail of the delay line), where the
    derivative of ``eigvals`` is NaN. A conjugate pair gives the same derivative from either
    member; where two different modes tie in modulus it is that of one of them, a
    one-sided derivative of the max. (Gelfand's formula, ``log ||M^N|| / N``, has the right
    value but not the right derivative: with a complex dominant pair, ``||M^N||`` oscillates
    with the phase ``N arg(lam)``, and the derivative of that phase does not vanish as N
    grows.)

    Raises:
      ValueError: for a matrix that is not square, or (where concrete) not finite.
    """
    shape = jnp.shape(matrix)
    if len(shape) != 2 or shape[0] != shape[1] or shape[0] < 1:
        raise ValueError(f"matrix must be a square 2-D array; got shape {shape}")
    if is_concrete(matrix) and not np.all(np.isfinite(np.asarray(matrix))):
        raise ValueError("matrix must be finite; it holds inf or NaN")
    return jnp.log(jnp.max(jnp.abs(jnp.linalg.eigvals(matrix))))


@log_spectral_radius.defjvp
def _log_spectral_radius_jvp(primals: tuple[jax.Array], tangents: tuple[jax.Array]) -> tuple[jax.Array, jax.Array]:
    (matrix,), (d_matrix,) = primals, tangents
    values, right = jnp.linalg.eig(matrix)
    i = jnp.argmax(jnp.abs(values))
    lam, v = values[i], right[:, i]
    # Left eigenvectors as right eigenvectors of the transpose (eig with left eigenvectors is
    # not available on every backend); pick the one of the same eigenvalue.
    values_t, right_t = jnp.linalg.eig(matrix.T)
    w = right_t[:, jnp.argmin(jnp.abs(values_t - lam))]
    d_lam = (w @ d_matrix.astype(v.dtype) @ v) / (w @ v)
    return jnp.log(jnp.abs(lam)), jnp.real(d_lam / lam).astype(matrix.dtype)


def stability_penalty(log_radius: jax.Array, dt: float, spec: ObjectiveSpec) -> jax.Array:
    """``weight * relu(decay_min - decay)^2`` with ``decay = -log(radius) / dt`` (1/s)."""
    decay = -log_radius / dt
    return spec.stability_weight * jax.nn.relu(spec.min_decay_rate - decay) ** 2
