"""Delayed feedback signal (DFS) controller: ``u(t) = -k (theta(t) - theta(t - tau))``.

Only the hub angle is measured; the history before t = 0 equals theta(0). The paper's
eq. (8) prints the plus sign, but its eqs. (9)-(10) and final controller carry the minus
sign, which jaxflex uses (the other sign is unstable). The paper's values are k = 55
(N*m/rad) and tau = 5 ms (5 samples at 1 kHz).

The delayed angle comes from one of two approximations of the delay (one controller,
chosen by ``approximation``):

* ``"buffer"`` (default): a ring buffer (:mod:`jaxflex.delay`) of static capacity. With
  ``interpolation="nearest"`` tau must be a whole number of samples (checked on concrete
  parameters; a traced tau that is not, under ``jit`` or ``vmap``, gives a NaN torque, so the
  run reports itself diverged instead of running with the delay rounded);
  ``"linear"`` and ``"cubic"`` read between samples, so tau is a differentiable parameter,
  up to ``capacity * dt``.
* ``"pade"``: the ``[N/N]`` Pade approximant of ``e^{-s tau}`` (:mod:`jaxflex.pade`), sampled
  exactly at ``dt``, filters the measured angle. Its N states replace the buffer; tau is
  differentiable and has no upper bound. The filter is sampled once per rollout, in
  ``init`` (one ``expm``), and carried unchanged in the state: recomputing it in ``step``
  would cost an ``expm`` per sample, while carrying it costs nothing per step (JAX does
  not store loop-invariant carries for the backward pass).

  ``pade_hold`` sets what the filter sees between samples. ``"foh"`` (default): the
  straight lines through consecutive samples, so as N grows the loop converges, slowly
  beyond N = 4 (see :mod:`jaxflex.pade`), to the ``"linear"`` buffer loop (the exact delay
  when tau is a whole number of samples).
  ``"zoh"``: the held staircase; the all-pass filter passes each new sample's jump straight
  through (feedthrough ``(-1)^N``), so the delayed angle is off by about one sample
  increment whatever N, the loop does not converge to the buffer as N grows, and over 3 s
  of the paper scenario it diverges at tau = 5.3 ms for N >= 16. ``"zoh"`` is kept as the
  textbook ``c2d`` of the filter, for comparison.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxflex import delay, pade
from jaxflex.controllers.base import Controller, check_finite_scalar, check_params_type, check_scalar_param

APPROXIMATIONS = ("buffer", "pade")
CAPACITY_REMEDY = "Pass a larger capacity to dfs() (the capacity key of a tune or montecarlo config)."


class DFSParams(NamedTuple):
    """Attributes: k: gain (N*m/rad); tau_s: delay (s)."""

    k: ArrayLike = 55.0
    tau_s: ArrayLike = 0.005


class PadeDelayState(NamedTuple):
    """State of the DFS controller with ``approximation="pade"``.

    Attributes:
      xi: [N] Pade filter state (rad), [N, B] for a batch; ``C xi + D theta`` is the
        delayed angle.
      filt: the filter sampled at ``dt`` for this tau (``Ad`` [N, N], ``Bd`` [N, 1],
        ``C`` [1, N], ``D`` [1, 1]). Computed once in ``init`` (one ``expm``) and carried
        unchanged, because step-wise recomputation would cost an ``expm`` per sample.
    """

    xi: jax.Array
    filt: pade.PadeDiscrete


def dfs(
    dt: float = 1e-3,
    capacity: int = 64,
    interpolation: str = "nearest",
    approximation: str = "buffer",
    pade_order: int = 4,
    pade_hold: str = "foh",
) -> Controller:
    """The DFS controller for a loop sampled every ``dt`` seconds.

    Args:
      dt: sample time (s), > 0.
      capacity: longest delay the buffer holds, in samples (static); tau <= capacity * dt.
        Used by ``approximation="buffer"`` only. ``check`` refuses a concrete tau outside
        ``(0, capacity dt]``; a traced one there (under ``jit``) gives a NaN torque, so the
        run reports itself diverged instead of running with a clamped delay.
      interpolation: buffer reads: ``"nearest"`` (tau a whole number of samples; a traced
        tau between samples gives a NaN torque, as one outside the buffer does; its
        derivative in tau is exactly 0: differentiate tau through ``"linear"``, ``"cubic"``
        or ``"pade"``), ``"linear"`` or ``"cubic"`` (see :mod:`jaxflex.delay`). Unused with
        ``"pade"``.
      approximation: ``"buffer"`` (ring buffer) or ``"pade"`` (Pade filter states; see the
        module docstring).
      pade_order: N, the Pade order (Python int >= 1); used with ``"pade"`` only.
      pade_hold: how the filter sees the sampled angle between samples, with ``"pade"``:
        ``"foh"`` (default; the straight line through consecutive samples) or ``"zoh"``
        (held). See the module docstring: only ``"foh"`` converges to the buffer.

    Raises:
      ValueError: naming the argument and its accepted values.
    """
    check_finite_scalar("dt", dt, positive=True)
    capacity = delay.check_capacity(capacity)
    if interpolation not in delay.INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {delay.INTERPOLATIONS}; got {interpolation!r}")
    if approximation not in APPROXIMATIONS:
        raise ValueError(f"approximation must be one of {APPROXIMATIONS}; got {approximation!r}")
    pade_order = pade.check_order(pade_order, "pade_order")
    if pade_hold not in pade.HOLDS:
        raise ValueError(f"pade_hold must be one of {pade.HOLDS}; got {pade_hold!r}")
    dt = float(dt)
    use_pade = approximation == "pade"

    def init(params: DFSParams, y0: jax.Array) -> delay.DelayState | PadeDelayState:
        theta0 = y0[:1]
        if not use_pade:
            return delay.delay_init(theta0, capacity)
        filt, xi0 = pade.sampled_delay(jnp.asarray(params.tau_s, y0.dtype), pade_order, dt, theta0, pade_hold)
        return PadeDelayState(xi0, filt)

    def step(params: DFSParams, state: delay.DelayState | PadeDelayState, y: jax.Array) -> tuple[delay.DelayState | PadeDelayState, jax.Array]:
        theta = y[:1]
        if use_pade:
            f = state.filt
            theta_delayed = f.C @ state.xi + f.D @ theta
            state = state._replace(xi=f.Ad @ state.xi + f.Bd @ theta)
            return state, -params.k * (theta - theta_delayed)
        steps = params.tau_s / dt
        state, theta_delayed = delay.delay_step(state, theta, steps, interpolation)
        held = (steps > 0) & (steps <= capacity * (1 + delay.WHOLE_SAMPLE_RTOL))
        if interpolation == "nearest":
            held = held & delay.whole_samples(steps)
        return state, jnp.where(held, -params.k * (theta - theta_delayed), jnp.nan)

    def check(params: DFSParams) -> None:
        check_params_type(params, DFSParams)
        check_scalar_param("k", params.k)
        tau = check_scalar_param("tau_s", params.tau_s, positive=True)
        if use_pade or tau is None:
            return
        steps = tau / dt
        if steps > capacity * (1 + delay.WHOLE_SAMPLE_RTOL):
            raise ValueError(
                f"tau_s must be in (0, {capacity * dt:g}] s (the delay buffer holds {capacity} samples of {dt:g} s); "
                f"got {tau:g} s. {CAPACITY_REMEDY}"
            )
        if interpolation == "nearest" and not delay.whole_samples(steps):
            raise ValueError(
                f"tau_s must be a whole number of samples of dt = {dt:g} s with interpolation='nearest'; got {tau:g} s "
                f"({steps:g} samples). Use interpolation='linear' or 'cubic' for fractional delays (delay = 'linear' or 'cubic' in by_name and the tune and montecarlo configs)."
            )

    return Controller(init, step, check, dt, batched=True)
