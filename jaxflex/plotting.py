"""Figures: NumPy arrays in, matplotlib figures out. The only module that imports matplotlib.

Signals are time-first ``[T]``. A run flagged as diverged is not drawn as NaN: its legend
says "diverged" and the finite part (if any) is drawn up to the first non-finite sample, on
axes scaled to the runs that did not diverge (its growth would flatten them to a line).
"""

from __future__ import annotations

import os
import re
import textwrap
from typing import Any, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxflex import fileio  # noqa: E402

_STYLES = {
    "open_loop": dict(color="0.45", ls="--", lw=1.0),
    "dfs": dict(color="C0", lw=1.2),
    "fuzzy": dict(color="C3", lw=1.2),
    "dfs+fuzzy": dict(color="C4", lw=1.2),
}
LABELS = {"open_loop": "Open loop", "dfs": "DFS", "fuzzy": "PD-type fuzzy", "dfs+fuzzy": "DFS + fuzzy"}
# Tuned gains, in every figure that has them ("tuned" in jaxflex tune's, "tuned <controller>"
# in jaxflex reproduce --params'): one look, so that a colour means the same in both.
TUNED_STYLE = dict(color="C2", lw=1.4, ls="-.")
# Any other run, in turn: never a colour another run of the same figure already has.
_OTHER_STYLES = (dict(color="C1", lw=1.2), dict(color="C5", lw=1.2, ls="--"), dict(color="C6", lw=1.2, ls=":"), dict(color="C8", lw=1.2, ls="-."))


def _styles(runs: Sequence[str], style_of: Mapping[str, str] | None = None) -> dict[str, dict]:
    """A distinct style per run of one figure: the paper's controllers keep theirs (a run
    ``style_of`` names takes that run's: "paper gains" of a tuning run takes its controller's),
    tuned gains ``TUNED_STYLE``, the others ``_OTHER_STYLES`` in turn (then matplotlib's
    defaults)."""
    style_of = style_of or {}
    fixed = {}
    for run in runs:
        key = style_of.get(run, run)
        if key in _STYLES:
            fixed[run] = _STYLES[key]
        elif key == "tuned" or key.startswith("tuned "):
            fixed[run] = TUNED_STYLE
    taken = {style["color"] for style in fixed.values()}
    others = iter(style for style in _OTHER_STYLES if style["color"] not in taken)
    return {run: fixed[run] if run in fixed else next(others, {}) for run in runs}


def arm_label(length_m: float, modes_hz: Sequence[float]) -> str:
    """Which arm a figure is of, as its title says it: "0.6 m arm, 2 modes at 13.3, 36.5 Hz"."""
    n = len(modes_hz)
    return f"{length_m:g} m arm, {n} mode{'s' if n > 1 else ''} at {', '.join(f'{float(f):.3g}' for f in modes_hz)} Hz"


def _finite_prefix(values: np.ndarray) -> int:
    bad = ~np.isfinite(values)
    return int(np.argmax(bad)) if bad.any() else values.shape[0]


def _check_shape(name: str, value: Any, shape: tuple[int, ...], what: str) -> None:
    """ValueError naming ``name`` when ``value`` is not of ``shape`` (``what`` it holds): a
    signal cut short would be drawn against the wrong times, or fail inside matplotlib."""
    if np.shape(value) != shape:
        raise ValueError(f"{name} must have shape {shape} ({what}); got {np.shape(value)}")


def responses(
    t: np.ndarray,
    runs: Mapping[str, Mapping[str, np.ndarray]],
    signals: Sequence[tuple[str, str]],
    diverged: Mapping[str, bool],
    title: str,
    style_of: Mapping[str, str] | None = None,
    settling: Mapping[str, Mapping[str, float]] | None = None,
) -> plt.Figure:
    """Time responses, one subplot per signal.

    A run that settles early would fill a sliver of the horizon (the paper's DFS settles in
    0.25 s of 3 s). A run has settled from the first sample after which each of its signals
    stays within ``SETTLED_FRACTION`` of its largest excursion from its final value. When
    every run drawn settles within ``ZOOM_FRACTION`` of the horizon, the time axis ends a
    quarter past the last of them (as :func:`percentile_bands` does) and a note gives the
    moment; when only some do (an open loop rings on), a second column shows that stretch.

    Args:
      t: [T] time (s).
      runs: run name -> signal name -> [T] values.
      signals: (signal name, y-axis label) pairs, one subplot each.
      diverged: run name -> whether the run diverged.
      title: figure title.
      style_of: run name -> the run (controller) whose line style it takes.
      settling: run name -> signal name -> settling time (s; 2 % band, as
        ``analysis.settling_time``'s default), each marked by a dotted line in the run's
        colour on that signal's panels and named in the legend (a report's settling times
        could not be read off its figures); a time that is not finite is not drawn.

    Raises:
      ValueError: for no signals, or a run that lacks one of them or holds one of another
        shape than ``t`` (naming both); a ``settling`` entry of a run or signal not drawn,
        or a time that is not a number >= 0.
    """
    if not signals:
        raise ValueError("signals must name at least one (signal, y-axis label) pair")
    for run, sig in runs.items():
        missing = [name for name, _ in signals if name not in sig]
        if missing:
            raise ValueError(f"runs[{run!r}] lacks signal(s) {missing}; it has {sorted(sig)}")
    names = [name for name, _ in signals]
    for run, times in (settling or {}).items():
        if run not in runs or not isinstance(times, Mapping) or set(times) - set(names):
            raise ValueError(f"settling[{run!r}] must map some of the signals drawn, {names}, of a run drawn, {list(runs)}, to a time; got {times!r}")
        for name, time in times.items():
            if isinstance(time, bool) or not isinstance(time, (int, float, np.floating, np.integer)) or time < 0:
                raise ValueError(f"settling[{run!r}][{name!r}] must be a settling time in s, >= 0; got {time!r}")
    t = np.asarray(t, dtype=float)
    for run, sig in runs.items():
        for name, _ in signals:
            _check_shape(f"runs[{run!r}][{name!r}]", sig[name], t.shape, "one value per time of t")
    values = {run: {name: np.asarray(sig[name]) for name, _ in signals} for run, sig in runs.items()}
    quick, end = [], None
    if t.size > 1:
        settled = [_run_settled(t, list(sig.values())) for run, sig in values.items() if not diverged.get(run, False)]
        quick = [s for s in settled if _settled_early(t, s)]
        end = _view_end(t, max(quick)) if quick and max(quick) > t[0] else None
    whole = end is not None and len(quick) == len(runs)  # every run settles early: no column to compare
    zoom = end is not None and not whole
    fig, axes = plt.subplots(len(signals), 2 if zoom else 1, figsize=(11.0 if zoom else 7.5, 2.6 * len(signals)), sharex="col", squeeze=False, gridspec_kw={"width_ratios": [2, 1]} if zoom else None)
    styles = _styles(list(runs), style_of)
    n = int(np.searchsorted(t, end, side="right")) if zoom else 0  # the zoom's samples
    for row, (name, ylabel) in enumerate(signals):
        _response_panel(axes[row, 0], t, {run: sig[name] for run, sig in values.items()}, diverged, styles)
        axes[row, 0].set_ylabel(ylabel)
        if zoom:
            _response_panel(axes[row, 1], t[:n], {run: sig[name][:n] for run, sig in values.items()}, diverged, styles)
            axes[row, 1].set_xlim(float(t[0]), end)
    for run, times in (settling or {}).items():
        for row, (name, _) in enumerate(signals):
            if name in times and np.isfinite(times[name]):
                label = f"{LABELS.get(run, run)} settled ({name}, 2 % band): {times[name]:.3g} s"
                for col in range(axes.shape[1]):
                    axes[row, col].axvline(times[name], color=styles[run].get("color", "k"), ls=":", lw=1.2, label=label if col == 0 else None)
    axes[-1, 0].set_xlabel("Time (s)")
    if whole:
        axes[0, 0].set_xlim(float(t[0]), end)
        _settled_note(axes[-1, 0], max(quick), float(t[-1]), "every run stays within {} of its largest excursion from its final value")
    if zoom:
        axes[0, 1].set_title(f"The first {_seconds(end - t[0], 2)} s", fontsize=9)
        axes[-1, 1].set_xlabel("Time (s)")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


ZOOM_FRACTION = 1 / 3
"""responses: runs settled within this fraction of the horizon get a zoomed column."""


def _settled_early(t: np.ndarray, settled: float | None) -> bool:
    """Whether a run settled at ``settled`` (None: it did not) did so within ZOOM_FRACTION of
    the horizon ``t``, early enough for a time axis that ends after it."""
    return settled is not None and settled - t[0] < ZOOM_FRACTION * (t[-1] - t[0])


def _run_settled(t: np.ndarray, signals: Sequence[np.ndarray]) -> float | None:
    """The time from which every signal stays within SETTLED_FRACTION of its largest
    excursion from its final value (its last sample; a hub angle settles at an offset);
    None when a value is not finite or a signal has not settled by the last sample."""
    latest = float(t[0])
    for v in signals:
        v = np.asarray(v, dtype=float)
        deviation = np.abs(v - v[-1])
        if not np.all(np.isfinite(deviation)):
            return None
        settled = _settle_time(t, deviation)
        if settled is None:
            return None
        latest = max(latest, settled)
    return latest


def _response_panel(ax: plt.Axes, t: np.ndarray, values: Mapping[str, np.ndarray], diverged: Mapping[str, bool], styles: Mapping[str, dict]) -> None:
    """One signal of every run against time, on axes scaled to the runs that did not diverge."""
    ends = {run: _finite_prefix(v) for run, v in values.items()}
    # the axes hold the runs that did not diverge; a diverged one is drawn until it leaves
    # them (its growing swings would cross them at every sample and fill them)
    settled = [v[: ends[run]] for run, v in values.items() if not diverged.get(run, False) and ends[run]]
    limits = None
    if settled and len(settled) < len(values):
        limits = _padded(min(np.min(v) for v in settled), max(np.max(v) for v in settled))
    for run, v in values.items():
        n = ends[run]
        if limits is not None and diverged.get(run, False):
            outside = np.flatnonzero((v[:n] < limits[0]) | (v[:n] > limits[1]))
            n = int(outside[0]) + 1 if outside.size else n
        label = LABELS.get(run, run) + (" (diverged)" if diverged.get(run, False) else "")
        ax.plot(t[:n], v[:n], label=label, **styles[run])
    if limits is not None:
        ax.set_ylim(*limits)
    ax.grid(alpha=0.3)


def _psd_fmax(freqs: np.ndarray, mode_freqs_hz: Sequence[float]) -> float:
    """psds' default upper frequency: 150 Hz or 1.5 times the highest mode, whichever is
    higher, within the estimate's frequencies."""
    return min(float(np.max(freqs)), max(150.0, 1.5 * max(mode_freqs_hz, default=0.0)))


def psd_limits(freqs: np.ndarray, curves: Sequence[np.ndarray], mode_freqs_hz: Sequence[float]) -> tuple[float, float] | None:
    """Log-scale y-limits that hold every finite, positive value of ``curves`` up to psds'
    default upper frequency, with a margin of 5 % of the decades on each side; None when
    there is no such value. For figures meant to be read side by side (fig6 and fig8)."""
    keep = np.asarray(freqs) <= _psd_fmax(freqs, mode_freqs_hz)
    for i, c in enumerate(curves):
        _check_shape(f"curves[{i}]", c, keep.shape, "one PSD value per frequency of freqs")
    values = np.concatenate([np.asarray(c, dtype=float)[keep] for c in curves]) if len(curves) else np.zeros(0)
    values = values[np.isfinite(values) & (values > 0)]
    if not values.size:
        return None
    lo, hi = float(values.min()), float(values.max())
    margin = (hi / lo) ** 0.05 if hi > lo else 10.0
    return lo / margin, hi * margin


def psds(freqs: np.ndarray, runs: Mapping[str, np.ndarray], mode_freqs_hz: Sequence[float], ylabel: str, title: str, fmax: float | None = None, style_of: Mapping[str, str] | None = None, ylim: tuple[float, float] | None = None) -> plt.Figure:
    """Power spectral densities on a log scale with the model's modal frequencies marked, up to
    ``fmax`` (Hz; default: 150 Hz or 1.5 times the highest mode, whichever is higher, within
    the estimate's frequencies). ``style_of``: run name -> the run whose line style it takes.
    ``ylim``: the y-axis limits (:func:`psd_limits` for figures shared with another); default
    matplotlib's."""
    freqs = np.asarray(freqs)
    for run, psd in runs.items():
        _check_shape(f"runs[{run!r}]", psd, freqs.shape, "one PSD value per frequency of freqs")
    if fmax is None:
        fmax = _psd_fmax(freqs, mode_freqs_hz)
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    keep = freqs <= fmax
    styles = _styles(list(runs), style_of)
    for run, psd in runs.items():
        psd = np.asarray(psd)
        if np.all(np.isfinite(psd)):
            ax.semilogy(freqs[keep], np.maximum(psd[keep], 1e-300), label=LABELS.get(run, run), **styles[run])
        else:  # a diverged run: named in the legend, not drawn
            ax.plot([], [], " ", label=f"{LABELS.get(run, run)} (non-finite, not drawn)")
    shown = [f for f in mode_freqs_hz if f <= fmax]
    for i, f in enumerate(shown):
        label = f"model modes ({', '.join(f'{float(g):.3g}' for g in shown)} Hz)" if i == 0 else None  # as arm_label writes them
        ax.axvline(f, color="k", lw=0.6, alpha=0.4, label=label)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_xlabel("Frequency (Hz)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return fig


def reduction_bars(reductions: Mapping[str, Mapping[str, Sequence[float]]], paper: Mapping[str, Sequence[float]] | None = None) -> plt.Figure:
    """Vibration reduction (dB) per mode, grouped by controller, one bar per PSD estimator.

    Args:
      reductions: estimator label -> controller -> [n_modes] dB; None (a diverged run) draws
        no bar, and "diverged" where it would stand.
      paper: controller -> the paper's dB per mode, drawn as hatched bars at the modes it
        gives (its two; none at a higher model mode, where a flat outline read as 0 dB).
    """
    estimators = list(reductions)
    controllers = list(next(iter(reductions.values())))
    n_modes = len(next(iter(next(iter(reductions.values())).values())))
    groups = [(c, m) for c in controllers for m in range(n_modes)]
    n_bars = len(estimators) + (1 if paper else 0)
    width = 0.8 / n_bars
    # 9 inches hold the paper's 2 modes x 2 controllers; more modes widen the figure so the
    # tick labels keep apart
    fig, ax = plt.subplots(figsize=(max(9.0, 3.0 + 1.3 * len(groups)), 3.8))
    x = np.arange(len(groups))
    # the estimators in shades of one colour map: the controllers' colours (DFS blue, fuzzy
    # red, tuned green) would say a bar belongs to a controller
    shades = plt.get_cmap("viridis")(np.linspace(0.15, 0.85, len(estimators)))
    for i, est in enumerate(estimators):
        vals = np.array([np.nan if reductions[est][c][m] is None else reductions[est][c][m] for c, m in groups], float)
        pos = x + (i - (n_bars - 1) / 2) * width
        ax.bar(pos, np.nan_to_num(vals, nan=0.0), width, label=f"jaxflex, {est}", color=shades[i])
        for xi in pos[np.isnan(vals)]:
            ax.text(xi, 0.0, "diverged", rotation=90, ha="center", va="bottom", fontsize=7, color="0.3")
    if paper:
        given = [(xi, paper[c][m]) for xi, (c, m) in zip(x, groups) if c in paper and m < len(paper[c]) and paper[c][m] is not None]
        if given:
            px, pv = zip(*given)
            ax.bar(np.asarray(px) + (n_bars - 1) / 2 * width, pv, width, label="paper", color="none", edgecolor="k", hatch="//")
    # the mode under each group, the controller once under its modes
    ax.set_xticks(x, [f"mode {m + 1}" for _, m in groups])
    for j, c in enumerate(controllers):
        ax.annotate(LABELS.get(c, c), xy=(j * n_modes + (n_modes - 1) / 2, 0.0), xycoords=("data", "axes fraction"), xytext=(0, -20), textcoords="offset points", ha="center", va="top")
        if j:
            ax.axvline(j * n_modes - 0.5, color="0.6", lw=0.8)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_ylabel("Reduction (dB)")
    ax.set_title("Level of vibration reduction at the natural frequencies")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the bars, hiding none
    fig.tight_layout()
    return fig


def surface(e: np.ndarray, e_dot: np.ndarray, values: np.ndarray, title: str = "Fuzzy control surface", note: str | None = None) -> plt.Figure:
    """3-D control surface over the normalised (angle, velocity) square; values [n_e, n_edot];
    ``note``, if given, is written under it."""
    fig = plt.figure(figsize=(6.5, 5.0))
    ax = fig.add_subplot(projection="3d")
    ee, dd = np.meshgrid(e, e_dot, indexing="ij")
    ax.plot_surface(ee, dd, values, cmap="viridis", linewidth=0, antialiased=True)
    ax.set_xlabel("Hub angle (normalised)")
    ax.set_ylabel("Hub velocity (normalised)")
    ax.set_zlabel("Torque (normalised)")
    ax.set_xticks(np.linspace(-1.0, 1.0, 5))  # every 0.25 crowded the 3-D axes' labels
    ax.set_yticks(np.linspace(-1.0, 1.0, 5))
    ax.set_title(title)
    if note:
        fig.text(0.5, 0.01, textwrap.fill(note, 90), ha="center", va="bottom", fontsize=8, color="0.3")
    fig.tight_layout(rect=(0.0, 0.06 if note else 0.0, 1.0, 1.0))
    return fig


def save(fig: plt.Figure, path: str | os.PathLike) -> None:
    """Write a PNG atomically and close the figure."""
    try:
        fileio.atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
    finally:
        plt.close(fig)


def loss_curves(
    steps: np.ndarray, loss: np.ndarray, val_steps: np.ndarray, val: np.ndarray, title: str, best_step: int | None = None, reference: tuple[str, float] | None = None, penalised: bool = False
) -> plt.Figure:
    """Training loss per step (top) and held-out objective at each validation (below, when
    there is one), each on its own axis: the held-out scenarios score on another level (3.3
    against 1.0 in a DFS run), and on one axis the training curve's 10 % fall read flat. Log
    scale where a panel's finite positive values span a decade or more (over less, a log axis
    labels one tick). ``best_step``: the step whose parameters were kept, marked by a vertical
    line in both panels and a ring on the held-out curve. ``reference``: ``(name,
    objective)`` of the gains that set the objective's scales ("paper" or "initial") and their
    training objective, named on the axis (1 only for the mean of one unit weight; the CVaR,
    the worst case and other weights score them otherwise). ``penalised``: the loss holds the
    DFS stability penalty too (a fuzzy run's legend named one it had not)."""
    val_steps, val = np.asarray(val_steps), np.asarray(val, float)
    panels = 2 if len(val_steps) else 1
    fig, axes = plt.subplots(panels, 1, figsize=(7.0, 3.6 if panels == 1 else 5.4), sharex=True, squeeze=False)
    train_ax = axes[0, 0]
    train_ax.plot(steps, loss, label="training loss (objective + stability penalty)" if penalised else "training loss (objective)", color="C0")
    train_ax.set_ylabel("Training objective" if reference is None else f"Training objective\n(the {reference[0]} gains score {reference[1]:.4g})")
    if panels == 2:
        val_ax = axes[1, 0]
        val_ax.plot(val_steps, val, "o-", label="held-out objective", color="C1", ms=3, clip_on=False)
        val_ax.set_ylabel("Held-out objective")
        if best_step is not None and np.any(val_steps == best_step):
            val_ax.plot([best_step], val[val_steps == best_step][:1], "o", ms=9, mfc="none", mec="k", clip_on=False, label="kept")
    for ax, values in zip(axes[:, 0], (loss, val)):
        if best_step is not None:  # clip_on=False: at the last step it lies on the axis' edge
            ax.axvline(best_step, color="k", ls=":", lw=1.2, clip_on=False, label=f"kept: the parameters after {best_step} updates" if ax is train_ax else None)
        values = np.asarray(values, float).ravel()
        values = values[np.isfinite(values) & (values > 0)]
        if values.size and values.max() >= 10 * values.min():
            ax.set_yscale("log")
        else:
            # a run that barely moves the objective read "1e-5+1" over the axis and ticks 0..2:
            # the objective's own values read at once
            ax.yaxis.get_major_formatter().set_useOffset(False)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    last = axes[-1, 0]
    last.set_xlabel("Step")
    last.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))  # steps are updates
    last.margins(x=0)  # the axis ran a step or more past the last one
    train_ax.set_title(title)
    fig.tight_layout()
    return fig


def _thin_ticks(ax: plt.Axes) -> None:
    """Fewer ticks on a linear x axis whose labels touch (-20000 ... 50000 in a third of a
    page's width ran together), down to 3."""
    if ax.get_xscale() != "linear":
        return
    renderer = ax.figure.canvas.get_renderer()
    for nbins in (6, 4, 3):
        boxes = [t.get_window_extent(renderer) for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]
        if all(a.x1 < b.x0 for a, b in zip(boxes, boxes[1:])):
            return
        ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(nbins))
        ax.figure.canvas.draw()  # the labels of the new ticks


def histograms(data: Mapping[str, np.ndarray], labels: Mapping[str, str], title: str, bins: int = 50) -> plt.Figure:
    """One histogram per metric (non-finite values left out and counted in the title), the
    metric's ``labels`` entry (its definition and unit) under it. Positive values spanning
    three decades or more (the ISE and effort of runs near instability) get log-spaced bins on
    a log axis: linear bins put nearly every run into the first. Values all equal get a bin
    around that value (matplotlib's default spans it +-0.5, so 2e-3 m read as 0), and a panel
    with no finite value says so. No metric at all is refused (ValueError)."""
    names = list(data)
    if not names:
        raise ValueError("data must hold at least one metric to draw")
    cols = 3
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(11, 3.0 * rows), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        values = np.asarray(data[name], float)
        finite = values[np.isfinite(values)]
        head = f"{name} ({values.size - finite.size} non-finite)" if finite.size < values.size else name
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            if lo > 0 and hi >= 1e3 * lo:
                ax.hist(finite, bins=np.geomspace(lo, hi, bins + 1), color="C0", alpha=0.8)
                ax.set_xscale("log")
            elif lo == hi:
                half = 0.05 * abs(lo) or 0.5
                ax.hist(finite, bins=bins, range=(lo - half, lo + half), color="C0", alpha=0.8)
                head += f": all {finite.size} = {lo:.4g}"
            else:
                ax.hist(finite, bins=bins, color="C0", alpha=0.8)
        else:
            ax.text(0.5, 0.5, "no finite value to draw", transform=ax.transAxes, ha="center", va="center", color="0.3")
            ax.set_xticks([])
            ax.set_yticks([])
        ax.set_title(head, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(names) :]:
        ax.axis("off")
    fig.canvas.draw()  # the tick formatters choose their offset or multiplier when drawn
    for ax, name in zip(axes.ravel(), names):
        ax.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))  # counts of runs
        offset = ax.xaxis.get_offset_text().get_text()
        # At the axis' lower right the offset would sit on the wrapped label: name it there.
        ax.xaxis.get_offset_text().set_visible(False)
        label = labels.get(name, name) + (f" (ticks: {offset})" if offset else "")
        ax.set_xlabel(textwrap.fill(label, 60), fontsize=7)
        ax.set_ylabel("runs", fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.canvas.draw()  # the panels' final widths, which set how many ticks the locators choose
    for ax in axes.ravel()[: len(names)]:
        _thin_ticks(ax)
    return fig


def percentile_bands(t: np.ndarray, bands: np.ndarray, percentiles: Sequence[float], ylabel: str, title: str) -> plt.Figure:
    """Percentile bands of a signal against time; bands [len(percentiles), T].

    Each percentile p < 50 whose mirror 100 - p is also given is a shaded band (inner bands
    darker), the median a solid line, and any other percentile a dashed line of its own.
    """
    pcts = [float(p) for p in percentiles]
    _check_shape("bands", bands, (len(pcts), np.shape(t)[0]), "len(percentiles), len(t)")
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    paired = sorted(p for p in pcts if p < 50 and 100 - p in pcts)  # outermost first
    for i, p in enumerate(paired):
        lo, hi = pcts.index(p), pcts.index(100 - p)
        ax.fill_between(t, bands[lo], bands[hi], alpha=0.25 + 0.15 * i, color="C0", lw=0, label=f"p{p:g}-p{100 - p:g}")
    for i, p in enumerate(pcts):
        if p == 50.0:
            ax.plot(t, bands[i], color="C0", lw=1.0, label="median")
        elif p not in paired and 100 - p not in paired:
            ax.plot(t, bands[i], color="C1", lw=0.8, ls="--", label=f"p{p:g}")
    if not np.any(np.isfinite(bands)):  # every scenario diverged: say so, over the horizon
        ax.text(0.5, 0.5, "no scenario left to draw", transform=ax.transAxes, ha="center", va="center", color="0.3")
        ax.get_yaxis().set_ticks([])
    else:
        ax.legend(fontsize=8)
    ax.set_xlabel("Time (s)")
    if np.shape(t)[0] > 1:
        view = _settled_view(t, bands)
        ax.set_xlim(float(t[0]), float(t[-1]) if view is None else view[1])
        if view is not None:
            _settled_note(ax, view[0], float(t[-1]), "every band stays within {} of the largest value drawn")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


SETTLED_FRACTION = 0.01  # percentile_bands and responses: this close to zero (or to a final value), relative to the largest value, has settled


def _settle_time(t: np.ndarray, deviation: np.ndarray) -> float | None:
    """The time of the first sample after which ``deviation`` (finite, >= 0) stays within
    SETTLED_FRACTION of its largest value: ``t[0]`` when it is all zero, None when the last
    sample is outside."""
    active = np.flatnonzero(deviation > SETTLED_FRACTION * deviation.max())
    if not active.size:
        return float(t[0])
    return float(t[active[-1] + 1]) if active[-1] + 1 < len(t) else None


def _shown(t: np.ndarray, lo: float | None, hi: float | None) -> slice:
    """The samples of ``t`` (ascending) from ``lo`` to ``hi`` (None: its first or last) and the
    one just outside each bound."""
    return slice(0 if lo is None else max(int(np.searchsorted(t, lo)) - 1, 0), None if hi is None else int(np.searchsorted(t, hi, side="right")) + 1)


def _view_end(t: np.ndarray, settled: float) -> float:
    """Where a time axis ends for a response settled at ``settled``: a quarter past it, at
    least 5 % of the horizon."""
    start, span = float(t[0]), float(t[-1]) - float(t[0])
    return start + max(1.25 * (settled - start), 0.05 * span)


def _padded(lo: float, hi: float) -> tuple[float, float]:
    """Axis limits around the values from ``lo`` to ``hi``: a tenth of their span beyond each
    (1e-12 around a flat signal)."""
    pad = 0.1 * (hi - lo) or 1e-12
    return lo - pad, hi + pad


def _seconds(value: float, digits: int = 3) -> str:
    """``value`` to ``digits`` significant digits, without an exponent (200, not 2e+02)."""
    return np.format_float_positional(value, precision=digits, unique=True, fractional=False, trim="-")


def _settled_note(ax: plt.Axes, settled: float, horizon: float, claim: str, end: str = "the horizon") -> None:
    """The note under a time axis that ends before the horizon (``end`` names it); ``claim``
    holds ``{}`` for the fraction."""
    text = f"from {_seconds(settled)} s to {end} ({_seconds(horizon)} s) {claim.format(f'{SETTLED_FRACTION:.0%}')}"
    # below the axis label, not inside the axes, where it lay over the settled curves
    ax.annotate(text, xy=(0.5, 0.0), xycoords=ax.xaxis.label, xytext=(0, -2), textcoords="offset points", ha="center", va="top", fontsize=8, color="0.3")


def _settled_view(t: np.ndarray, bands: np.ndarray) -> tuple[float, float] | None:
    """(settled, end): the time from which every band stays within SETTLED_FRACTION of the
    largest finite value, and where percentile_bands ends its time axis (``_view_end``).
    None, to draw the whole horizon: no finite value, or an end that would leave out less
    than half of the horizon (a response settled in 0.4 s filled a tenth of a 3 s figure)."""
    magnitude = np.where(np.isfinite(bands), np.abs(bands), 0.0).max(axis=0)
    settled = _settle_time(t, magnitude) if magnitude.max() > 0 else None
    if settled is None:
        return None
    end = _view_end(t, settled)
    return (settled, end) if end - float(t[0]) < 0.5 * (float(t[-1]) - float(t[0])) else None


def stability_chart(
    k: np.ndarray,
    tau_s: np.ndarray,
    spectral_radius: np.ndarray,
    rightmost_real: np.ndarray | None = None,
    first_delay_s: np.ndarray | None = None,
    point: tuple[float, float] | None = None,
    title: str = "DFS stability chart",
) -> plt.Figure:
    """Where the DFS loop is stable over a (k, tau) grid.

    Args:
      k: [n_k] gains (N*m/rad).
      tau_s: [n_tau] delays (s).
      spectral_radius: [n_tau, n_k] sampled loop (structural eigenvalue excluded); < 1 stable.
      rightmost_real: [n_tau, n_k] real part (1/s) of the continuous loop's rightmost
        non-structural root; < 0 stable. Omitted or all NaN: only the sampled loop is shown.
        Each cell is coloured by both loops' verdicts at its (k, tau); no boundary is
        interpolated between rows.
      first_delay_s: [n_k] first destabilising delay of the continuous loop (from the
        crossings), drawn as dots.
      point: (k, tau_s) operating point to mark (the paper's 55, 0.005).
      title: figure title.

    Raises:
      ValueError: naming an array whose shape does not fit ``k`` and ``tau_s``.
    """
    k, tau_ms = np.asarray(k, float), 1e3 * np.asarray(tau_s, float)
    radius = np.asarray(spectral_radius, float)
    grid = (tau_ms.size, k.size)
    _check_shape("spectral_radius", radius, grid, "[n_tau, n_k]: one row per delay of tau_s")
    if rightmost_real is not None:
        _check_shape("rightmost_real", rightmost_real, grid, "[n_tau, n_k], as spectral_radius")
    if first_delay_s is not None:
        _check_shape("first_delay_s", first_delay_s, (k.size,), "one delay per gain of k")
    sampled = radius < 1
    have_cont = rightmost_real is not None and np.any(np.isfinite(rightmost_real))
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    if have_cont:
        cont = np.asarray(rightmost_real, float) < 0
        cls = 2 * sampled + cont  # 0 neither, 1 continuous only, 2 sampled only, 3 both
        colors = ["#f4c7c3", "#fce8b2", "#c6dafc", "#b7e1cd"]
        names = ["unstable (both)", "stable: continuous only", "stable: sampled only", "stable (both)"]
    else:
        cls = sampled.astype(int)
        colors = ["#f4c7c3", "#b7e1cd"]
        names = ["unstable (sampled)", "stable (sampled)"]
    cmap = matplotlib.colors.ListedColormap(colors)
    ax.pcolormesh(k, tau_ms, cls, cmap=cmap, vmin=-0.5, vmax=len(colors) - 0.5, shading="nearest")
    handles = [matplotlib.patches.Patch(color=c, label=n) for c, n in zip(colors, names) if np.any(cls == names.index(n))]
    # No contour lines: the sampled loop exists at whole samples only, and the continuous
    # loop's rightmost root is computed on the same rows, so a contour interpolated between
    # rows put the boundaries up to 6 % off the exact crossings (k = 150: 4.53 against 4.80 ms).
    # The cells show both loops at their rows; the dots are the exact first crossings.
    if first_delay_s is not None:
        first = 1e3 * np.asarray(first_delay_s, float)
        ok = np.isfinite(first) & (first <= tau_ms.max())
        if ok.any():
            ax.plot(k[ok], first[ok], "o", ms=3, color="C3")
            handles.append(matplotlib.lines.Line2D([], [], color="C3", marker="o", ms=3, ls="none", label="continuous: first destabilising delay (exact crossings)"))
    if point is not None:
        ax.plot([point[0]], [1e3 * point[1]], marker="*", ms=14, color="k", mec="w", ls="none")
        handles.append(matplotlib.lines.Line2D([], [], color="k", marker="*", ms=10, ls="none", label=f"operating point (k = {point[0]:g}, tau = {1e3 * point[1]:g} ms)"))
    ax.set_xlabel("Gain k (N*m/rad)")
    ax.set_ylabel("Delay tau (ms)")
    ax.set_title(_title_lines(title, 75))  # it lists the arm's modes: 6 of them ran off the figure
    # under the chart: inside, it covered the top right, where the regions differ (found in a walkthrough)
    ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    fig.tight_layout()
    return fig


def calibration(
    measured_hz: np.ndarray,
    before_hz: np.ndarray,
    after_hz: np.ndarray,
    title: str,
    measured_damping: np.ndarray | None = None,
    model_damping: np.ndarray | None = None,
) -> plt.Figure:
    """Measured natural frequencies against the model's before and after a calibration: the
    frequencies per mode (log scale over a decade or more), and the model's error in percent of the measured;
    with ``measured_damping`` (modes 1..n_d), a third panel of the damping ratios, measured and
    the calibrated model's (``model_damping``, every mode)."""
    modes = np.arange(1, len(measured_hz) + 1)
    damped = measured_damping is not None and len(measured_damping) > 0
    fig, axes = plt.subplots(1, 3 if damped else 2, figsize=(13.0 if damped else 9.0, 3.6))
    left, right = axes[:2]
    # measured: an open square that a calibrated dot on it fills, not hides (a bold X did)
    measured = dict(marker="s", ls="none", ms=10, mfc="none", mec="k", mew=1.5, label="measured")
    calibrated = dict(marker="o", ls="none", ms=4, color="C0", zorder=3, label="model calibrated")
    left.plot(modes, measured_hz, **measured)
    left.plot(modes, before_hz, "o", mfc="none", color="C1", label="model before")
    left.plot(modes, after_hz, **calibrated)
    if max(np.max(measured_hz), np.max(before_hz)) >= 10 * min(np.min(measured_hz), np.min(before_hz)):
        left.set_yscale("log")
    left.set_ylabel("Natural frequency (Hz)")
    width = 0.38
    for offset, values, label, color in ((-width / 2, before_hz, "model before", "C1"), (width / 2, after_hz, "model calibrated", "C0")):
        error = 100.0 * (np.asarray(values) / measured_hz - 1.0)
        # a calibrated error of 0 draws no bar: its label shows it, as +0.00, above the axis (a
        # -1e-14 % was "-0.00", and a label below the axis when the round-off was negative)
        bars = right.bar(modes + offset, np.where(np.abs(error) < 0.005, 0.0, error), width, label=label, color=color)
        right.bar_label(bars, fmt=lambda v: f"{v:+.2f}", fontsize=7)
    right.axhline(0.0, color="k", lw=0.8)
    right.margins(y=0.12)  # room for the bar labels inside the frame
    right.set_ylabel("Error (% of measured)")
    if damped:
        axes[2].plot(np.arange(1, len(measured_damping) + 1), 100.0 * np.asarray(measured_damping), **measured)
        axes[2].plot(modes, 100.0 * np.asarray(model_damping), **calibrated)
        axes[2].set_ylabel("Damping ratio (%)")
        # from 0, with room above the highest ratio: the autoscaled top sat on it (ratios of
        # 1 and 0.98 % drew their markers cut in half by the frame, under the legend)
        shown = 100.0 * np.concatenate([np.asarray(measured_damping, float), np.asarray(model_damping, float)])
        shown = shown[np.isfinite(shown)]
        axes[2].set_ylim(0.0, 1.25 * float(shown.max()) if shown.size and shown.max() > 0 else None)
    for ax in axes:
        ax.set_xlabel("Mode")
        ax.set_xticks(modes)
        ax.set_xlim(0.5, len(modes) + 0.5)  # the first and last modes' markers clear of the frame
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def _title_lines(text: str, width: int) -> str:
    """``text`` in as few lines of at most ``width`` characters as it needs, of about equal
    length, and never a number parted from its unit: wrapped greedily, the stability chart's
    title ended in a lone "(zoh)" or "1\nms (zoh)"."""
    text = re.sub(r"(\d) (?=(?:ms|s|Hz|m)\b)", "\\1\u00a0", text)  # textwrap breaks at ASCII spaces only
    count = max(1, len(textwrap.wrap(text, width)))
    return next("\n".join(lines) for w in range(max(1, -(-len(text) // count)), width + 1) if len(lines := textwrap.wrap(text, w)) <= count)


ZOOM_PERIODS = 5
"""identification: the periods of the slowest mode its zoomed column shows."""


def identification(t: np.ndarray, record: np.ndarray, t_model: np.ndarray, model: np.ndarray, names: Sequence[str], title: str, period_s: float | None = None) -> plt.Figure:
    """A free-vibration record (every sample, no decimation) and the model of its modes over
    the window identified, one row per channel.

    A record that settles within ZOOM_FRACTION of its length (every channel within
    SETTLED_FRACTION of its largest excursion from its last value) is drawn up to a quarter
    past that time, with a note under the axis (a 100 s record of a decay over 10 s was a solid
    band), unless the window identified starts after that. With ``period_s`` (the slowest mode's period, s), a second column shows the first
    ZOOM_PERIODS periods from the window's start, where the record and the model can be told
    apart. Each column draws only the samples it shows, and one either side.
    """
    t, record, t_model, model = (np.asarray(a, dtype=float) for a in (t, record, t_model, model))
    zoom = period_s is not None
    fig, axes = plt.subplots(len(names), 2 if zoom else 1, figsize=(13.0 if zoom else 9.0, 1.2 + 2.0 * len(names)), sharex="col", squeeze=False, gridspec_kw={"width_ratios": [2, 1]} if zoom else None)
    settled = _run_settled(t, list(record.T)) if t.size > 1 else None
    start = float(t_model[0])
    end = _view_end(t, settled) if _settled_early(t, settled) and settled > t[0] else None
    if end is not None and start >= end:  # a window identified after the record settled would be cut off: the whole record
        end = None
    stop = start + ZOOM_PERIODS * float(period_s) if zoom else None
    # each column draws the samples it shows and one either side, which carry the lines to its edges
    drawn = [(_shown(t, None, end), _shown(t_model, None, end))] + ([(_shown(t, start, stop), _shown(t_model, start, stop))] if zoom else [])
    for row, (name, y, fit) in enumerate(zip(names, record.T, model.T)):
        for ax, (rec, mod) in zip(axes[row], drawn):
            ax.plot(t[rec], y[rec], color="0.6", lw=1.0, label="record")
            ax.plot(t_model[mod], fit[mod], color="C0", lw=1.0, ls="--", label="modes identified")
            ax.axvline(t_model[0], color="k", lw=0.8, ls=":")
            ax.grid(alpha=0.3)
        axes[row, 0].set_ylabel(name)
    axes[0, 0].legend(fontsize=8, loc="best")  # a hub that drifts up fills the upper right
    for ax in axes[-1]:
        ax.set_xlabel("Time (s)")
    if end is not None:
        axes[0, 0].set_xlim(float(t[0]), end)
        _settled_note(axes[-1, 0], settled, float(t[-1]), "every channel stays within {} of its largest excursion from its last value", "the record's end")
    if zoom:
        axes[0, 1].set_xlim(start, stop)
        axes[0, 1].set_title(f"{ZOOM_PERIODS} periods of the slowest mode ({_seconds(float(period_s))} s each)", fontsize=9)
        for row, (y, fit) in enumerate(zip(record.T, model.T)):
            shown = np.concatenate([y[(t >= start) & (t <= stop)], fit[t_model <= stop]])
            if shown.size and np.all(np.isfinite(shown)):
                axes[row, 1].set_ylim(*_padded(shown.min(), shown.max()))
    fig.suptitle(title)
    fig.tight_layout()
    return fig
