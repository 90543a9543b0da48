"""Welch power spectral density in ``jax.numpy`` and the dB vibration reduction at modes.

Time is axis 0: a signal is ``[T]`` or ``[T, n]`` (one PSD per column), unlike
python-control and ``scipy.signal``, which default to the last axis.

``welch`` computes what ``scipy.signal.welch(x, fs, window=..., nperseg=...,
noverlap=..., detrend=..., scaling='density', return_onesided=True,
average='mean', axis=0)`` computes for real ``x`` (``nfft = nperseg``, no boundary
extension, no padding: trailing samples that do not fill a segment are dropped).
It is pure ``jnp`` (segments by a static gather, ``rfft``), so it works under
``jit``, ``vmap`` and ``grad``. Segment length, overlap, window and detrend are
static Python values; ``x`` and ``fs`` may be traced.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, NamedTuple, Union

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import checks
from jaxflex.controllers.base import check_finite_scalar, is_concrete

WINDOWS = ("hann", "hamming", "blackman", "boxcar")
"""Accepted window names (scipy's periodic, ``sym=False``, definitions)."""

DETRENDS = ("constant", "linear", None, False)
"""Accepted ``detrend`` values; ``None`` and ``False`` both mean no detrending."""

# Cosine-sum coefficients a_k of w[n] = sum_k (-1)^k a_k cos(2 pi k n / N), n = 0..N-1,
# N = nperseg (periodic window), as scipy.signal.windows.general_cosine defines them.
_COSINE_COEFFS = {
    "hann": (0.5, 0.5),
    "hamming": (0.54, 0.46),
    "blackman": (0.42, 0.50, 0.08),
    "boxcar": (1.0,),
}

Detrend = Union[str, None, bool]


@dataclasses.dataclass(frozen=True)
class PSDSettings:
    """Static settings of the Welch estimator (a hashable record, not an array pytree).

    Its fields are Python strings and ints, so pass it by closure or as a static
    argument to ``jax.jit``, never as a traced argument.

    Attributes:
      window: one of ``WINDOWS``: "hann", "hamming", "blackman", "boxcar".
      nperseg: samples per segment, ``1 <= nperseg <= T`` (``T`` is checked by ``welch``).
      noverlap: samples shared by consecutive segments, ``0 <= noverlap < nperseg``;
        ``None`` means ``nperseg // 2``.
      detrend: "constant" (remove each segment's mean), "linear" (remove each
        segment's least-squares line), or ``None``/``False`` (none).

    Raises:
      ValueError: naming the field and its accepted range, when built (``nperseg = 0`` was
        kept, to fail only in ``welch``).
    """

    window: str = "hann"
    nperseg: int = 256
    noverlap: int | None = None
    detrend: Detrend = "constant"

    def __post_init__(self) -> None:
        _check_window_and_detrend(self.window, self.detrend)
        nperseg = checks.integer("nperseg", self.nperseg)
        object.__setattr__(self, "nperseg", nperseg)
        if self.noverlap is not None:
            object.__setattr__(self, "noverlap", checks.integer(f"noverlap (None, or below nperseg = {nperseg})", self.noverlap, low=0, high=nperseg - 1))

    def resolved_noverlap(self) -> int:
        """The overlap actually used: ``noverlap``, or ``nperseg // 2`` when ``None``."""
        return self.nperseg // 2 if self.noverlap is None else self.noverlap

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description of the estimator, for reports.

        ``noverlap`` is resolved to the integer used, ``detrend`` is ``None`` when off,
        and the fixed choices (density scaling, one-sided, mean over segments,
        ``nfft = nperseg``) are stated too.
        """
        return {
            "estimator": "welch",
            "window": self.window,
            "nperseg": int(self.nperseg),
            "noverlap": int(self.resolved_noverlap()),
            "detrend": self.detrend if self.detrend else None,
            "nfft": int(self.nperseg),
            "scaling": "density",
            "onesided": True,
            "average": "mean",
        }


def _float_dtype(x: jax.Array) -> Any:
    """x's dtype if floating, else JAX's default float (float64 under x64)."""
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError("welch takes a real signal x; got a complex dtype " f"{x.dtype}")
    if jnp.issubdtype(x.dtype, jnp.floating):
        return x.dtype
    return jnp.result_type(float)


def get_window(window: str, nperseg: int, dtype: Any = None) -> jax.Array:
    """Periodic window of length ``nperseg``, as ``scipy.signal.get_window(window, nperseg)``.

    Args:
      window: one of ``WINDOWS``.
      nperseg: window length (static int >= 1). A length-1 window is ``[1]``, as in scipy.
      dtype: floating dtype of the result; JAX's default float when ``None``.

    Returns:
      ``[nperseg]`` window: ``sum_k (-1)^k a_k cos(2 pi k n / nperseg)``, ``n = 0..nperseg-1``,
      with ``a = (0.5, 0.5)`` (hann), ``(0.54, 0.46)`` (hamming), ``(0.42, 0.5, 0.08)``
      (blackman), ``(1,)`` (boxcar).

    Raises:
      ValueError: for an unknown window name or ``nperseg < 1``.
    """
    if not isinstance(window, str) or window not in _COSINE_COEFFS:
        raise ValueError(f"window must be one of {WINDOWS}; got {window!r}")
    nperseg = checks.integer("nperseg", nperseg)
    dtype = jnp.result_type(float) if dtype is None else checks.float_dtype("dtype", dtype)
    return _get_window(window, nperseg, dtype)


@partial(jax.jit, static_argnums=(0, 1, 2))
def _get_window(window: str, nperseg: int, dtype: Any) -> jax.Array:
    if nperseg == 1:
        return jnp.ones((1,), dtype)
    phase = 2.0 * np.pi * jnp.arange(nperseg, dtype=dtype) / nperseg
    w = jnp.zeros((nperseg,), dtype)
    for k, a_k in enumerate(_COSINE_COEFFS[window]):
        w = w + ((-1.0) ** k * a_k) * jnp.cos(k * phase)
    return w


def _check_window_and_detrend(window: Any, detrend: Any) -> None:
    if not (isinstance(window, str) and window in WINDOWS):
        raise ValueError(f"window must be one of {WINDOWS}; got {window!r}")
    if not (any(detrend is d for d in (None, False)) or (isinstance(detrend, str) and detrend in ("constant", "linear"))):
        raise ValueError(f"detrend must be one of 'constant', 'linear', None or False; got {detrend!r}")


def _validate(x_shape: tuple[int, ...], fs: Any, window: Any, nperseg: Any, noverlap: Any, detrend: Any) -> int:
    """Static checks (and fs when concrete); returns the resolved noverlap."""
    if len(x_shape) not in (1, 2):
        raise ValueError(f"x must have shape [T] or [T, n] (time first); got shape {x_shape}")
    n_t = x_shape[0]
    _check_window_and_detrend(window, detrend)
    if isinstance(nperseg, bool) or not isinstance(nperseg, (int, np.integer)):
        raise ValueError(f"nperseg must be a Python int with 1 <= nperseg <= T = {n_t}; got {nperseg!r}")
    if not 1 <= nperseg <= n_t:
        raise ValueError(f"nperseg must satisfy 1 <= nperseg <= T = {n_t}; got {nperseg}")
    if noverlap is None:
        noverlap = nperseg // 2
    if isinstance(noverlap, bool) or not isinstance(noverlap, (int, np.integer)):
        raise ValueError(f"noverlap must be a Python int with 0 <= noverlap < nperseg = {nperseg}; got {noverlap!r}")
    if not 0 <= noverlap < nperseg:
        raise ValueError(f"noverlap must satisfy 0 <= noverlap < nperseg = {nperseg}; got {noverlap}")
    if is_concrete(fs):
        check_finite_scalar("fs", fs, positive=True, unit="Hz")
    elif jnp.ndim(fs) != 0:
        raise ValueError(f"fs must be a scalar (Hz); got shape {jnp.shape(fs)}")
    return int(noverlap)


def _detrend_segments(segs: jax.Array, detrend: Detrend) -> jax.Array:
    """Detrend along axis 1 of ``segs`` [n_seg, nperseg, ...]."""
    if detrend is None or detrend is False:
        return segs
    segs = segs - jnp.mean(segs, axis=1, keepdims=True)
    if detrend == "constant":
        return segs
    # linear: least-squares line a + b t; with t centred and the mean removed, b = <t, x> / <t, t>.
    nperseg = segs.shape[1]
    t = jnp.arange(nperseg, dtype=segs.dtype) - (nperseg - 1) / 2.0
    t = t.reshape((1, nperseg) + (1,) * (segs.ndim - 2))
    tt = jnp.sum(t * t)
    tt_safe = jnp.where(tt > 0, tt, 1.0)  # nperseg == 1: the residual is already 0
    slope = jnp.sum(t * segs, axis=1, keepdims=True) / tt_safe
    return segs - slope * t


def welch(
    x: ArrayLike,
    fs: ArrayLike,
    *,
    window: str = "hann",
    nperseg: int = 256,
    noverlap: int | None = None,
    detrend: Detrend = "constant",
    settings: PSDSettings | None = None,
) -> tuple[jax.Array, jax.Array]:
    """One-sided Welch power spectral density, density scaling, mean over segments.

    Segments of ``nperseg`` samples start every ``nperseg - noverlap`` samples
    (``n_seg = (T - noverlap) // (nperseg - noverlap)``; leftover samples are dropped).
    Each segment is detrended, multiplied by the window ``w``, transformed with an
    ``rfft`` of length ``nperseg``, and ``|X|^2 / (fs * sum(w^2))`` is doubled at every
    bin but DC (and Nyquist when ``nperseg`` is even), then averaged over segments.
    Equal to ``scipy.signal.welch(x, fs, window, nperseg, noverlap, detrend=detrend,
    scaling='density', return_onesided=True, average='mean', axis=0)`` for real ``x``.

    Args:
      x: ``[T]`` or ``[T, n]`` real signal, time first (units of the signal, e.g. m).
      fs: scalar sampling frequency (Hz); may be traced. Checked finite and > 0 when
        concrete.
      window: "hann", "hamming", "blackman" or "boxcar" (periodic, as
        ``scipy.signal.get_window`` gives them).
      nperseg: static int, samples per segment, ``1 <= nperseg <= T``.
      noverlap: static int, ``0 <= noverlap < nperseg``; ``None`` means ``nperseg // 2``.
      detrend: "constant" (remove each segment's mean), "linear" (remove each
        segment's least-squares line) or ``None``/``False``.
      settings: a ``PSDSettings`` to use instead of the four keywords above; passing it
        together with any of them changed from its default raises ``ValueError``.

    Returns:
      ``(freqs, psd)``: ``freqs`` ``[F]`` (Hz), ``F = nperseg // 2 + 1``, bin ``k`` at
      ``k * fs / nperseg``; ``psd`` ``[F]`` or ``[F, n]`` (units^2/Hz). Floating dtype of
      ``x`` (JAX's default float for integer ``x``).

    Raises:
      ValueError: naming the parameter and its accepted range, for a bad shape of
        ``x``, ``nperseg``, ``noverlap``, ``window``, ``detrend``, or a concrete ``fs``
        that is not finite and > 0.
    """
    if settings is not None:
        checks.instance("settings", settings, PSDSettings, "build one with PSDSettings(window, nperseg, noverlap, detrend)")
        if (window, nperseg, noverlap, detrend) != ("hann", 256, None, "constant"):
            raise ValueError("pass either settings= or window/nperseg/noverlap/detrend keywords, not both")
        window, nperseg, noverlap, detrend = settings.window, settings.nperseg, settings.noverlap, settings.detrend
    if is_concrete(x):
        checks.real_array("x", x)  # a string is refused by name, not by JAX's TypeError
    x = jnp.asarray(x)
    noverlap = _validate(x.shape, fs, window, nperseg, noverlap, detrend)
    dtype = _float_dtype(x)
    detrend = None if detrend is False else detrend
    return _welch(
        x.astype(dtype), jnp.asarray(fs, dtype), window=window, nperseg=int(nperseg), noverlap=noverlap, detrend=detrend
    )


@partial(jax.jit, static_argnames=("window", "nperseg", "noverlap", "detrend"))
def _welch(
    x: jax.Array, fs: jax.Array, *, window: str, nperseg: int, noverlap: int, detrend: str | None
) -> tuple[jax.Array, jax.Array]:
    # Jitted like many jax.numpy functions, so eager calls compile once per static configuration
    # and shape instead of dispatching each op; inside an outer jit it is inlined.
    dtype = x.dtype
    n_t = x.shape[0]
    step = nperseg - noverlap
    n_seg = (n_t - noverlap) // step
    idx = np.arange(n_seg)[:, None] * step + np.arange(nperseg)[None, :]  # [n_seg, nperseg], static
    segs = _detrend_segments(x[idx], detrend)  # [n_seg, nperseg, (n)]
    w = _get_window(window, nperseg, dtype)
    segs = segs * w.reshape((1, nperseg) + (1,) * (x.ndim - 1))
    spec = jnp.fft.rfft(segs, n=nperseg, axis=1)  # [n_seg, F, (n)]
    power = jnp.real(spec) ** 2 + jnp.imag(spec) ** 2
    n_f = nperseg // 2 + 1
    onesided = np.full((n_f,), 2.0)
    onesided[0] = 1.0
    if nperseg % 2 == 0:
        onesided[-1] = 1.0
    scale = jnp.asarray(onesided, dtype) / (fs * jnp.sum(w * w))  # [F]
    psd = jnp.mean(power, axis=0) * scale.reshape((n_f,) + (1,) * (x.ndim - 1))
    freqs = jnp.arange(n_f, dtype=dtype) * (fs / nperseg)
    return freqs, psd


def _check_band(f0: ArrayLike | None, rel_band: Any) -> None:
    """A concrete centre ``f0`` (a scalar, finite and > 0, in Hz) and ``rel_band`` (finite and
    > 0), by name; traced ones pass."""
    if is_concrete(rel_band):
        check_finite_scalar("rel_band", rel_band, positive=True)
    if f0 is not None and is_concrete(f0):
        check_finite_scalar("f0", f0, positive=True, unit="Hz")


def _check_bins(name: str, values: ArrayLike) -> None:
    """A concrete ``values`` must be a non-empty 1-D real array ([F], by bin), by ``name``."""
    if is_concrete(values):
        arr = checks.real_array(name, values)
        if arr.ndim != 1 or arr.size == 0:
            raise ValueError(f"{name} must be a non-empty 1-D array, one value per frequency bin; got shape {arr.shape}")


def band_mask(freqs: ArrayLike, f0: ArrayLike, rel_band: float = 0.15) -> jax.Array:
    """Bins inside the band ``|f - f0| <= rel_band * f0``.

    Args:
      freqs: ``[F]`` bin frequencies (Hz).
      f0: scalar centre frequency (Hz).
      rel_band: half-width of the band as a fraction of ``f0``.

    Returns:
      ``[F]`` bool.
    """
    _check_band(f0, rel_band)
    _check_bins("freqs", freqs)
    freqs = jnp.asarray(freqs)
    f0 = jnp.asarray(f0)
    return jnp.abs(freqs - f0) <= rel_band * f0


def band_peak(freqs: ArrayLike, psd: ArrayLike, f0: ArrayLike, rel_band: float = 0.15) -> tuple[jax.Array, jax.Array]:
    """Bin where ``psd`` peaks within ``|f - f0| <= rel_band * f0``.

    Args:
      freqs: ``[F]`` bin frequencies (Hz).
      psd: ``[F]`` power spectral density (units^2/Hz).
      f0: scalar centre frequency (Hz), e.g. a natural frequency.
      rel_band: half-width of the search band as a fraction of ``f0``.

    Returns:
      ``(f_peak, index)``: the peak bin's frequency (Hz; NaN when no bin lies in the
      band) and its int index into ``freqs`` (0 when no bin lies in the band). Ties go
      to the lowest frequency.
    """
    _check_band(f0, rel_band)
    _check_bins("freqs", freqs)
    _check_bins("psd", psd)
    freqs = jnp.asarray(freqs)
    psd = jnp.asarray(psd)
    if freqs.ndim != 1 or psd.shape != freqs.shape:
        raise ValueError(f"freqs and psd must both have shape [F]; got {freqs.shape} and {psd.shape}")
    return _band_peak(freqs, psd, jnp.asarray(f0), rel_band)


@jax.jit
def _band_peak(freqs: jax.Array, psd: jax.Array, f0: jax.Array, rel_band: Any) -> tuple[jax.Array, jax.Array]:
    mask = band_mask(freqs, f0, rel_band)
    index = jnp.argmax(jnp.where(mask, psd, -jnp.inf))
    f_peak = jnp.where(jnp.any(mask), freqs[index], jnp.nan)
    return f_peak, index


def _reduction_inputs(freqs: ArrayLike, psd_open: ArrayLike, psd_closed: ArrayLike, mode_freqs_hz: ArrayLike, rel_band: Any):
    """The arrays of a reduction, checked by name (concrete ones; traced ones pass)."""
    for name, value in (("freqs", freqs), ("psd_open", psd_open), ("psd_closed", psd_closed)):
        if is_concrete(value):
            checks.real_array(name, value)
            if name != "freqs" and np.any(np.asarray(value) < 0):  # NaN (a diverged run) passes, and gives NaN
                raise ValueError(f"{name} must be a power spectral density, >= 0 (units^2/Hz); got a minimum of {np.nanmin(np.asarray(value)):g}")
    freqs = jnp.asarray(freqs)
    psd_open = jnp.asarray(psd_open)
    psd_closed = jnp.asarray(psd_closed)
    if psd_closed.shape != psd_open.shape:
        raise ValueError(
            f"psd_open and psd_closed must have the same shape [F]; got {psd_open.shape} and {psd_closed.shape}"
        )
    _check_band(None, rel_band)
    if is_concrete(mode_freqs_hz):
        checks.real_array("mode_freqs_hz", mode_freqs_hz)
    mode_freqs_hz = jnp.atleast_1d(jnp.asarray(mode_freqs_hz))
    if mode_freqs_hz.ndim != 1:
        raise ValueError(f"mode_freqs_hz must have shape [n_modes]; got {mode_freqs_hz.shape}")
    if is_concrete(mode_freqs_hz):
        mf = np.asarray(mode_freqs_hz)
        if not np.all(np.isfinite(mf) & (mf > 0)):
            raise ValueError(f"mode_freqs_hz must be finite and > 0 (Hz); got {mf}")
    if freqs.ndim != 1 or psd_open.shape != freqs.shape:
        raise ValueError(f"freqs and psd_open must both have shape [F]; got {freqs.shape} and {psd_open.shape}")
    return freqs, psd_open, psd_closed, mode_freqs_hz


def vibration_reduction_db(
    freqs: ArrayLike,
    psd_open: ArrayLike,
    psd_closed: ArrayLike,
    mode_freqs_hz: ArrayLike,
    rel_band: float = 0.15,
) -> jax.Array:
    """Level of vibration reduction at each natural frequency, in dB.

    Definition: for each modal frequency ``f_i``, take the bin ``k_i`` where the
    OPEN-loop PSD is largest among the bins with ``|f - f_i| <= rel_band * f_i``, and
    return ``10 * log10(psd_open[k_i] / psd_closed[k_i])``, both PSDs read at that
    same bin. Positive values mean the closed loop has less power there. Both PSDs
    must come from the same estimator settings (same ``freqs``). NaN when no bin lies
    in a band (with a gradient of exactly 0 there: a NaN entry adds nothing to a
    gradient, so a loss on it must check for NaN itself); +inf where ``psd_closed`` is 0
    at the bin.

    Args:
      freqs: ``[F]`` bin frequencies (Hz) shared by both PSDs.
      psd_open: ``[F]`` open-loop PSD (units^2/Hz).
      psd_closed: ``[F]`` closed-loop PSD (units^2/Hz).
      mode_freqs_hz: ``[n_modes]`` natural frequencies (Hz), or a scalar.
      rel_band: half-width of each search band as a fraction of its frequency.

    Returns:
      ``[n_modes]`` reduction (dB).
    """
    freqs, psd_open, psd_closed, mode_freqs_hz = _reduction_inputs(freqs, psd_open, psd_closed, mode_freqs_hz, rel_band)
    return _vibration_reduction_db(freqs, psd_open, psd_closed, mode_freqs_hz, rel_band)


@jax.jit
def _vibration_reduction_db(freqs, psd_open, psd_closed, mode_freqs_hz, rel_band):
    f_peak, index = jax.vmap(lambda f0: _band_peak(freqs, psd_open, f0, rel_band))(mode_freqs_hz)
    db = 10.0 * jnp.log10(psd_open[index] / psd_closed[index])
    return jnp.where(jnp.isnan(f_peak), jnp.nan, db)


class RegionReduction(NamedTuple):
    """``region_reduction_db``'s result, each ``[n_modes]``."""

    db: jax.Array
    """``10 * log10(open peak / closed highest)`` (dB)."""
    f_closed_hz: jax.Array
    """Frequency of the closed loop's highest bin in the region (Hz)."""
    is_peak: jax.Array
    """Whether that bin is a peak of the closed-loop PSD (above 0 and at least both its
    neighbours; never the spectrum's first or last bin), not the skirt of a peak outside the
    region, which reaches its highest at the region's edge."""


def region_reduction_db(
    freqs: ArrayLike,
    psd_open: ArrayLike,
    psd_closed: ArrayLike,
    mode_freqs_hz: ArrayLike,
    rel_band: float = 0.15,
) -> RegionReduction:
    """The least reduction over each mode's region, in dB, and where it falls.

    ``vibration_reduction_db`` reads both PSDs at the open loop's peak bin, as the paper
    defines its figure. A controller that moves a resonance (DFS moves the paper arm's first
    mode from 13.3 to about 17.6 Hz) leaves its new peak off that bin, and the reduction
    there overstates what the loop removed. Here the open loop's peak (taken as in
    ``vibration_reduction_db``) is set against the closed loop's highest PSD anywhere in
    the mode's region: from the geometric midpoint with the mode below to that with the mode
    above, and from ``f_1 / 2`` below the first mode and to ``2 f_n`` above the last.
    Where that highest bin is the skirt of a neighbouring mode's peak, its frequency sits at
    the region's edge.

    Args:
      freqs: ``[F]`` bin frequencies (Hz) shared by both PSDs.
      psd_open: ``[F]`` open-loop PSD (units^2/Hz).
      psd_closed: ``[F]`` closed-loop PSD (units^2/Hz).
      mode_freqs_hz: ``[n_modes]`` natural frequencies (Hz), strictly increasing.
      rel_band: half-width of the open loop's search band as a fraction of each frequency.

    Returns:
      ``RegionReduction(db, f_closed_hz, is_peak)``: NaN, NaN and False where no bin lies
      in a band or region, or a PSD there is NaN (a diverged run).

    Raises:
      ValueError: as ``vibration_reduction_db``, and for concrete ``mode_freqs_hz`` that
        are not strictly increasing.
    """
    freqs, psd_open, psd_closed, mode_freqs_hz = _reduction_inputs(freqs, psd_open, psd_closed, mode_freqs_hz, rel_band)
    if is_concrete(mode_freqs_hz) and np.any(np.diff(np.asarray(mode_freqs_hz)) <= 0):
        raise ValueError(f"mode_freqs_hz must be strictly increasing (Hz); got {np.asarray(mode_freqs_hz)}")
    return _region_reduction_db(freqs, psd_open, psd_closed, mode_freqs_hz, rel_band)


@jax.jit
def _region_reduction_db(freqs, psd_open, psd_closed, mode_freqs_hz, rel_band):
    f_open, open_index = jax.vmap(lambda f0: _band_peak(freqs, psd_open, f0, rel_band))(mode_freqs_hz)
    middles = jnp.sqrt(mode_freqs_hz[:-1] * mode_freqs_hz[1:])
    edges = jnp.concatenate([mode_freqs_hz[:1] / 2, middles, mode_freqs_hz[-1:] * 2])  # mode i's region: [edges[i], edges[i + 1])
    inside = (freqs[None, :] >= edges[:-1, None]) & (freqs[None, :] < edges[1:, None])  # [n_modes, F]
    closed_index = jnp.argmax(jnp.where(inside, psd_closed[None, :], -jnp.inf), axis=1)
    found = jnp.any(inside, axis=1) & ~jnp.isnan(f_open)
    db = 10.0 * jnp.log10(psd_open[open_index] / psd_closed[closed_index])
    found = found & ~jnp.isnan(db)  # a NaN PSD (a diverged run) in the band or the region: no frequency, no peak
    below = psd_closed[jnp.maximum(closed_index - 1, 0)]
    above = psd_closed[jnp.minimum(closed_index + 1, freqs.shape[0] - 1)]
    top = psd_closed[closed_index]
    is_peak = found & (closed_index > 0) & (closed_index < freqs.shape[0] - 1) & (top > 0) & (top >= below) & (top >= above)
    return RegionReduction(jnp.where(found, db, jnp.nan), jnp.where(found, freqs[closed_index], jnp.nan), is_peak)
