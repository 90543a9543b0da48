"""Delayed feedback signal (DFS) controller: ``u(t) = -k (theta(t) - theta(t - tau))``.

Only the hub angle is measured; the history before t = 0 equals theta(0). The paper's
eq. (8) prints the plus sign, but its eqs. (9)-(10) and final controller carry the minus
sign, which jaxflex uses (the other sign is unstable). The paper's values are k = 55
(N*m/rad) and tau = 5 ms (5 samples at 1 kHz).

The delay is read from a ring buffer (:mod:`jaxflex.delay`) of static capacity. With
``interpolation="nearest"`` tau must be a whole number of samples (checked on concrete
parameters); ``"linear"`` reads between samples, so tau is a differentiable parameter.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import delay
from jaxflex.controllers.base import Controller, check_finite_scalar

_WHOLE_SAMPLE_RTOL = 1e-6  # tau / dt within this of an integer is a whole number of samples (float32 round-off)


class DFSParams(NamedTuple):
    """Attributes: k: gain (N*m/rad); tau_s: delay (s)."""

    k: ArrayLike = 55.0
    tau_s: ArrayLike = 0.005


def dfs(dt: float = 1e-3, capacity: int = 64, interpolation: str = "nearest") -> Controller:
    """The DFS controller for a loop sampled every ``dt`` seconds.

    Args:
      dt: sample time (s), > 0.
      capacity: longest delay the buffer holds, in samples (static); tau <= capacity * dt.
      interpolation: ``"nearest"`` (tau a whole number of samples) or ``"linear"``.
    """
    check_finite_scalar("dt", dt, positive=True)
    delay.check_capacity(capacity)
    if interpolation not in delay.INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {delay.INTERPOLATIONS}; got {interpolation!r}")
    dt = float(dt)

    def init(params: DFSParams, y0: jax.Array) -> delay.DelayState:
        del params
        return delay.delay_init(y0[:1], capacity)

    def step(params: DFSParams, state: delay.DelayState, y: jax.Array) -> tuple[delay.DelayState, jax.Array]:
        theta = y[:1]
        state, theta_delayed = delay.delay_step(state, theta, params.tau_s / dt, interpolation)
        return state, -params.k * (theta - theta_delayed)

    def check(params: DFSParams) -> None:
        check_finite_scalar("k", params.k)
        tau = check_finite_scalar("tau_s", params.tau_s, positive=True)
        steps = tau / dt
        if steps > capacity * (1 + _WHOLE_SAMPLE_RTOL):
            raise ValueError(
                f"tau_s must be in (0, {capacity * dt:g}] s (the delay buffer holds {capacity} samples of {dt:g} s); "
                f"got {tau:g} s. Pass a larger capacity to dfs()."
            )
        if interpolation == "nearest" and abs(steps - np.round(steps)) > _WHOLE_SAMPLE_RTOL * max(1.0, steps):
            raise ValueError(
                f"tau_s must be a whole number of samples of dt = {dt:g} s with interpolation='nearest'; got {tau:g} s "
                f"({steps:g} samples). Use interpolation='linear' for fractional delays."
            )

    return Controller(init, step, check)
