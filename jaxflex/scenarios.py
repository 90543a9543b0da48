"""Disturbance scenarios: initial state, tip-force sequence and sensor noise.

A :class:`Scenario` is an all-array pytree; batches of scenarios are the same pytree with a
leading batch axis (what ``jax.vmap`` maps over). The horizon is the (static) length of the
force sequence.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex.plant import DiscretePlant, LinearPlant, n_modes_of

READINGS = ("printed", "block")


class Scenario(NamedTuple):
    """One disturbance scenario.

    Attributes:
      x0: [n_x] initial state: hub angle (rad), modal amplitudes (m), then their rates.
      force: [T, 1] transverse tip force (N), held over each sample.
      noise: [T, 2] additive sensor noise on the measured hub angle (rad) and velocity (rad/s).
    """

    x0: jax.Array
    force: jax.Array
    noise: jax.Array


def horizon_steps(horizon_s: float, dt: float) -> int:
    """Number of samples in ``horizon_s`` seconds at ``dt`` (both concrete, > 0)."""
    for name, value in (("horizon_s", horizon_s), ("dt", dt)):
        v = float(value)
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0 (seconds); got {value}")
    steps = int(round(float(horizon_s) / float(dt)))
    if steps < 1:
        raise ValueError(f"horizon_s must cover at least one sample of dt = {dt}; got {horizon_s}")
    return steps


def paper_scenario(plant: LinearPlant | DiscretePlant, horizon_s: float = 3.0, dt: float = 1e-3, reading: str = "printed", dtype=None) -> Scenario:
    """The paper's disturbance: an initial condition, no force, no noise.

    The paper prints ``x0 = [0 0 1e-3 0 1e-5 0]`` beside a state printed as
    ``[theta theta_dot q1 q2 q1_dot q2_dot]``.

    Args:
      plant: the plant (only its number of modes is used).
      horizon_s: simulated time (s); the paper's figures show 3 s.
      dt: sample time (s).
      reading: ``"printed"`` (default): in the printed order, q_1(0) = 1e-3 m and
        q_1_dot(0) = 1e-5 m/s. ``"block"``: the numbers read in jaxflex's state order,
        q_2(0) = 1e-3 m and q_1_dot(0) = 1e-5 m/s (needs n_modes >= 2).
      dtype: floating dtype of the arrays (default: the plant's).
    """
    n = n_modes_of(plant)
    steps = horizon_steps(horizon_s, dt)
    dtype = plant.C.dtype if dtype is None else dtype
    x0 = np.zeros(2 * (n + 1))
    if reading == "printed":
        x0[1], x0[n + 2] = 1e-3, 1e-5
    elif reading == "block":
        if n < 2:
            raise ValueError(f"reading='block' sets q_2 and needs n_modes >= 2; got n_modes = {n}")
        x0[2], x0[n + 2] = 1e-3, 1e-5
    else:
        raise ValueError(f"reading must be one of {READINGS}; got {reading!r}")
    return Scenario(jnp.asarray(x0, dtype), jnp.zeros((steps, 1), dtype), jnp.zeros((steps, 2), dtype))


def initial_condition(x0: ArrayLike, steps: int, dtype=None) -> Scenario:
    """A scenario with the given initial state and no force or noise for ``steps`` samples."""
    x0 = jnp.asarray(x0, dtype)
    if x0.ndim != 1:
        raise ValueError(f"x0 must have shape (n_x,); got {x0.shape}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an integer >= 1; got {steps!r}")
    return Scenario(x0, jnp.zeros((steps, 1), x0.dtype), jnp.zeros((steps, 2), x0.dtype))
