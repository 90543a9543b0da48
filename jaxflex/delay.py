"""Ring-buffer delay line carried through ``lax.scan``.

The buffer has a static capacity (the longest delay it can serve, in samples) and holds the
last ``capacity + 1`` samples. Each step pushes the current sample, then reads the sample
``d`` steps back, ``0 <= d <= capacity``. Before t = 0 the history equals the first sample
(the paper's convention for the DFS controller).

Reads take a delay in samples that may be traced: ``"nearest"`` rounds it to a whole
number of samples; ``"linear"`` interpolates between the two neighbouring samples, so the
read is differentiable in the delay and exact at whole samples.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

INTERPOLATIONS = ("nearest", "linear")


class DelayState(NamedTuple):
    """Ring buffer of past samples.

    Attributes:
      buffer: [capacity + 1, n] past samples; slot ``head - 1`` (mod size) is the newest.
      head: shape () int32, the slot the next sample is written to.
    """

    buffer: jax.Array
    head: jax.Array


def check_capacity(capacity: int) -> int:
    """The capacity sets an array shape, so it must be a Python int >= 1."""
    if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
        raise ValueError(f"capacity must be an integer >= 1 (samples); got {capacity!r}")
    return capacity


def delay_init(y0: ArrayLike, capacity: int) -> DelayState:
    """A delay line whose whole history equals ``y0`` [n]."""
    capacity = check_capacity(capacity)
    y0 = jnp.asarray(y0)
    if y0.ndim != 1:
        raise ValueError(f"y0 must have shape (n,); got {y0.shape}")
    buffer = jnp.broadcast_to(y0[None, :], (capacity + 1, y0.shape[0]))
    return DelayState(buffer, jnp.zeros((), jnp.int32))


def delay_push(state: DelayState, y: jax.Array) -> DelayState:
    """Write the newest sample ``y`` [n]."""
    size = state.buffer.shape[0]
    buffer = state.buffer.at[state.head].set(y)
    return DelayState(buffer, (state.head + 1) % size)


def delay_read(state: DelayState, delay_steps: ArrayLike, interpolation: str = "nearest") -> jax.Array:
    """The sample ``delay_steps`` before the newest one, [n].

    Args:
      state: the delay line after the current sample was pushed.
      delay_steps: delay in samples, in [0, capacity]; may be traced. Values outside are
        clipped to that range (check them where they are concrete: ``DFS.check``).
      interpolation: ``"nearest"`` or ``"linear"`` (see the module docstring).
    """
    size = state.buffer.shape[0]
    d = jnp.clip(jnp.asarray(delay_steps, state.buffer.dtype), 0, size - 1)
    newest = state.head - 1
    if interpolation == "nearest":
        index = (newest - jnp.round(d).astype(jnp.int32)) % size
        return state.buffer[index]
    if interpolation == "linear":
        whole = jnp.minimum(jnp.floor(d), size - 2)
        frac = d - whole
        i0 = (newest - whole.astype(jnp.int32)) % size
        i1 = (i0 - 1) % size
        return (1 - frac) * state.buffer[i0] + frac * state.buffer[i1]
    raise NotImplementedError(f"interpolation must be one of {INTERPOLATIONS}; got {interpolation!r}")


def delay_step(state: DelayState, y: jax.Array, delay_steps: ArrayLike, interpolation: str = "nearest") -> tuple[DelayState, jax.Array]:
    """Push ``y`` and read the sample ``delay_steps`` back: a ``lax.scan`` body."""
    state = delay_push(state, y)
    return state, delay_read(state, delay_steps, interpolation)
