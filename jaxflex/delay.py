"""Ring-buffer delay line carried through ``lax.scan``.

The buffer has a static capacity (the longest delay it can serve, in samples) and holds the
last ``capacity + 1`` samples. Each step pushes the current sample, then reads the sample
``d`` steps back, ``0 <= d <= capacity``. Before t = 0 the history equals the first sample
(the paper's convention for the DFS controller).

Reads take a delay ``d`` in samples that may be traced; the capacity is static, so a new
delay never recompiles. State: ``capacity + 1`` samples and the write index, whatever the
mode. Every mode is exact at whole samples; they differ between them:

* ``"nearest"`` rounds ``d`` to a whole number of samples: one gather per step. The delay
  is quantised to ``dt``; the read is piecewise constant in ``d`` (zero gradient).
* ``"linear"`` interpolates between the two neighbouring samples: two gathers and three
  flops per step. Error ``O(dt^2)``: at most ``dt^2 max|y''| / 8`` for a smooth signal; a
  sinusoid with ``w dt = 0.1`` read halfway between samples loses 1.2e-3 of its amplitude.
  The read is continuous and piecewise linear in ``d``, with kinks at whole samples.
* ``"cubic"``: 4-point Lagrange interpolation on the samples ``floor(d) - 1 .. floor(d) + 2``
  back (two neighbours each side): four gathers and about 40 flops per step. Error
  ``O(dt^4)``: at most ``(3 / 128) dt^4 max|y''''|`` between the two middle nodes; the same
  sinusoid loses 2.3e-6 of its amplitude. The read reproduces cubic polynomials in time
  exactly, is continuous in ``d``, and its derivative in ``d`` jumps at whole samples,
  where the stencil shifts by one (as the linear read's does). There gradients are
  one-sided: JAX returns the derivative from above (``floor(d)`` picks the stencil of
  ``[d, d + 1)``), except at ``d = capacity`` where only the one from below exists.
  "Whole" means ``tau / dt`` as computed in the run's dtype: in float32 ``0.005 / 0.001``
  rounds to 4.9999995, so the derivative there is the one from below (12 % apart for the
  paper's loop), and under jit even 3 ms at 1 ms has given the one from below.

  Near the ends the stencil is clamped into the buffer, keeping four nodes: for ``d < 1``
  it is the samples 0..3 back, for ``d > capacity - 1`` the samples ``capacity - 3 ..
  capacity`` back. It stays exact for cubics and at whole samples, only off-centre (error
  constant 1 / 24 instead of 3 / 128 in those outermost intervals). A buffer of capacity 1
  or 2 has only 2 or 3 samples: the read is then Lagrange on all of them (linear,
  quadratic).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import checks

INTERPOLATIONS = ("nearest", "linear", "cubic")
WHOLE_SAMPLE_RTOL = 1e-6  # d within this (relative) of an integer is a whole number of samples (float32 round-off)
_CUBIC_POINTS = 4  # nodes of the Lagrange stencil


class DelayState(NamedTuple):
    """Ring buffer of past samples.

    Attributes:
      buffer: [capacity + 1, n] past samples; slot ``head - 1`` (mod size) is the newest.
        A batch of lines shares the slots: ``[capacity + 1, n, B]``, one contiguous row of
        the batch per slot.
      head: shape () int32, the slot the next sample is written to (shared by a batch).
    """

    buffer: jax.Array
    head: jax.Array


def whole_samples(d: ArrayLike) -> ArrayLike:
    """Whether a delay of ``d`` samples is a whole number of them, to ``WHOLE_SAMPLE_RTOL``:
    a Python or NumPy bool for a concrete ``d`` (reckoned in float64), a traced one otherwise."""
    xp = np if isinstance(d, (int, float, np.number, np.ndarray)) else jnp
    return xp.abs(d - xp.round(d)) <= WHOLE_SAMPLE_RTOL * xp.maximum(1.0, d)


MAX_CAPACITY = 1_000_000
"""The longest delay buffer, in samples (1000 s at 1 kHz): a larger one asked for terabytes
and failed in the allocator, naming nothing."""


def check_capacity(capacity: int) -> int:
    """The capacity sets an array shape, so it must be an integer >= 1 (returned as an int)."""
    return checks.integer("capacity", capacity, unit="samples", high=MAX_CAPACITY)


def delay_init(y0: ArrayLike, capacity: int) -> DelayState:
    """A delay line whose whole history equals ``y0`` [n] (or a batch of lines, ``y0``
    [n, B]: every sample pushed and read is then [n, B])."""
    capacity = check_capacity(capacity)
    y0 = jnp.asarray(y0)
    if y0.ndim not in (1, 2):
        raise ValueError(f"y0 must have shape (n,), or (n, B) for a batch of lines; got {y0.shape}")
    buffer = jnp.broadcast_to(y0[None], (capacity + 1,) + y0.shape)
    return DelayState(buffer, jnp.zeros((), jnp.int32))


def delay_push(state: DelayState, y: jax.Array) -> DelayState:
    """Write the newest sample ``y`` [n] ([n, B] for a batch of lines)."""
    if jnp.shape(y) != state.buffer.shape[1:]:
        raise ValueError(f"y must have shape {state.buffer.shape[1:]} (one value per channel of the line); got {jnp.shape(y)}")
    size = state.buffer.shape[0]
    buffer = state.buffer.at[state.head].set(y)
    return DelayState(buffer, (state.head + 1) % size)


def delay_read(state: DelayState, delay_steps: ArrayLike, interpolation: str = "nearest") -> jax.Array:
    """The sample ``delay_steps`` before the newest one, [n] ([n, B] for a batch of lines).

    Args:
      state: the delay line after the current sample was pushed.
      delay_steps: delay in samples, in [0, capacity]; may be traced. Values outside are
        clipped to that range (check them where they are concrete: ``DFS.check``).
      interpolation: ``"nearest"``, ``"linear"`` or ``"cubic"`` (see the module docstring).

    Raises:
      ValueError: for another ``interpolation``.
    """
    size = state.buffer.shape[0]
    # Clamped by selection, not min/max: at d = capacity (and 0), where min/max would split
    # the gradient between their tied arguments, the read keeps its full one-sided derivative.
    d = jnp.asarray(delay_steps, state.buffer.dtype)
    d = jnp.where(d > size - 1, size - 1, jnp.where(d < 0, 0, d))
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
    if interpolation == "cubic":
        n_pts = min(_CUBIC_POINTS, size)  # static: a tiny buffer has fewer samples
        start = jnp.clip(jnp.floor(d) - 1, 0, size - n_pts)  # first node, clamped into the buffer
        t = d - start  # position in the stencil, in [0, n_pts - 1]; carries the gradient
        weights = []
        for i in range(n_pts):  # Lagrange basis on nodes 0..n_pts-1: exactly 0 or 1 at integer t
            w = jnp.ones_like(t)
            for j in range(n_pts):
                if j != i:
                    w = w * (t - j) / (i - j)
            weights.append(w)
        index = (newest - start.astype(jnp.int32) - jnp.arange(n_pts, dtype=jnp.int32)) % size
        return jnp.tensordot(jnp.stack(weights), state.buffer[index], axes=1)
    raise ValueError(f"interpolation must be one of {INTERPOLATIONS}; got {interpolation!r}")


def delay_step(state: DelayState, y: jax.Array, delay_steps: ArrayLike, interpolation: str = "nearest") -> tuple[DelayState, jax.Array]:
    """Push ``y`` and read the sample ``delay_steps`` back: a ``lax.scan`` body."""
    state = delay_push(state, y)
    return state, delay_read(state, delay_steps, interpolation)
