"""The closed loop: one ``lax.scan`` over time for any controller and any scenario.

At sample k the controller sees ``y[k] = C x[k] + noise[k]``, returns ``u[k]``, and the
plant advances ``x[k+1] = Ad x[k] + Bd u[k] + Ed force[k]`` (inputs held over the sample).

``rollout`` is pure, unjitted and unbatched: callers compose ``jax.jit``, ``jax.vmap``
(over scenarios, plants or parameters) and ``jax.grad`` around it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxflex.controllers.base import Controller, is_concrete
from jaxflex.plant import DiscretePlant
from jaxflex.scenarios import Scenario


class Trajectory(NamedTuple):
    """A simulated response; time is the first axis.

    Attributes:
      t: [T] sample times (s), starting at 0.
      x: [T, n_x] state at each sample.
      u: [T, 1] hub torque (N*m) held from each sample to the next.
      y: [T, 2] measurement seen by the controller (hub angle rad, hub velocity rad/s).
      z: [T, 3] hub angle (rad), elastic tip deflection (m), tip position (m).
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    y: jax.Array
    z: jax.Array


def _check_shapes(plant: DiscretePlant, scenario: Scenario) -> None:
    n_x = plant.Ad.shape[-1]
    if plant.Ad.shape != (n_x, n_x):
        raise ValueError(f"Ad must be square; got {plant.Ad.shape}")
    if scenario.x0.shape != (n_x,):
        raise ValueError(f"scenario.x0 must have shape ({n_x},) for this plant; got {scenario.x0.shape}")
    steps = scenario.force.shape[0] if scenario.force.ndim == 2 else -1
    if scenario.force.shape != (steps, 1) or steps < 1:
        raise ValueError(f"scenario.force must have shape (T, 1) with T >= 1; got {scenario.force.shape}")
    if scenario.noise.shape != (steps, 2):
        raise ValueError(f"scenario.noise must have shape ({steps}, 2); got {scenario.noise.shape}")


def rollout(plant: DiscretePlant, controller: Controller, params: Any, scenario: Scenario) -> Trajectory:
    """Simulate the closed loop over the scenario's horizon.

    Args:
      plant: sampled plant (``plant.discretize``).
      controller: any :class:`~jaxflex.controllers.base.Controller`.
      params: the controller's parameter pytree (leaves may be traced).
      scenario: one unbatched scenario; the horizon T is ``scenario.force.shape[0]``.

    Returns:
      Trajectory with fields [T, ...]. A loop that diverges returns non-finite or huge
      values; :func:`jaxflex.analysis.metrics.diverged` reports it.
    """
    _check_shapes(plant, scenario)
    if is_concrete(params):
        controller.check(params)

    def body(carry, inputs):
        x, state = carry
        force, noise = inputs
        y = plant.C @ x + noise
        state, u = controller.step(params, state, y)
        x_next = plant.Ad @ x + plant.Bd @ u + plant.Ed @ force
        return (x_next, state), (x, u, y, plant.Cz @ x)

    y0 = plant.C @ scenario.x0 + scenario.noise[0]
    carry0 = (scenario.x0, controller.init(params, y0))
    _, (x, u, y, z) = jax.lax.scan(body, carry0, (scenario.force, scenario.noise))
    t = jnp.arange(scenario.force.shape[0], dtype=x.dtype) * plant.dt
    return Trajectory(t, x, u, y, z)
