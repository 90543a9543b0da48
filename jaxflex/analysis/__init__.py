"""Analysis of simulated responses: Welch PSD, dB vibration reduction at modes, time metrics.

Signals are time first: ``[T]`` or ``[T, n]`` (one column per channel), as ``lax.scan``
stacks them, unlike python-control's ``(n, T)`` and ``scipy.signal``'s default last
axis. Batches go in front (``[B, T, n]``) and are handled with ``jax.vmap``.
Everything here is pure ``jax.numpy``, works under ``jit``/``vmap``/``grad``, and
imports no plotting library.
"""

from jaxflex.analysis.metrics import (
    DIVERGENCE_THRESHOLD,
    ROUNDOFF_FLOOR_EPS,
    RUN_DIVERGED_DOC,
    SignalMetrics,
    control_effort,
    diverged,
    iae,
    ise,
    peaks,
    run_diverged,
    samples_at,
    settling_time,
    signal_metrics,
)
from jaxflex.analysis.psd import (
    DETRENDS,
    WINDOWS,
    PSDSettings,
    RegionReduction,
    band_mask,
    band_peak,
    get_window,
    region_reduction_db,
    vibration_reduction_db,
    welch,
)

__all__ = [
    "DETRENDS",
    "DIVERGENCE_THRESHOLD",
    "PSDSettings",
    "RegionReduction",
    "ROUNDOFF_FLOOR_EPS",
    "RUN_DIVERGED_DOC",
    "SignalMetrics",
    "WINDOWS",
    "band_mask",
    "band_peak",
    "control_effort",
    "diverged",
    "get_window",
    "region_reduction_db",
    "iae",
    "ise",
    "peaks",
    "run_diverged",
    "samples_at",
    "settling_time",
    "signal_metrics",
    "vibration_reduction_db",
    "welch",
]
