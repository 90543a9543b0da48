"""What the figures show: labels, limits, texts and styles of the matplotlib objects."""

import numpy as np
import pytest

from jaxflex import beam, plotting
from jaxflex.scenarios import ScenarioSpec, perturbed_params


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plotting.plt.close("all")


def test_tune_psd_marks_the_modes_of_the_scenarios_own_plant(monkeypatch, tmp_path):
    # With plant uncertainty in the scenarios, a held-out arm's peaks sit away from the
    # nominal frequencies: the lines labelled "model modes" were the nominal arm's. The titles
    # name the arm each figure is of (a 0.8 m arm here, not the paper's 0.6 m).
    from tuning import run
    from tuning.tuner import Problem, TuneConfig

    arm = beam.BeamParams(length_m=0.8)
    config = TuneConfig(controller="dfs", n_scenarios=2, n_heldout=2, beam=arm, scenarios=ScenarioSpec(horizon_s=0.05, youngs_modulus_rel=0.4, payload_max_kg=0.1))
    problem = Problem(config)
    marked, titles = [], {"responses": [], "psds": [], "loss": []}
    monkeypatch.setattr(plotting, "psds", lambda freqs, runs, modes, ylabel, title, **k: marked.append(np.asarray(modes)) or titles["psds"].append(title) or plotting.plt.figure())
    monkeypatch.setattr(plotting, "responses", lambda t, runs, signals, div, title, **k: titles["responses"].append(title) or plotting.plt.figure())
    monkeypatch.setattr(plotting, "loss_curves", lambda steps, loss, vs, v, title, *a, **k: titles["loss"].append(title) or plotting.plt.figure())
    state = {"problem": problem, "history": [{"step": 0, "loss": 1.0, "val_objective": 1.0}], "best_step": 0, "best_raw": problem.initial_raw}
    run._figures(state, str(tmp_path), 1.0)
    assert len(marked) == 3  # the paper scenario (nominal plant), then held-out 1 and 2
    nominal = np.asarray(beam.natural_frequencies_hz(arm, config.n_modes))
    assert titles["responses"][0].endswith(f"2 modes at {nominal[0]:.3g}, {nominal[1]:.3g} Hz")  # the nominal arm's, said as such
    np.testing.assert_allclose(marked[0], nominal)
    assert titles["loss"] == [f"Tuning dfs for the 0.8 m arm, 2 modes at {nominal[0]:.3g}, {nominal[1]:.3g} Hz"]
    for i, modes in enumerate(marked[1:]):
        plant = perturbed_params(arm, jax_index(problem.heldout.plant, i))
        expected = np.asarray(beam.natural_frequencies_hz(plant, config.n_modes))
        assert np.max(np.abs(expected / nominal - 1)) > 0.01  # the draw moved them
        np.testing.assert_allclose(modes, expected, rtol=1e-6)
        title = f"dfs: paper vs tuned gains, held-out scenario {i + 1}\n0.8 m arm, 2 modes at {expected[0]:.3g}, {expected[1]:.3g} Hz (this scenario's plant)"
        assert titles["responses"][i + 1] == titles["psds"][i + 1] == title


def jax_index(tree, i):
    import jax

    return jax.tree.map(lambda a: a[i], tree)


@pytest.mark.parametrize("controller", ["dfs", "fuzzy", "dfs+fuzzy"])
def test_a_run_looks_the_same_in_tune_and_reproduce_figures(controller):
    # jaxflex tune drew "paper gains" green dash-dot, the look of the *tuned* run in
    # reproduce --params' fig_tuned_response.png, and DFS's paper gains were not DFS's blue.
    t = np.linspace(0.0, 1.0, 50)
    y = {"tip": np.exp(-t)}

    def looks(fig):
        return {line.get_label(): (line.get_color(), line.get_linestyle()) for line in fig.axes[0].get_lines()}

    tune = looks(plotting.responses(t, {"paper gains": y, "tuned": y}, [("tip", "Tip (m)")], {}, "t", style_of={"paper gains": controller}))
    base = "dfs" if controller == "dfs" else "fuzzy"
    paper = f"{plotting.LABELS[controller]} (paper gains)"  # reproduce --params' legend
    repro = looks(plotting.responses(t, {"open_loop": y, paper: y, f"tuned {controller}": y}, [("tip", "Tip (m)")], {}, "t", style_of={paper: controller}))
    assert tune["tuned"] == repro[f"tuned {controller}"]
    assert tune["paper gains"] == repro[paper]
    if controller != "dfs+fuzzy":  # the paper's own run of that controller looks the same
        assert repro[paper] == looks(plotting.responses(t, {base: y}, [("tip", "Tip (m)")], {}, "t"))[plotting.LABELS[base]]
    assert len(set(tune.values())) == 2 and len(set(repro.values())) == 3
    psd = plotting.psds(t, {"paper gains": y["tip"], "tuned": y["tip"]}, (), "y", "t", style_of={"paper gains": controller})
    assert looks(psd) == tune


def test_reduction_bars_with_more_modes_than_the_paper():
    # jaxflex reproduce --modes 4: the "PD-type fuzzy\nmode N" tick labels ran into each
    # other, and the paper's missing modes 3 and 4 were flat hatched outlines, read as 0 dB
    red = {"hann-1024": {"dfs": [67.9, 79.9, 67.3, -16.5], "fuzzy": [86.2, 83.4, 65.9, None]}, "hann-256": {"dfs": [52.0, 53.0, 44.0, -11.0], "fuzzy": [42.0, 65.0, 52.0, 7.0]}}
    fig = plotting.reduction_bars(red, {"dfs": [123.4, 66.9], "fuzzy": [102.2, 23.2]})
    fig.canvas.draw()
    ax = fig.axes[0]
    boxes = [label.get_window_extent() for label in ax.get_xticklabels() if label.get_text()]
    boxes += [text.get_window_extent() for text in ax.texts if text.get_text() in ("DFS", "PD-type fuzzy")]
    assert len(boxes) == 10
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1 :])
    paper = [p.get_height() for p in ax.patches if p.get_hatch()]
    assert paper == [123.4, 66.9, 102.2, 23.2]
    assert [text.get_text() for text in ax.texts].count("diverged") == 1
    # an estimator's bars share one colour, and it is no controller's (DFS blue read as "the DFS bar")
    from matplotlib.colors import to_rgba

    legend = {text.get_text(): handle.get_facecolor() for text, handle in zip(ax.get_legend().get_texts(), ax.get_legend().legend_handles)}
    controller_colours = {to_rgba(style["color"]) for style in (*plotting._STYLES.values(), plotting.TUNED_STYLE)}
    estimator_colours = {legend[f"jaxflex, {est}"] for est in red}
    assert len(estimator_colours) == 2 and not estimator_colours & controller_colours
    bars = [p for p in ax.patches if not p.get_hatch()]
    assert [p.get_facecolor() for p in bars] == [legend["jaxflex, hann-1024"]] * 8 + [legend["jaxflex, hann-256"]] * 8


def test_histograms_show_decades_equal_values_and_empty_metrics():
    # montecarlo near the stability edge (dfs k = 100, E +-40 %): peak tip deflections from
    # 7e-4 to 700 m put 38 of 39 runs into the first linear bin; scenarios that are all alike
    # drew their 2e-3 m on an axis of +-0.5, read as 0; every run diverged: blank axes 0..1
    rng = np.random.default_rng(0)
    spread = np.concatenate([rng.uniform(1e-3, 1e-2, 38), [700.0]])
    fig = plotting.histograms({"peak": spread, "same": np.full(16, 2e-3), "none": np.array([])}, {}, "dfs: 39 of 64 runs")
    peak, same, none = fig.axes[:3]
    assert peak.get_xscale() == "log"
    assert sum(p.get_height() for p in peak.patches if p.get_x() < 1e-2) == 38
    lo, hi = same.get_xlim()
    assert 1.5e-3 < lo < 2e-3 < hi < 2.5e-3 and "all 16 = 0.002" in same.get_title()
    assert [t.get_text() for t in none.texts] == ["no finite value to draw"]
    assert fig._suptitle.get_text() == "dfs: 39 of 64 runs"


def test_histogram_tick_labels_do_not_run_together():
    """Wide labels (-20000 ... 50000) in a third of the page's width ran into each other; the
    counts of runs had ticks at 0.2, 0.4, ... of a run."""
    rng = np.random.default_rng(0)
    fig = plotting.histograms({name: rng.uniform(-12345.6, 45678.9, 100) for name in "abc"}, {}, "t")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        boxes = [t.get_window_extent(renderer) for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]
        assert len(boxes) >= 3 and all(a.x1 < b.x0 for a, b in zip(boxes, boxes[1:]))
        assert all(float(y).is_integer() for y in ax.get_yticks())


def test_percentile_bands_when_every_scenario_diverged():
    # montecarlo with dfs k = 130: all 64 diverged, and tip_bands.png showed a time axis of
    # -0.04..0.04 s with a legend of bands that were not there
    t = np.arange(3000) * 1e-3
    fig = plotting.percentile_bands(t, np.full((3, t.size), np.nan), [5.0, 50.0, 95.0], "Tip deflection (m)", "0 of 64")
    ax = fig.axes[0]
    assert ax.get_xlim() == (0.0, t[-1])
    assert [x.get_text() for x in ax.texts] == ["no scenario left to draw"] and ax.get_legend() is None


def test_calibration_damping_markers_clear_of_the_frame_and_the_legend():
    # calibrate --record: measured ratios 1 and 0.98 % sat on the top of the frame, half cut,
    # with mode 2's under the legend
    fig = plotting.calibration(np.array([13.31, 35.1]), np.array([13.32, 36.47]), np.array([13.31, 35.1]), "t", np.array([0.01, 0.009815]), np.array([0.01, 0.009815]))
    fig.canvas.draw()
    ax = fig.axes[2]
    assert ax.get_ylim()[0] == 0.0 and ax.get_ylim()[1] >= 1.2
    legend = ax.get_legend().get_window_extent()
    points = ax.transData.transform([(1, 1.0), (2, 0.9815)])
    assert not any(legend.contains(*p) for p in points)
    for ax in fig.axes:  # the first and last modes' markers sat on the side frames, half cut
        assert ax.get_xlim() == (0.5, 2.5)


def test_calibration_measured_marker_leaves_the_calibrated_dot_visible_and_errors_are_labelled():
    # the measured bold X hid the calibrated dot drawn on it, and a calibrated error of 0 drew
    # no bar at all, as if it were missing
    fig = plotting.calibration(np.array([13.31, 35.1]), np.array([13.32, 36.47]), np.array([13.31, 35.1]), "t", np.array([0.01, 0.009815]), np.array([0.01, 0.009815]))
    for ax in (fig.axes[0], fig.axes[2]):
        measured, calibrated = (line for line in ax.get_lines() if line.get_label() in ("measured", "model calibrated"))
        assert measured.get_marker() == "s" and measured.get_markerfacecolor() == "none"
        assert calibrated.get_zorder() > measured.get_zorder() and calibrated.get_markersize() < measured.get_markersize()
    fig.canvas.draw()
    right = fig.axes[1]
    labels = [t.get_text() for t in right.texts]
    assert labels == [f"{100 * (13.32 / 13.31 - 1):+.2f}", f"{100 * (36.47 / 35.1 - 1):+.2f}", "+0.00", "+0.00"] == ["+0.08", "+3.90", "+0.00", "+0.00"]
    # a fit a hair under the measurement (-2e-14 %) is labelled +0.00, as the CLI prints it, not -0.00
    fig = plotting.calibration(np.array([13.31, 35.1]), np.array([13.32, 36.47]), np.array([13.31, np.nextafter(35.1, 0)]), "t")
    fig.canvas.draw()
    assert [t.get_text() for t in fig.axes[1].texts][2:] == ["+0.00", "+0.00"]


def test_stability_chart_title_with_many_modes_stays_on_the_figure():
    title = "DFS stability: 0.9 m arm, 6 modes at 13.3, 36.5, 115, 241, 412, 628 Hz, sampled at 1 ms (zoh)"
    k, tau = np.linspace(0, 165, 5), np.linspace(1e-3, 4e-2, 4)
    fig = plotting.stability_chart(k, tau, np.full((4, 5), 0.99), title=title)
    fig.canvas.draw()
    box = fig.axes[0].title.get_window_extent()
    assert 0 <= box.x0 and box.x1 <= fig.bbox.x1 and box.y1 <= fig.bbox.y1


def test_loss_curves_of_a_run_that_barely_moves_read_without_an_offset():
    steps = np.arange(21)
    fig = plotting.loss_curves(steps, 1.0 + 1e-6 * steps[::-1], np.array([0, 10, 20]), 1.0 + 1e-6 * np.array([3.0, 2.0, 1.0]), "Tuning dfs", 20, ("paper", 1.0))
    fig.canvas.draw()
    ax = fig.axes[0]
    assert ax.yaxis.get_offset_text().get_text() == ""
    ticks = [float(t.get_text().replace("\u2212", "-")) for t in ax.get_yticklabels() if t.get_text()]
    assert all(0.99 < v < 1.01 for v in ticks)


def test_identification_legend_leaves_the_record_visible():
    # calibrate --record: the hub angle drifts up through the decay, under the legend that was
    # pinned to the upper right
    t = np.arange(0.0, 4.0, 1e-3)
    hub = 2e-3 * np.exp(-0.8 * t) * np.cos(2 * np.pi * 13.3 * t) + 1e-3 * t
    tip = -3e-3 * np.exp(-0.8 * t) * np.cos(2 * np.pi * 13.3 * t)
    y = np.stack([hub, tip], axis=1)
    fig = plotting.identification(t, y, t, y, ["hub_rad", "tip_m"], "tap.csv")
    fig.canvas.draw()
    ax = fig.axes[0]
    legend = ax.get_legend().get_window_extent()
    points = ax.transData.transform(np.stack([t[::10], hub[::10]], axis=1))
    assert not any(legend.contains(*p) for p in points)


def test_figures_name_empty_or_missing_data():
    """An empty histogram set failed in matplotlib's gridspec, and a run without a signal with
    a bare KeyError."""
    with pytest.raises(ValueError, match="data must hold at least one metric"):
        plotting.histograms({}, {}, "none")
    t = np.arange(3.0)
    with pytest.raises(ValueError, match=r"runs\['dfs'\] lacks signal\(s\) \['tip'\]; it has \['hub'\]"):
        plotting.responses(t, {"dfs": {"hub": t}}, [("tip", "m")], {}, "x")
    with pytest.raises(ValueError, match="signals must name at least one"):
        plotting.responses(t, {"dfs": {"hub": t}}, [], {}, "x")


def test_figures_refuse_arrays_that_do_not_fit_their_axes():
    """A signal cut short was drawn against the wrong times, and a PSD or a chart of another
    shape failed inside matplotlib (IndexError, TypeError), naming nothing."""
    t = np.linspace(0.0, 1.0, 20)
    with pytest.raises(ValueError, match=r"runs\['dfs'\]\['tip'\] must have shape \(20,\) \(one value per time of t\); got \(10,\)"):
        plotting.responses(t, {"dfs": {"tip": t[:10]}}, [("tip", "m")], {}, "x")
    freqs = np.linspace(0.0, 500.0, 11)
    with pytest.raises(ValueError, match=r"runs\['a'\] must have shape \(11,\) \(one PSD value per frequency of freqs\); got \(5,\)"):
        plotting.psds(freqs, {"a": np.ones(5)}, [13.0], "y", "t")
    k, tau = np.linspace(10.0, 100.0, 4), np.linspace(1e-3, 8e-3, 3)
    radius = np.full((3, 4), 0.9)
    with pytest.raises(ValueError, match=r"spectral_radius must have shape \(3, 4\) \(\[n_tau, n_k\]: one row per delay of tau_s\); got \(4, 3\)"):
        plotting.stability_chart(k, tau, radius.T)
    with pytest.raises(ValueError, match=r"rightmost_real must have shape \(3, 4\)"):
        plotting.stability_chart(k, tau, radius, rightmost_real=np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"first_delay_s must have shape \(4,\) \(one delay per gain of k\); got \(3,\)"):
        plotting.stability_chart(k, tau, radius, first_delay_s=np.ones(3))
    plotting.stability_chart(k, tau, radius, rightmost_real=-np.ones((3, 4)), first_delay_s=np.ones(4))  # the shapes that fit draw


def _assert_note_below_the_axis(fig, ax):
    """The settled note lies under the time axis' label and inside the figure: drawn inside
    the axes, it lay over the settled curves."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    note, = ax.texts
    box, label, axes_box = note.get_window_extent(renderer), ax.xaxis.label.get_window_extent(renderer), ax.get_window_extent(renderer)
    assert box.y1 <= label.y0 and label.y1 <= axes_box.y0, (box, label, axes_box)
    assert 0 <= box.y0 and 0 <= box.x0 and box.x1 <= fig.bbox.width, (box, fig.bbox)


def test_percentile_bands_end_the_time_axis_when_the_motion_settles():
    # montecarlo's tip_bands.png drew 3 s while the response was over in 0.4 s
    t = np.arange(3000) * 1e-3
    decay = 5e-3 * np.exp(-t / 0.05) * np.sin(2 * np.pi * 13.3 * t)
    fig = plotting.percentile_bands(t, np.stack([-np.abs(decay), decay, np.abs(decay)]), [5.0, 50.0, 95.0], "Tip deflection (m)", "t")
    ax = fig.axes[0]
    # the peak, 3.4e-3 at the first crest (t = 18.8 ms), falls to 1 % of itself where
    # 5e-3 exp(-t / 0.05) = 3.4e-5, t = 0.249 s: the last sample above it is a crest just before
    magnitude = np.abs(decay)
    settled = t[np.flatnonzero(magnitude > 0.01 * magnitude.max())[-1] + 1]  # the first sample of the settled tail
    assert 0.22 < settled < 0.25 and np.all(magnitude[t >= settled] <= 0.01 * magnitude.max())
    assert ax.get_xlim() == pytest.approx((0.0, 1.25 * settled))
    assert [x.get_text() for x in ax.texts] == [f"from {settled:.3g} s to the horizon (3 s) every band stays within 1% of the largest value drawn"]
    _assert_note_below_the_axis(fig, ax)
    # motion to the end, or settling after a third of the horizon: the whole horizon, no note
    for bands in (np.stack([-np.ones_like(t), 0 * t, np.ones_like(t)]), np.stack([-1.0 * (t < 1.3), 0 * t, 1.0 * (t < 1.3)])):
        ax = plotting.percentile_bands(t, bands, [5.0, 50.0, 95.0], "y", "t").axes[0]
        assert ax.get_xlim() == (0.0, t[-1]) and not ax.texts
    # a kick at the first sample only: the axis keeps 5 % of the horizon
    kick = np.zeros((3, t.size))
    kick[:, 0] = [-1.0, 0.0, 1.0]
    assert plotting.percentile_bands(t, kick, [5.0, 50.0, 95.0], "y", "t").axes[0].get_xlim() == pytest.approx((0.0, 0.05 * t[-1]))


def test_stability_chart_legend_sits_under_the_chart_and_names_only_what_is_drawn():
    # the legend covered the chart's top right, where the regions differ, and named the
    # spectral-radius line and the crossing dots on a chart (k = -5) that had neither
    k, tau = np.linspace(0, 60, 7), np.arange(1, 13) * 1e-3
    radius = 0.95 + 0.01 * np.add.outer(np.arange(12), np.arange(7))  # crosses 1
    rightmost = radius - 1.02
    fig = plotting.stability_chart(k, tau, radius, rightmost, np.full(7, 0.0075), point=(20.0, 0.004))
    fig.canvas.draw()
    ax = fig.axes[0]
    assert ax.get_legend().get_window_extent().y1 < ax.get_window_extent().y0  # below the axes
    assert ax.get_legend().get_window_extent().y0 >= 0  # on the figure
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "unstable (both)", "stable: continuous only", "stable (both)",
        "continuous: first destabilising delay (exact crossings)", "operating point (k = 20, tau = 4 ms)",
    ]
    # no boundary interpolated between the rows: the sampled loop has none between whole
    # samples, and the continuous loop's was drawn up to 6 % off its exact crossings
    assert not ax.collections[1:]
    stable = plotting.stability_chart(k, tau, np.full((12, 7), 0.99), np.full((12, 7), -1.0), np.full(7, np.inf))
    assert [t.get_text() for t in stable.axes[0].get_legend().get_texts()] == ["stable (both)"]


def test_surface_writes_its_note_and_histograms_name_their_counts():
    """The fuzzy surface's flat zero corners looked like a plotting fault (a figure walkthrough):
    reproduce writes why under it. Histogram counts had no axis label."""
    grid = np.linspace(-1.0, 1.0, 5)
    fig = plotting.surface(grid, grid, np.zeros((5, 5)), note="flat at 0 where no rule fires")
    assert [t.get_text() for t in fig.texts] == ["flat at 0 where no rule fires"]
    assert not plotting.surface(grid, grid, np.zeros((5, 5))).texts
    fig = plotting.histograms({"a": np.arange(10.0), "b": np.arange(5.0)}, {}, "t")
    assert [ax.get_ylabel() for ax in fig.axes[:2]] == ["runs", "runs"]


def _ringing(t, decay_per_s, amplitude=1e-3):
    return amplitude * np.exp(-decay_per_s * t) * np.cos(2 * np.pi * 13.3 * t)


def _settles(t, v):
    """The first time after which |v - v[-1]| stays within 1 % of its largest value."""
    deviation = np.abs(v - v[-1])
    return t[np.flatnonzero(deviation > 0.01 * deviation.max())[-1] + 1]


def test_a_run_that_settles_early_gets_a_zoomed_column_beside_the_whole_horizon():
    """The paper's DFS settles in about 0.25 s of 3 s and filled a twelfth of the figure's
    width beside the ringing open loop: a second column shows the stretch until every
    signal of it has settled (here the tip, slower than q1)."""
    t = np.arange(3000) * 1e-3
    q1, tip = _ringing(t, 40.0), 2 * _ringing(t, 20.0)
    settle = _settles(t, tip)
    assert _settles(t, q1) < settle
    runs = {"open_loop": {"q1": _ringing(t, 0.8), "tip": 2 * _ringing(t, 0.8)}, "dfs": {"q1": q1, "tip": tip}}
    fig = plotting.responses(t, runs, [("q1", "q1 (m)"), ("tip", "Tip (m)")], {}, "DFS")
    (whole_q, zoom_q), (whole_tip, zoom_tip) = np.array(fig.axes).reshape(2, 2)
    assert whole_q.get_xlim()[1] >= 3.0 and [line.get_xdata()[-1] for line in whole_q.get_lines()] == [t[-1], t[-1]]
    for ax in (zoom_q, zoom_tip):
        assert ax.get_xlim() == pytest.approx((0.0, 1.25 * settle))
        assert all(line.get_xdata()[-1] <= 1.25 * settle for line in ax.get_lines()) and len(ax.get_lines()) == 2
    assert 0.2 < settle < 0.35 and zoom_q.get_title() == f"The first {np.format_float_positional(1.25 * settle, precision=2, fractional=False, trim='-')} s"
    assert zoom_tip.get_ylim()[1] == pytest.approx(whole_tip.get_ylim()[1], rel=0.1)  # the open loop's first swings set both
    # a run that settles within a hundredth of the horizon: the zoom spans 5 % of it at least
    fast = _ringing(t, 600.0)
    fig = plotting.responses(t, {"open_loop": runs["open_loop"], "dfs": {"q1": fast, "tip": fast}}, [("q1", "q1 (m)"), ("tip", "Tip (m)")], {}, "DFS")
    assert _settles(t, fast) < 0.01 and fig.axes[1].get_xlim() == pytest.approx((0.0, 0.05 * t[-1]))


def test_runs_that_all_settle_early_end_the_time_axis_and_runs_that_ring_keep_the_horizon():
    t = np.arange(3000) * 1e-3
    quick, slower = _ringing(t, 25.0), _ringing(t, 12.0)
    hub = 3e-4 * (1 - np.exp(-20 * t))  # settles at an offset, as the hub angle does
    settle = max(_settles(t, slower), _settles(t, hub))
    fig = plotting.responses(t, {"paper gains": {"tip": slower, "hub": hub}, "tuned": {"tip": quick, "hub": hub}}, [("tip", "Tip (m)"), ("hub", "Hub (rad)")], {}, "tuned")
    assert len(fig.axes) == 2 and fig.axes[0].get_xlim() == pytest.approx((0.0, 1.25 * settle)) and settle < 1.0
    note = f"from {np.format_float_positional(settle, precision=3, fractional=False, trim='-')} s to the horizon (3 s) every run stays within 1% of its largest excursion from its final value"
    assert [text.get_text() for text in fig.axes[1].texts] == [note]
    _assert_note_below_the_axis(fig, fig.axes[1])
    # a run that rings to the end (or settles past a third of the horizon) keeps the whole horizon, alone
    for decay in (0.8, 2.0):  # 1 % of the peak never, and at 2.3 s
        fig = plotting.responses(t, {"open_loop": {"tip": _ringing(t, decay)}}, [("tip", "Tip (m)")], {}, "open loop")
        assert len(fig.axes) == 1 and fig.axes[0].get_xlim()[1] >= 3.0 and not fig.axes[0].texts
    # a run that diverged, or holds a NaN, is not settled, however it ends: the others are
    # shown beside the whole horizon, not alone
    broken = quick.copy()
    broken[100] = np.nan
    for run, div in (({"tip": quick}, {"tuned": True}), ({"tip": broken}, {})):
        fig = plotting.responses(t, {"paper gains": {"tip": slower}, "tuned": run}, [("tip", "Tip (m)")], div, "tuned")
        assert len(fig.axes) == 2 and fig.axes[1].get_xlim() == pytest.approx((0.0, 1.25 * _settles(t, slower)))
    # a long horizon in plain seconds (it read "2e+02" and "3e+03"); no time at all draws empty axes
    long = np.arange(3000) * 1.0
    fig = plotting.responses(long, {"a": {"tip": _ringing(long / 1000, 25.0)}}, [("tip", "Tip (m)")], {}, "long")
    assert "to the horizon (3000 s)" in fig.axes[0].texts[0].get_text()
    assert len(plotting.responses(np.zeros(0), {"a": {"tip": np.zeros(0)}}, [("tip", "Tip (m)")], {}, "empty").axes) == 1


def test_psd_limits_hold_every_curve_up_to_the_drawn_frequency():
    freqs = np.linspace(0.0, 500.0, 501)
    a, b = np.full(501, 1e-8), np.full(501, 1e-12)
    a[300], b[10] = 1.0, 0.0  # beyond 150 Hz: not drawn; a zero: not on a log axis
    lo, hi = plotting.psd_limits(freqs, [a, b], [13.3, 36.5])
    assert lo == pytest.approx(1e-12 / 10**0.2) and hi == pytest.approx(1e-8 * 10**0.2)  # 5 % of the 4 decades each side
    assert plotting.psd_limits(freqs, [a], [200.0]) == pytest.approx((1e-8 / 10**0.4, 10**0.4))  # up to 300 Hz: 8 decades
    assert plotting.psd_limits(freqs, [np.zeros(501)], [13.3]) is None
    with pytest.raises(ValueError, match=r"curves\[1\] must have shape \(501,\) \(one PSD value per frequency of freqs\); got \(500,\)"):
        plotting.psd_limits(freqs, [a, b[:500]], [13.3])
    ax = plotting.psds(freqs, {"open_loop": a, "dfs": b}, [13.3], "PSD", "t", ylim=(1e-13, 1e-7)).axes[0]
    assert ax.get_ylim() == pytest.approx((1e-13, 1e-7))


def test_responses_mark_a_settling_time_on_its_signals_panels():
    """fig5 and fig7 showed neither the settling time report.md gives nor where it falls: the
    settling time is a dotted line in the run's colour on its signal's panels, named once."""
    t = np.arange(3000) * 1e-3
    decay = np.exp(-20 * t) * np.cos(80 * t)
    runs = {"open_loop": {"q1": np.cos(80 * t), "tip": np.cos(80 * t)}, "dfs": {"q1": decay, "tip": 2 * decay}}
    fig = plotting.responses(t, runs, [("q1", "q1 (m)"), ("tip", "tip (m)")], {}, "t", settling={"dfs": {"q1": 0.234}})
    q1_lines = [line for ax in fig.axes[:2] for line in ax.get_lines() if list(line.get_xdata()) == [0.234, 0.234]]
    assert len(q1_lines) == 2 and q1_lines[0].get_color() == plotting._STYLES["dfs"]["color"]  # both columns of the q1 row
    assert [line.get_label() for line in q1_lines][0] == "DFS settled (q1, 2 % band): 0.234 s"
    tip_axes = fig.axes[2:]
    assert not [line for ax in tip_axes for line in ax.get_lines() if list(line.get_xdata()) == [0.234, 0.234]]
    assert "DFS settled (q1, 2 % band): 0.234 s" in [text.get_text() for text in fig.axes[0].get_legend().get_texts()]
    plotting.plt.close(fig)


def test_responses_refuse_a_settling_time_of_nothing_drawn():
    t = np.arange(10) * 1e-3
    runs = {"dfs": {"q1": np.zeros(10)}}
    for settling, match in (
        ({"fuzzy": {"q1": 0.1}}, r"settling\['fuzzy'\] must map some of the signals drawn, \['q1'\], of a run drawn, \['dfs'\]"),
        ({"dfs": {"tip": 0.1}}, r"settling\['dfs'\] must map some of the signals drawn"),
        ({"dfs": {"q1": None}}, r"settling\['dfs'\]\['q1'\] must be a settling time in s, >= 0; got None"),
        ({"dfs": {"q1": -1.0}}, r"settling\['dfs'\]\['q1'\] must be a settling time in s, >= 0; got -1.0"),
    ):
        with pytest.raises(ValueError, match=match):
            plotting.responses(t, runs, [("q1", "q1 (m)")], {}, "t", settling=settling)
