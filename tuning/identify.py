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
vectors ``[1, z_k, ..., z_k^L]``; the SVD gives a basis ``U`` of the ``r`` strongest
directions, and the eigenvalues of ``pinv(U[:-1]) U[1:]`` are the poles. Channels share the
poles, so their Hankel matrices are stacked side by side (each scaled to unit RMS). The
amplitudes ``a`` follow by linear least squares, and the reconstruction's residual says how
well the record is a sum of ``r`` decaying modes.

``r = 2 n + 2``: the ``n`` modes asked for with their conjugates, and room for the rigid mode's
constant and ramp. Real poles and poles with less than one cycle in the record (the rigid
mode, drift, offsets) are set aside; of the oscillating ones, the ``n`` with the most energy
in the record (RMS over the window, summed over channels) are the modes. Without noise the
poles are exact; with noise, their error shrinks as the record lengthens.

Modes above the Nyquist frequency ``1 / (2 dt)`` fold back onto lower frequencies: sample at
several times the highest mode that the record holds.
"""

from __future__ import annotations

import math
import os
from typing import Any, NamedTuple

import numpy as np

from jaxflex import checks

MAX_ROWS = 400
"""The Hankel matrix has at most this many rows (lags; ``N / 3`` below that). More rows cost
time in the QR and gain little: on a record of 3000 samples with 1 % noise, 1000 rows gave
the same frequency and damping errors as 400, within the spread of five noise seeds, in 4x the
time."""
QR_BLOCK = 4096
"""Rows of the Hankel matrix's transpose per QR step."""
MIN_RMS = 1e-6
"""An oscillating pole pair whose RMS over the window is below this fraction of the record's
(each channel scaled to unit RMS) is round-off, not a mode."""
GRID_RTOL = 0.05
"""Sample times may stray from a uniform grid by this fraction of the sample time (rounding)."""


class Modes(NamedTuple):
    """The modes found in a record (:func:`identify_modes`).

    Attributes:
      frequencies_hz: [n] undamped natural frequencies (Hz), ascending.
      damping: [n] damping ratios, each in (0, 1).
      rms: [n, n_ch] each mode's RMS over the window in each channel (the channel's units).
      dt: the sample time (s).
      start_s, end_s: the window of the record used (s, the record's clock).
      residual: the RMS of the record minus its reconstruction, as a fraction of the
        record's RMS, over all channels (each scaled to unit RMS): near 0 for a clean free
        decay.
      reconstruction: [N, n_ch] the record's model over the window, from every pole found
        (the rigid mode's included).
    """

    frequencies_hz: np.ndarray
    damping: np.ndarray
    rms: np.ndarray
    dt: float
    start_s: float
    end_s: float
    residual: float
    reconstruction: np.ndarray

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
        }


def read_record(path: str | os.PathLike, option: str = "--record") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A record from a comma-separated file: time (s) in the first column, one channel per
    further column; an optional first line of column names; ``#`` starts a comment.

    Returns:
      ``(t [N], y [N, n_ch], names)``: names from the header line, else ``channel 1``, ...

    Raises:
      ValueError: naming ``option`` for a file that is missing or not such a table.
    """
    try:
        with open(path, encoding="utf-8") as f:
            lines = [line.split("#", 1)[0].strip() for line in f]
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{option}: cannot read {os.fspath(path)!r}: {err}") from None
    rows = [(i + 1, [cell.strip() for cell in line.split(",")]) for i, line in enumerate(lines) if line]
    if not rows:
        raise ValueError(f"{option}: {os.fspath(path)!r} holds no rows")
    names = None
    try:
        [float(cell) for cell in rows[0][1]]
    except ValueError:
        (_, names), rows = rows[0], rows[1:]
    width = len(names) if names is not None else len(rows[0][1]) if rows else 0
    if width < 2:
        raise ValueError(f"{option}: {os.fspath(path)!r} must have a time column (s) and at least one channel, comma-separated")
    values = []
    for number, cells in rows:
        try:
            if len(cells) != width:
                raise ValueError(f"{len(cells)} columns, not {width}")
            values.append([float(cell) for cell in cells])
        except ValueError as err:
            raise ValueError(f"{option}: line {number} of {os.fspath(path)!r}: {err}") from None
    table = np.asarray(values, np.float64).reshape(-1, width)
    names = list(names[1:]) if names is not None else [f"channel {c}" for c in range(1, width)]
    return table[:, 0], table[:, 1:], names


def identify_modes(t: Any, y: Any, n_modes: int = 2, *, start_s: float | None = None, end_s: float | None = None) -> Modes:
    """The ``n_modes`` strongest oscillating modes of a free-vibration record.

    Args:
      t: [N] sample times (s), uniform.
      y: [N] or [N, n_ch] the record, one column per channel (any units).
      n_modes: the number of flexible modes to find, >= 1.
      start_s, end_s: the window of ``t`` to use (default: all of it). Start after the
        excitation has ended: before that, the record is not a free decay.

    Raises:
      ValueError: naming the argument for a record that is not finite, uniformly sampled, or
        long enough for ``n_modes``, or a window outside it; and when fewer than ``n_modes``
        oscillating modes are found, or one that does not decay (not a free decay).
    """
    n_modes = checks.integer("n_modes", n_modes, high=100)
    t = checks.real_array("t", t).astype(np.float64)
    y = checks.real_array("y", y).astype(np.float64)
    y = y[:, None] if y.ndim == 1 else y
    if t.ndim != 1 or y.ndim != 2 or y.shape[0] != t.shape[0]:
        raise ValueError(f"t must be [N] and y [N] or [N, channels] with the same N; got shapes {t.shape} and {y.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("the record must be finite: it holds NaN or infinite values")
    if np.any(np.diff(t) <= 0):
        raise ValueError("t must be strictly ascending (s)")
    lo = t[0] if start_s is None else checks.number("start_s", start_s, -math.inf)
    hi = t[-1] if end_s is None else checks.number("end_s", end_s, -math.inf)
    window = (t >= lo) & (t <= hi)
    t, y = t[window], y[window]
    order = 2 * n_modes + 2
    needed = 3 * (order + 1)
    if t.size < needed:
        raise ValueError(f"the window [{lo:g}, {hi:g}] s holds {t.size} samples; {n_modes} modes need at least {needed} (start_s, end_s, or a longer record)")
    dt = (t[-1] - t[0]) / (t.size - 1)
    if np.max(np.abs(t - (t[0] + dt * np.arange(t.size)))) > GRID_RTOL * dt:
        raise ValueError(f"t must be uniformly sampled (within {GRID_RTOL:g} of a sample time); resample the record first")
    scale = np.sqrt(np.mean(y**2, axis=0))
    if np.any(scale == 0):
        raise ValueError(f"channel(s) {(np.flatnonzero(scale == 0) + 1).tolist()} of y are 0 throughout the window")
    poles, rms, reconstruction = _poles(y / scale, order)
    residual = float(np.sqrt(np.mean((reconstruction - y / scale) ** 2)))
    with np.errstate(divide="ignore"):  # a pole at 0 (noise) is no mode
        s = np.log(poles) / dt
    # one of each conjugate pair (real poles, negative ones included, are not modes), with a
    # cycle or more in the window, and more than round-off in it
    oscillating = np.flatnonzero((poles.imag > 0) & (s.imag * (t[-1] - t[0]) > 2 * np.pi) & (np.sqrt(np.sum(rms**2, axis=1)) > MIN_RMS))
    if oscillating.size < n_modes:
        raise ValueError(
            f"found {oscillating.size} oscillating mode(s) in the window, not the {n_modes} asked for: "
            "ask for fewer, or give a longer window of a free decay"
        )
    strongest = oscillating[np.argsort(-np.sum(rms[oscillating] ** 2, axis=1))[:n_modes]]
    strongest = strongest[np.argsort(np.abs(s[strongest]))]
    omega = np.abs(s[strongest])
    damping = -s[strongest].real / omega
    if np.any(damping <= 0):
        growing = ", ".join(f"{w / (2 * np.pi):.4g} Hz" for w, z in zip(omega, damping) if z <= 0)
        raise ValueError(f"the mode(s) at {growing} do not decay in the window: it must be a free decay, after the excitation has ended (start_s)")
    return Modes(omega / (2 * np.pi), damping, rms[strongest] * scale, float(dt), float(t[0]), float(t[-1]), residual, reconstruction * scale)


def _poles(y: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ESPRIT on the channels of ``y`` [N, n_ch]: ``order`` poles, each one's RMS over the
    window in each channel [order, n_ch], and the reconstruction [N, n_ch] from them all."""
    n = y.shape[0]
    lags = min(n // 3, MAX_ROWS) + 1
    # The Hankel matrix H = R^T Q^T has the left singular vectors of R^T: R from a QR of H^T
    # (a window of each channel per row) taken block by block, so memory stays O(lags^2)
    # however long the record (100,000 samples of 2 channels: 8 s).
    r = np.zeros((0, lags))
    for c in range(y.shape[1]):
        windows = np.lib.stride_tricks.sliding_window_view(y[:, c], lags)
        for first in range(0, windows.shape[0], QR_BLOCK):
            r = np.linalg.qr(np.concatenate([r, windows[first : first + QR_BLOCK]]), mode="r")
    u = np.linalg.svd(r.T)[0][:, :order]
    poles = np.linalg.eigvals(np.linalg.lstsq(u[:-1], u[1:], rcond=None)[0]).astype(np.complex128)
    # z^t, each column divided by its largest magnitude (z^0, or z^(N-1) for a growing pole,
    # which would otherwise overflow over a long window)
    magnitude = np.abs(poles)
    steps = np.arange(n)[:, None]
    growing = magnitude > 1
    basis = np.where(growing, (poles / np.where(growing, magnitude, 1)) ** steps * np.where(growing, magnitude, 1) ** (steps - (n - 1)), poles**steps)
    amplitudes = np.linalg.lstsq(basis, y.astype(np.complex128), rcond=None)[0]
    # a mode is a pole and its conjugate, 2 Re(a z^t); a real pole alone, Re(a z^t)
    parts = np.real(basis[:, :, None] * amplitudes[None]) * np.where(poles.imag != 0, 2.0, 1.0)[None, :, None]
    return poles, np.sqrt(np.mean(parts**2, axis=0)), np.real(basis @ amplitudes)
