"""Time-domain metrics of a sampled response: settling time, peaks, ISE, IAE, effort, divergence.

Every function takes a signal ``s`` ``[T]`` or ``[T, n]`` (time first; ``[T, n]`` is
treated column by column and gives ``[n]`` results) sampled every ``dt`` seconds, uses
no Python control flow on values, and works under ``jit``, ``vmap`` and ``grad``
(``settling_time`` has zero gradient almost everywhere: it is piecewise constant).
Results keep the floating dtype of ``s``; ``dt`` is cast to it. Sizes and options that
set shapes (``final_fraction``, ``times_s``) are static Python values; ``dt`` and
``band`` may be traced, and are checked (finite, > 0) only when concrete.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import checks
from jaxflex.controllers.base import check_finite_scalar, is_concrete

DIVERGENCE_THRESHOLD = 1e6
"""Default bound on |x| above which ``diverged`` reports a run as diverged."""


ROUNDOFF_FLOOR_EPS = 16
"""Deviations below this many machine epsilons of max |s| always count as inside the settling band."""


def _as_signal(s: ArrayLike, name: str = "s") -> jax.Array:
    """``s`` as a floating ``[T]`` or ``[T, n]`` array (integers -> JAX's default float)."""
    if is_concrete(s):
        checks.real_array(name, s)  # a string or a bool array is refused by name, not by JAX's TypeError
    s = jnp.asarray(s)
    if s.ndim not in (1, 2) or s.shape[0] < 1:
        raise ValueError(f"{name} must have shape [T] or [T, n] with T >= 1 (time first); got shape {s.shape}")
    if not jnp.issubdtype(s.dtype, jnp.floating):
        s = s.astype(jnp.result_type(float))
    return s


def _as_dt(dt: ArrayLike, dtype: Any) -> jax.Array:
    """``dt`` (s) as a scalar of ``dtype``; checked a finite real number > 0 when concrete."""
    if is_concrete(dt):
        check_finite_scalar("dt", dt, positive=True, unit="s")
    elif jnp.ndim(dt) != 0:
        raise ValueError(f"dt must be a scalar (s); got shape {jnp.shape(dt)}")
    return jnp.asarray(dt, dtype)


def settling_time(s: ArrayLike, dt: ArrayLike, *, band: float = 0.02, final_fraction: float = 0.1) -> jax.Array:
    """Settling time (s): when ``s`` enters and stays in a band around its final value.

    Definition: the final value ``s_f`` is the mean of the last ``final_fraction`` of
    the record (``max(1, round(final_fraction * T))`` samples). The band half-width is
    ``band * max_t |s(t) - s_f|``. The settling time is the time of the first sample
    after which ``|s - s_f|`` stays within the band (``<=``) for the rest of the
    record: ``(k + 1) * dt`` with ``k`` the index of the last sample outside the band
    (sample 0 is at time 0). The band half-width is never below a roundoff floor of
    ``ROUNDOFF_FLOOR_EPS * eps * max_t |s(t)|`` (16 machine epsilons of the signal's
    scale), so a constant record is not judged by its roundoff. It is 0 when no sample
    is outside the band (a constant signal, or ``band >= 1``), and ``+inf`` when the last sample is outside the band
    (the record ends before the signal settles). Because the band is measured from
    ``s_f``, a decaying oscillation around a nonzero offset is handled correctly. A
    signal with a non-finite sample (a diverged run) has no settling time: NaN.

    Args:
      s: ``[T]`` or ``[T, n]`` signal (any unit), time first.
      dt: scalar sample spacing (s).
      band: band half-width as a fraction of the peak deviation from ``s_f``
        (default 2 %).
      final_fraction: static float in (0, 1], fraction of the record averaged for
        ``s_f``.

    Returns:
      scalar or ``[n]`` settling time (s), dtype of ``s``.
    """
    s = _as_signal(s)
    dt = _as_dt(dt, s.dtype)
    n_t = s.shape[0]
    if isinstance(final_fraction, (jax.core.Tracer, bool)) or not isinstance(final_fraction, (int, float, np.floating)):
        raise ValueError(f"final_fraction must be a static Python float in (0, 1]; got {final_fraction!r}")
    if not 0 < final_fraction <= 1:
        raise ValueError(f"final_fraction must be in (0, 1]; got {final_fraction}")
    if is_concrete(band):
        check_finite_scalar("band", band, positive=True)
    n_final = max(1, int(round(final_fraction * n_t)))
    return _settling_time(s, dt, jnp.asarray(band, s.dtype), n_final)


@partial(jax.jit, static_argnums=(3,))
def _settling_time(s: jax.Array, dt: jax.Array, band: jax.Array, n_final: int) -> jax.Array:
    # Jitted so eager calls compile once per shape instead of dispatching each op.
    n_t = s.shape[0]
    s_f = jnp.mean(s[n_t - n_final :], axis=0, keepdims=True)  # [1, (n)]
    dev = jnp.abs(s - s_f)  # [T, (n)]
    # Roundoff floor: s - s_f of a constant record is a few eps * |s|, not 0 (XLA's mean is
    # within ~4 eps); such deviations must count as inside the band.
    floor = ROUNDOFF_FLOOR_EPS * jnp.finfo(s.dtype).eps * jnp.max(jnp.abs(s), axis=0, keepdims=True)
    threshold = jnp.maximum(band * jnp.max(dev, axis=0, keepdims=True), floor)
    outside = dev > threshold  # [T, (n)]
    last_outside = (n_t - 1) - jnp.argmax(outside[::-1], axis=0)  # valid where any(outside)
    t_settle = jnp.where(jnp.any(outside, axis=0), (last_outside + 1).astype(s.dtype) * dt, jnp.zeros((), s.dtype))
    t_settle = jnp.where(outside[-1], jnp.asarray(jnp.inf, s.dtype), t_settle)
    return jnp.where(jnp.all(jnp.isfinite(s), axis=0), t_settle, jnp.asarray(jnp.nan, s.dtype))


def peaks(s: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """Smallest and largest value over time.

    Args:
      s: ``[T]`` or ``[T, n]`` signal, time first.

    Returns:
      ``(min, max)``, each scalar or ``[n]``, in the unit of ``s``.
    """
    s = _as_signal(s)
    return jnp.min(s, axis=0), jnp.max(s, axis=0)


def ise(s: ArrayLike, dt: ArrayLike) -> jax.Array:
    """Integral of squared signal, ``sum_t s(t)^2 * dt`` (rectangle rule).

    Args:
      s: ``[T]`` or ``[T, n]`` signal, time first.
      dt: scalar sample spacing (s).

    Returns:
      scalar or ``[n]``, unit of ``s`` squared times s.
    """
    s = _as_signal(s)
    return jnp.sum(s * s, axis=0) * _as_dt(dt, s.dtype)


def iae(s: ArrayLike, dt: ArrayLike) -> jax.Array:
    """Integral of absolute signal, ``sum_t |s(t)| * dt`` (rectangle rule).

    Args:
      s: ``[T]`` or ``[T, n]`` signal, time first.
      dt: scalar sample spacing (s).

    Returns:
      scalar or ``[n]``, unit of ``s`` times s.
    """
    s = _as_signal(s)
    return jnp.sum(jnp.abs(s), axis=0) * _as_dt(dt, s.dtype)


def control_effort(u: ArrayLike, dt: ArrayLike) -> jax.Array:
    """Control effort ``sum_t u(t)^2 * dt`` (rectangle rule).

    Args:
      u: ``[T]`` or ``[T, n_u]`` control input, time first (e.g. N*m).
      dt: scalar sample spacing (s).

    Returns:
      scalar or ``[n_u]``, e.g. N^2*m^2*s.
    """
    return ise(u, dt)


RUN_DIVERGED_DOC = (
    "the run blew up (a state non-finite or above 1e6) or its tip deflected by more than the arm's length, "
    "far outside the small-deflection model"
)
"""What ``run_diverged`` means, as montecarlo's summary.json and reproduce's results.json say."""


def run_diverged(blew_up: ArrayLike, peak_tip_m: ArrayLike, length_m: ArrayLike) -> jax.Array:
    """Whether a closed-loop run diverged, as the commands report it (``RUN_DIVERGED_DOC``).

    A growing loop can leave the model long before it blows up: one reached 27 km on a 1.2 m
    arm in 2 s with every state below 1e6, and was averaged into a Monte Carlo's statistics.

    Args:
      blew_up: ``diverged`` of the run's states (``RunMetrics.diverged`` of a streamed run).
      peak_tip_m: the run's peak |tip deflection| (m); NaN counts through ``blew_up``.
      length_m: the arm's length (m).

    Returns:
      bool, the broadcast shape of the arguments.

    Raises:
      ValueError: naming ``length_m`` when, concrete, it is not a finite number > 0 (a
        length of 0 or NaN called every run, or none, diverged), or a concrete ``blew_up``
        that is not boolean or ``peak_tip_m`` that is not real.
    """
    if is_concrete(length_m):
        check_finite_scalar("length_m", length_m, positive=True, unit="m")
    if is_concrete(blew_up) and np.asarray(blew_up).dtype.kind != "b":
        raise ValueError(f"blew_up must be a bool or an array of bools (RunMetrics.diverged); got {blew_up!r}")
    if is_concrete(peak_tip_m):
        checks.real_array("peak_tip_m", peak_tip_m)
    return jnp.logical_or(blew_up, jnp.asarray(peak_tip_m) > length_m)


def diverged(x: ArrayLike, threshold: ArrayLike = DIVERGENCE_THRESHOLD) -> jax.Array:
    """Whether a run blew up: any non-finite entry, or any ``|x| > threshold``.

    Reduces over every axis; ``vmap`` it for one flag per batch member.

    Args:
      x: array of any shape, e.g. a ``[T, n_x]`` state trajectory.
      threshold: bound on ``|x|`` (units of ``x``), a number > 0 (inf: non-finite entries
        only), default ``1e6``.

    Returns:
      scalar bool.
    """
    if is_concrete(threshold):
        arr = checks.real_array("threshold", threshold, scalar=True)
        if arr.ndim != 0 or not arr > 0:  # a bound <= 0 called every run diverged
            raise ValueError(f"threshold must be a number > 0 (a bound on |x|; inf for non-finite entries only); got {threshold!r}")
    if is_concrete(x):
        checks.real_array("x", x)  # a string was JAX's TypeError, naming no parameter
    x = jnp.asarray(x)
    return jnp.logical_or(~jnp.all(jnp.isfinite(x)), jnp.any(jnp.abs(x) > threshold))


class SignalMetrics(NamedTuple):
    """Metrics of one signal (each scalar for ``[T]``, ``[n]`` for ``[T, n]``).

    Attributes:
      min: smallest value (unit of the signal).
      max: largest value (unit of the signal).
      settling_time_s: settling time (s), as ``settling_time`` defines it.
      ise: ``sum s^2 dt`` (unit^2 * s).
      iae: ``sum |s| dt`` (unit * s).
    """

    min: jax.Array
    max: jax.Array
    settling_time_s: jax.Array
    ise: jax.Array
    iae: jax.Array


def signal_metrics(s: ArrayLike, dt: ArrayLike, *, band: float = 0.02, final_fraction: float = 0.1) -> SignalMetrics:
    """Peaks, settling time, ISE and IAE of ``s`` in one record.

    Args:
      s: ``[T]`` or ``[T, n]`` signal, time first.
      dt: scalar sample spacing (s).
      band: settling band as a fraction of the peak deviation (see ``settling_time``).
      final_fraction: static fraction of the record averaged for the final value.

    Returns:
      ``SignalMetrics``.
    """
    s = _as_signal(s)
    s_min, s_max = peaks(s)
    return SignalMetrics(
        min=s_min,
        max=s_max,
        settling_time_s=settling_time(s, dt, band=band, final_fraction=final_fraction),
        ise=ise(s, dt),
        iae=iae(s, dt),
    )


def samples_at(s: ArrayLike, dt: ArrayLike, times_s: Sequence[float]) -> jax.Array:
    """Values of ``s`` at the samples nearest to given times.

    Sample ``k`` is at time ``k * dt``; the index used for time ``t`` is
    ``floor(t / dt + 0.5)`` (round half up).

    Args:
      s: ``[T]`` or ``[T, n]`` signal, time first.
      dt: scalar sample spacing (s). When concrete, the indices are computed in NumPy
        and out-of-record times raise; when traced, out-of-record times give NaN.
      times_s: static sequence of ``K`` times (s).

    Returns:
      ``[K]`` or ``[K, n]`` values.

    Raises:
      ValueError: when (concrete ``dt``) a time's nearest index lies outside
        ``0 .. T-1``, i.e. the time is outside ``[-dt/2, (T - 1/2) dt)``.
    """
    s = _as_signal(s)
    n_t = s.shape[0]
    try:
        if isinstance(times_s, (str, bytes)) or any(isinstance(t, (str, bytes, bool)) for t in times_s):
            raise TypeError("not numbers")
        times = np.asarray([float(t) for t in times_s], dtype=np.float64)
    except (TypeError, jax.errors.ConcretizationTypeError) as err:
        raise ValueError(f"times_s must be a static sequence of floats (s); got {times_s!r}") from err
    dt_arr = _as_dt(dt, s.dtype)
    if is_concrete(dt):
        dt_val = float(dt)
        idx = np.floor(times / dt_val + 0.5).astype(np.int64)
        bad = (idx < 0) | (idx > n_t - 1)
        if np.any(bad):
            raise ValueError(
                f"times_s must lie in the record [0, {(n_t - 1) * dt_val:g}] s to within half a sample, "
                f"[{-dt_val / 2:g}, {(n_t - 0.5) * dt_val:g}) s (T = {n_t}, dt = {dt_val:g}); got {times[bad].tolist()}"
            )
        return s[idx]
    idx = jnp.floor(jnp.asarray(times, s.dtype) / dt_arr + 0.5).astype(jnp.int32)
    inside = (idx >= 0) & (idx <= n_t - 1)
    vals = s[jnp.clip(idx, 0, n_t - 1)]
    inside = inside.reshape(inside.shape + (1,) * (s.ndim - 1))
    return jnp.where(inside, vals, jnp.asarray(jnp.nan, s.dtype))
