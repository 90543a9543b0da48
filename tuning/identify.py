"""The arm's modes from a measured free-vibration record: frequencies and damping ratios for
:func:`tuning.calibrate.calibrate`.

A record after the excitation has ended (a tap on the link, a released deflection, a torque
pulse that is over) is a sum of decaying modes in every channel: hub angle, tip deflection,
an accelerometer or a strain gauge. Sampled every ``dt``, channel ``c`` is
``y_c[t] = sum_k a_kc z_k^t`` with one pole ``z_k = exp(s_k dt)`` per mode and conjugate, and
``s = -zeta w +- i w sqrt(1 - zeta^2)``: ``w / 2 pi`` the undamped natural frequency (Hz) that
:func:`jaxflex.beam.natural_frequencies_hz` computes, ``zeta`` the damping ratio. With the hub
free the rigid mode adds a constant and a ramp (a double pole at ``z = 1``).

The poles are found by the shift invariance of the record's Hankel matrix (ESPRIT, the
matrix pencil method): its columns, ``[y[t], y[t + 1], ..., y[t + L]]``, span the space of the
vectors ``[1, z_k, ..., z_k^L]``; an SVD gives a basis ``U`` of the ``r`` strongest
directions, and the eigenvalues of ``pinv(U[:-1]) U[1:]`` are the poles. Channels share the
poles, so their Hankel matrices are stacked side by side (each scaled to unit RMS about its
straight-line trend). The
amplitudes ``a`` follow by linear least squares, and the reconstruction's residual says how
well the record is a sum of ``r`` decaying modes.

``r = 2 (n + EXTRA_MODES) + 2``: the ``n`` modes asked for and ``EXTRA_MODES`` more (a real
arm's higher modes, which would otherwise bias the lower ones), each with its conjugate, and
room for the rigid mode's constant and ramp. Real poles and poles with less than one cycle in
the window (the rigid mode, drift, offsets) are set aside, and so are modes no stronger than
``NOISE_FACTOR`` times the noise (what the model leaves of the record) in every channel, or no
longer so a period after their peak (poles fitted to round-off, gone within a sample or two);
of the rest, the ``n`` lowest are the modes. A record that rises in the window is reported
(``RISE_FACTOR``): a free decay does not grow, and a window that starts before the response (at
rest, or in the excitation) is fitted with spurious modes and little residual. Without noise, and
with no more modes in the record than fitted, the poles are exact; with noise, their error
shrinks as the record lengthens, while its lags (at most ``MAX_ROWS``) span a period or more of each mode (see ``lag_span_s``).

Modes above the Nyquist frequency ``1 / (2 dt)`` fold back onto lower frequencies: sample at
several times the highest mode that the record holds.
"""

from __future__ import annotations

import math
import os
from typing import Any, NamedTuple

import numpy as np
from threadpoolctl import threadpool_limits

from jaxflex import checks, fileio

MAX_ROWS = 400
"""The Hankel matrix's lags span at most this many samples (it has one row more; ``N // 3``
samples below that, so ``lag_span_s`` is at most ``MAX_ROWS dt``). More rows cost
time in the QR and gain little: on a record of 3000 samples with 1 % noise, 1000 rows gave
the same frequency and damping errors as 400, within the spread of five noise seeds, in 4x the
time."""
QR_BLOCK = 4096
"""Rows of the Hankel matrix's transpose per QR step."""
EXTRA_MODES = 4
"""Modes fitted beyond those asked for: a real arm's record holds its higher modes too, and a
model without them shifts the lower ones (the paper's arm simulated with 8 modes, asked for 2
with none extra: mode 3 taken for mode 2; for 3, mode 2's damping ratio 9-27 % off)."""
NOISE_FACTOR = 3.0
"""A mode counts when its RMS in some channel is above this many times what the model leaves
of that channel (the noise), or of ``MIN_RMS`` (round-off) on a noise-free record, and so is
its envelope there one period after its peak."""
MIN_RMS = 1e-6
"""The noise floor of a noise-free record, as a fraction of each channel's RMS."""
RISE_BLOCK = 16
"""The fewest samples ``RISE_FACTOR`` compares the RMS over: over a quarter period of a fast
mode 1 (2 samples at 100 Hz and 1 kHz), a channel of noise alone rose over 5x from a quiet first
block in 1 record of 20; over 16 samples its mean square varies as chi^2 with 16 degrees of
freedom, and a 5x rise over 375 to 6250 blocks has a chance of 1e-6 to 5e-6."""

RISE_FACTOR = 5.0
"""A window whose RMS over a later quarter period of mode 1 (``RISE_BLOCK`` samples at least),
in some channel (about its straight-line trend), is above this many times that over its first
quarter period is reported (``Modes.rise``; the CLI prints a note): a free decay does not grow,
and a window that starts before the response (at rest, or in the excitation) is fitted with a
spurious, heavily damped mode and a small residual (modes at 4.1 and 19 Hz tapped at 0.2 s,
from 0.1 s: a mode at 11.7 Hz with a damping ratio of 0.41, 0.5 % left unexplained, and the
19 Hz mode lost). That record (``tests/test_identify.py``) rises 32x from its start, 27x from
0.1 s, 16x from 40 ms before the tap, 2.8x from 20 ms before it and 1.03x from its end. It is a
note, not a refusal: a genuine free decay rises too where its modes nearly cancel over the
first block, and not only close modes that beat. The README's tap record (modes at 13.3 and
35.1 Hz) rises 5.8-13x in its hub angle from 4 % of the start times after the pulse, and the
hub angle after an impulse up to 24x; no factor separates the two. A free hub's angle, at rest
and then drifting, is no straight line to measure a rise about: the tip's deflection, or a
strain gauge, shows it."""
GRID_RTOL = 0.5
"""Sample times may stray from a uniform grid by this fraction of the sample time: each is still
nearest its own sample, as times written with few decimals are (1024 Hz to 4 decimals: 0.26)."""


class Modes(NamedTuple):
    """The modes found in a record (:func:`identify_modes`).

    Attributes:
      frequencies_hz: [n] undamped natural frequencies (Hz), ascending.
      damping: [n] damping ratios, each in (0, 1).
      rms: [n, n_ch] each mode's RMS over the window in each channel (the channel's units).
      dt: the sample time (s).
      start_s, end_s: the window of the record used (s, the record's clock).
      residual: the RMS of the record minus its model, as a fraction of the RMS of the
        model's oscillating part (offset and drift left out), over all channels (each scaled
        to unit RMS about its trend): near 0 for a clean free decay.
      reconstruction: [N, n_ch] the record's model over the window, from every pole found
        (the rigid mode's, and the higher modes', included).
      order: the number of poles fitted.
      lag_span_s: the time the Hankel matrix's lags span (s). Shorter than a period of a
        mode, that mode is poorly resolved: the record is sampled much faster than it needs.
      rise: the window's largest rise, when above ``RISE_FACTOR``: ``(factor, channel (0-based),
        onset_s, peak_s)``; None for a window that does not rise so (a free decay).
    """

    frequencies_hz: np.ndarray
    damping: np.ndarray
    rms: np.ndarray
    dt: float
    start_s: float
    end_s: float
    residual: float
    reconstruction: np.ndarray
    order: int
    lag_span_s: float
    rise: tuple[float, int, float, float] | None = None

    @property
    def times(self) -> np.ndarray:
        """[N] the sample times of the window (s)."""
        return self.start_s + self.dt * np.arange(self.reconstruction.shape[0])

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers for JSON."""
        return {
            "frequencies_hz": self.frequencies_hz.tolist(),
            "damping": self.damping.tolist(),
            "rms": self.rms.tolist(),
            "dt": self.dt,
            "start_s": self.start_s,
            "end_s": self.end_s,
            "residual": self.residual,
            "order": self.order,
            "lag_span_s": self.lag_span_s,
            "rise": None if self.rise is None else dict(zip(("factor", "channel", "onset_s", "peak_s"), self.rise)),
        }


def read_record(path: str | os.PathLike, option: str = "path") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A record from a comma-separated file: time (s) in the first column, one channel per
    further column; an optional first line of column names; ``#`` starts a comment.

    Returns:
      ``(t [N], y [N, n_ch], names)``: names from the header line, else ``channel 1``, ...

    Raises:
      ValueError: naming ``option`` (the CLI passes ``"--record"``) for a file that is missing or
        not such a table.
    """
    path = fileio.check_path(option, path)
    try:
        with open(path, encoding="utf-8-sig") as f:  # -sig: a byte-order mark is no part of the first cell
            lines = [line.split("#", 1)[0].strip() for line in f]
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{option}: cannot read {os.fspath(path)!r}: {err}") from None
    # a trailing comma (spreadsheet exports) leaves an empty last cell: not a column
    rows = [(i + 1, _cells(line)) for i, line in enumerate(lines) if line]
    if not rows:
        raise ValueError(f"{option}: {os.fspath(path)!r} holds no rows")
    names, header = None, ""
    if any(_number(cell) is None for cell in rows[0][1]):
        (first, names), rows = rows[0], rows[1:]
        header = f" as the header line {first} has (its names may hold no comma: quotes are not read)"
    width = len(names) if names is not None else len(rows[0][1])
    if width < 2:
        raise ValueError(f"{option}: {os.fspath(path)!r} must have a time column (s) and at least one channel, comma-separated")
    values = []
    for number, cells in rows:
        if len(cells) != width:
            raise ValueError(f"{option}: line {number} of {os.fspath(path)!r}: {len(cells)} columns, not {width}{header}")
        row = [_number(cell) for cell in cells]
        bad = [cell for cell, value in zip(cells, row) if value is None or not math.isfinite(value)]
        if bad:
            mark = " (the file must be comma-separated with '.' for decimals: a ';'-separated export with decimal commas is not read)" if ";" in bad[0] else ""
            raise ValueError(f"{option}: line {number} of {os.fspath(path)!r}: {bad[0]!r} is not a finite number{mark}")
        values.append(row)
    if not values:
        raise ValueError(f"{option}: {os.fspath(path)!r} holds no rows of numbers")
    table = np.asarray(values, np.float64)
    names = list(names[1:]) if names is not None else [f"channel {c}" for c in range(1, width)]
    return table[:, 0], table[:, 1:], names


def _cells(line: str) -> list[str]:
    cells = [cell.strip() for cell in line.split(",")]
    return cells[:-1] if len(cells) > 1 and not cells[-1] else cells


def _number(cell: str) -> float | None:
    """The cell's number, or None when it is not one."""
    try:
        return float(cell)
    except ValueError:
        return None


# BLAS on one thread: the factorisations are too small to share, and NumPy's default two
# threads contended (a 100,000-sample record took 11 to 80 s to identify on a 2-core machine,
# against 3 s on one thread). The caller's setting is back on return.
@threadpool_limits.wrap(limits=1, user_api="blas")
def identify_modes(t: Any, y: Any, n_modes: int = 2, *, start_s: float | None = None, end_s: float | None = None) -> Modes:
    """The ``n_modes`` lowest modes above the noise of a free-vibration record.

    Args:
      t: [N] sample times (s), uniform.
      y: [N] or [N, n_ch] the record, one column per channel (any units).
      n_modes: the number of flexible modes to find, >= 1.
      start_s, end_s: the window of ``t`` to use (default: all of it; ``start_s`` within the
        record, an ``end_s`` past it cut to it). Start after the excitation has ended: before
        that, the record is not a free decay.

    Raises:
      ValueError: naming the argument for a record that is not finite, uniformly sampled, or
        long enough for ``n_modes``, or a window outside it; and when fewer than ``n_modes``
        modes stand above the noise, or one of them does not decay (not a free decay).
    """
    n_modes = checks.integer("n_modes", n_modes, high=100)
    t = checks.real_array("t", t).astype(np.float64)
    y = checks.real_array("y", y).astype(np.float64)
    y = y[:, None] if y.ndim == 1 else y
    if t.ndim != 1 or y.ndim != 2 or y.shape[0] != t.shape[0]:
        raise ValueError(f"t must be [N] and y [N] or [N, channels] with the same N; got shapes {t.shape} and {y.shape}")
    if t.size < 2 or y.shape[1] == 0:
        raise ValueError(f"the record must hold at least 2 samples of at least 1 channel; got t of shape {t.shape} and y of shape {y.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("the record must be finite: it holds NaN or infinite values")
    if np.any(np.diff(t) <= 0):
        raise ValueError("t must be strictly ascending (s)")
    lo = t[0] if start_s is None else _time("start_s", start_s)
    hi = t[-1] if end_s is None else _time("end_s", end_s)
    # an end past the record is cut to it; a start outside it is refused (a start in seconds
    # from the tap on a record of Unix times took the whole record, rest and tap included)
    if start_s is not None and not t[0] <= lo < t[-1]:
        raise ValueError(f"start_s must be within the record, from its first sample at {t[0]:.15g} s to before its last at {t[-1]:.15g} s "
                         f"(t's clock); got {lo:.15g} s")
    if end_s is not None and hi <= t[0]:
        raise ValueError(f"end_s must be after the record's first sample, at {t[0]:.10g} s (t's clock); got {hi:.10g} s")
    if hi <= lo:  # both given: a bound left out is the record's end, which the checks above keep apart from the other
        raise ValueError(f"end_s must be after start_s; got start_s = {lo:g} s, end_s = {hi:g} s")
    window = (t >= lo) & (t <= hi)
    t, y = t[window], y[window]
    order = 2 * (n_modes + EXTRA_MODES) + 2
    needed = 3 * (order + 1)  # lags (N / 3) above the order
    if t.size < needed:
        raise ValueError(f"the window {lo:g}-{hi:g} s holds {t.size} samples; {n_modes} modes need at least {needed} (a wider window or a longer record)")
    # the grid that fits the times best: rounding of the times written averages out
    steps = np.arange(t.size)
    t0, dt = np.polynomial.polynomial.polyfit(steps, t, 1)
    if np.max(np.abs(t - (t0 + dt * steps))) > GRID_RTOL * dt:
        raise ValueError(f"t must be uniformly sampled (within {GRID_RTOL:g} of a sample time, which allows for rounding); resample the record first")
    # each channel scaled to unit RMS about its straight-line trend: an offset or a drift says
    # nothing of how strong the modes are
    trend = np.polynomial.polynomial.polyfit(steps, y, 1)
    centred = y - trend[0] - np.outer(steps, trend[1])
    scale = np.sqrt(np.mean(centred**2, axis=0))
    flat = np.flatnonzero(scale <= 1e-12 * np.max(np.abs(y), axis=0))  # round-off about the line
    if flat.size:
        raise ValueError(f"channel(s) {(flat + 1).tolist()} of y are constant or a straight line throughout the window")
    poles, amplitudes, basis, lags = _poles(y / scale, order)
    model = np.real(basis @ amplitudes)  # of y / scale
    noise = np.sqrt(np.mean((model - y / scale) ** 2, axis=0))  # [n_ch]
    # (f Re w)^2 averages f^2 (|w|^2 + Re w^2) / 2: f = 2 for a pole and its conjugate, 1 for a real pole
    factor = np.where(poles.imag != 0, 2.0, 1.0)[:, None]
    rms = factor * np.sqrt(np.maximum(np.abs(amplitudes) ** 2 * np.mean(np.abs(basis) ** 2, axis=0)[:, None] + np.real(amplitudes**2 * np.mean(basis**2, axis=0)[:, None]), 0.0) / 2)
    with np.errstate(divide="ignore"):  # a pole at 0 (noise) is no mode
        s = np.log(poles) / dt
    # one of each conjugate pair (real poles, negative ones included, are not modes), with a
    # cycle or more in the window
    oscillating = (poles.imag > 0) & (s.imag * (t[-1] - t[0]) > 2 * np.pi)
    modes = 2 * np.real(basis[:, oscillating] @ amplitudes[oscillating])
    residual = float(np.sqrt(np.mean(noise**2) / np.mean(modes**2))) if np.any(oscillating) else math.inf
    # above the noise in some channel (what is left of the record, or round-off), and still
    # above it there a period after its peak (each basis column peaks at 1): a pole fitted to
    # round-off can be as strong but gone within a sample or two (a damping ratio near 1),
    # which is no vibration
    floor = NOISE_FACTOR * np.maximum(noise, MIN_RMS)
    with np.errstate(divide="ignore", invalid="ignore"):
        period_later = factor * np.abs(amplitudes) * np.exp(-2 * np.pi * np.abs(s.real) / np.abs(s.imag))[:, None]
    found = np.flatnonzero(oscillating & np.any((rms > floor) & (period_later > floor), axis=1))
    found = found[np.argsort(np.abs(s[found]))]
    if found.size < n_modes:
        shown = f" ({', '.join(f'{abs(f) / (2 * np.pi):.4g} Hz' for f in s[found])})" if found.size else ""
        raise ValueError(f"found {found.size} mode(s) above the noise in the window{shown}, not the {n_modes} asked for: ask for fewer, or give a longer window of a free decay")
    kept = found[:n_modes]  # the lowest
    omega = np.abs(s[kept])
    damping = -s[kept].real / omega
    if np.any(damping <= 0):
        growing = ", ".join(f"{w / (2 * np.pi):.4g} Hz" for w, z in zip(omega, damping) if z <= 0)
        raise ValueError(f"the mode(s) at {growing} do not decay in the window: it must be a free decay, after the excitation has ended (start_s)")
    rise = _rise(t, centred, omega[0] / (2 * np.pi), dt)
    return Modes(omega / (2 * np.pi), damping, rms[kept] * scale, float(dt), float(t[0]), float(t[-1]), residual, model * scale, order, (lags - 1) * float(dt), rise)


def _rise(t: np.ndarray, centred: np.ndarray, mode_1_hz: float, dt: float) -> tuple[float, int, float, float] | None:
    """The largest rise of a channel's RMS over blocks of a quarter period of mode 1 from its
    first block, when above ``RISE_FACTOR``: ``(factor, channel, onset_s, peak_s)``. ``centred``
    [N, n_ch]: each channel about its straight-line trend (the rigid mode's drift taken out)."""
    # a quarter period of mode 1, and at least RISE_BLOCK samples: a channel of noise alone had
    # a first block of 2 samples 7x quieter than its loudest (mode 1 at 100 Hz, 1 kHz)
    block = max(RISE_BLOCK, round(0.25 / (mode_1_hz * dt)))
    n_blocks = centred.shape[0] // block
    rms = np.sqrt(np.mean(centred[: n_blocks * block].reshape(n_blocks, block, -1) ** 2, axis=1))  # [n_blocks, n_ch]
    rising = np.flatnonzero(rms.max(axis=0) > RISE_FACTOR * rms[0])
    if not rising.size:
        return None
    with np.errstate(divide="ignore"):  # a first block at exact rest
        rise = rms.max(axis=0)[rising] / rms[0, rising]
    worst = int(rising[np.argmax(rise)])
    onset = float(t[block * np.argmax(rms[:, worst] > RISE_FACTOR * rms[0, worst])])
    return float(rise.max()), worst, onset, float(t[np.argmax(np.abs(centred[:, worst]))])


def _time(name: str, value: Any) -> float:
    """``value`` as a finite number (checks.number, with no bound), refused as a time."""
    try:
        return checks.number(name, value, -math.inf)
    except ValueError:
        raise ValueError(f"{name} must be a finite time (s); got {value!r}") from None


def _poles(y: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """ESPRIT on the channels of ``y`` [N, n_ch]: ``order`` poles ``z``, their amplitudes
    [order, n_ch], the basis ``z^t`` [N, order] they multiply (each column divided by its
    largest magnitude, so that a growing pole does not overflow over a long window), and the
    number of lags."""
    n = y.shape[0]
    lags = min(n // 3, MAX_ROWS) + 1
    # The Hankel matrix H = R^T Q^T has the left singular vectors of R^T: R from a QR of H^T
    # (a window of each channel per row) taken block by block, so memory stays O(lags^2)
    # however long the record (100,000 samples of 2 channels: 3 s on one core).
    r = np.zeros((0, lags))
    for c in range(y.shape[1]):
        windows = np.lib.stride_tricks.sliding_window_view(y[:, c], lags)
        for first in range(0, windows.shape[0], QR_BLOCK):
            r = np.linalg.qr(np.concatenate([r, windows[first : first + QR_BLOCK]]), mode="r")
    u = np.linalg.svd(r.T)[0][:, :order]
    poles = np.linalg.eigvals(np.linalg.lstsq(u[:-1], u[1:], rcond=None)[0]).astype(np.complex128)
    magnitude = np.abs(poles)
    steps = np.arange(n)[:, None]
    growing = magnitude > 1
    basis = np.empty((n, order), np.complex128)
    basis[:, ~growing] = poles[~growing] ** steps
    basis[:, growing] = (poles[growing] / magnitude[growing]) ** steps * magnitude[growing] ** (steps - (n - 1))
    amplitudes = np.linalg.lstsq(basis, y.astype(np.complex128), rcond=None)[0]
    return poles, amplitudes, basis, lags
