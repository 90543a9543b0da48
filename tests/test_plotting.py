"""What the figures show: labels, limits, texts and styles of the matplotlib objects."""

import numpy as np
import pytest

from jaxflex import beam, plotting
from jaxflex.scenarios import ScenarioSpec, perturbed_params


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plotting.plt.close("all")


def _capture_tune_figures(monkeypatch):
    """tuning.run._figures' calls to the plotting functions, recorded, each drawing an empty figure."""
    seen = {"responses": [], "psds": [], "loss": []}
    monkeypatch.setattr(plotting, "responses", lambda t, runs, signals, div, title, **k: seen["responses"].append((t, runs, title, k)) or plotting.plt.figure())
    monkeypatch.setattr(plotting, "psds", lambda freqs, runs, modes, ylabel, title, **k: seen["psds"].append((freqs, runs, np.asarray(modes), title, k)) or plotting.plt.figure())
    monkeypatch.setattr(plotting, "loss_curves", lambda steps, loss, vs, v, title, *a, **k: seen["loss"].append((title, a, k)) or plotting.plt.figure())
    return seen


def test_tune_psd_marks_the_modes_of_the_scenarios_own_plant(monkeypatch, tmp_path):
    # With plant uncertainty in the scenarios, a held-out arm's peaks sit away from the
    # nominal frequencies: the lines labelled "model modes" were the nominal arm's. The titles
    # name the arm each figure is of (a 0.8 m arm here, not the paper's 0.6 m).
    from tuning import run
    from tuning.tuner import Problem, TuneConfig

    arm = beam.BeamParams(length_m=0.8)
    config = TuneConfig(controller="dfs", n_scenarios=2, n_heldout=2, beam=arm, scenarios=ScenarioSpec(horizon_s=0.05, youngs_modulus_rel=0.4, payload_max_kg=0.1))
    problem = Problem(config)
    seen = _capture_tune_figures(monkeypatch)
    state = {"problem": problem, "history": [{"step": 0, "loss": 1.0, "val_objective": 1.0}], "best_step": 0, "best_raw": problem.initial_raw}
    run._figures(state, str(tmp_path), 1.0)
    marked = [call[2] for call in seen["psds"]]
    titles = {"responses": [call[2] for call in seen["responses"]], "psds": [call[3] for call in seen["psds"]], "loss": [call[0] for call in seen["loss"]]}
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


def test_tune_figures_get_the_tip_and_hub_their_psd_and_the_runs_looks(monkeypatch, tmp_path):
    """What tune's figures are handed: loss.png the kept step, the reference gains' objective
    and whether the loss holds the DFS penalty; each response the tip and the hub, each PSD
    the tip's, with the reference gains in their controller's look."""
    from jaxflex.analysis import welch
    from tuning import run
    from tuning.tuner import Problem, TuneConfig

    config = TuneConfig(controller="dfs", n_scenarios=2, n_heldout=1, scenarios=ScenarioSpec(horizon_s=0.05))
    problem = Problem(config)
    seen = _capture_tune_figures(monkeypatch)
    history = [{"step": s, "loss": 1.0 - 0.1 * s, "val_objective": 1.0 if s % 2 == 0 else None} for s in range(5)]
    state = {"problem": problem, "history": history, "best_step": 4, "best_raw": problem.initial_raw}
    assert run._figures(state, str(tmp_path), 0.75) == ["loss.png", "response_0.png", "psd_0.png", "response_1.png", "psd_1.png"]
    (_, args, kwargs), = seen["loss"]
    assert args == (4, ("paper", 0.75)) and kwargs == {"penalised": True}
    t, runs, title, kwargs = seen["responses"][0]
    assert title.startswith("dfs: paper vs tuned gains, paper scenario")
    # the paper scenario starts at q1 = 1 mm with the hub at rest at 0: the tip's deflection is
    # phi_1(L) q1 with |phi_1(L)| = 2 (report.md's normalisation), the hub angle 0
    for name in ("paper gains", "tuned"):
        assert abs(runs[name]["tip"][0]) == pytest.approx(2e-3, rel=1e-9)
        assert runs[name]["hub"][0] == 0.0
    assert kwargs == {"style_of": {"paper gains": "dfs"}}
    freqs, psd, _, _, kwargs = seen["psds"][0]
    assert kwargs == {"style_of": {"paper gains": "dfs"}}
    assert freqs.max() == pytest.approx(0.5 / config.scenarios.dt)  # up to the loop's Nyquist frequency
    for name in ("paper gains", "tuned"):  # the PSD of the tip deflection drawn beside it
        _, expected = welch(np.asarray(runs[name]["tip"]), 1 / config.scenarios.dt, nperseg=min(1024, t.shape[0]))
        np.testing.assert_allclose(psd[name], np.asarray(expected), rtol=1e-9)
    # include_paper = false: no "paper scenario" figure (member 0 of the batch is a drawn one)
    config = TuneConfig(controller="dfs", n_scenarios=2, n_heldout=1, scenarios=ScenarioSpec(horizon_s=0.05, include_paper=False))
    problem = Problem(config)
    seen = _capture_tune_figures(monkeypatch)
    state = {"problem": problem, "history": [{"step": 0, "loss": 1.0, "val_objective": 1.0}], "best_step": 0, "best_raw": problem.initial_raw}
    assert run._figures(state, str(tmp_path), 1.0) == ["loss.png", "response_0.png", "psd_0.png"]
    assert [title.split("\n")[0] for _, _, title, _ in seen["responses"]] == ["dfs: paper vs tuned gains, held-out scenario 1"]


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
    assert fig.axes[0].get_title() == "DFS stability: 0.9\u00a0m arm, 6 modes at 13.3, 36.5,\n115, 241, 412, 628\u00a0Hz, sampled at 1\u00a0ms (zoh)"


def test_a_wrapped_title_has_lines_of_about_equal_length_and_keeps_numbers_with_their_units():
    # wrapped greedily at 75 characters, the 3-mode chart's title ended in a lone "(zoh)", the
    # 4-mode one's in "1\nms (zoh)"
    three = "DFS stability: 0.9 m arm, 3 modes at 13.3, 36.5, 115 Hz, sampled at 1 ms (zoh)"
    assert plotting._title_lines(three, 75) == "DFS stability: 0.9\u00a0m arm, 3 modes at\n13.3, 36.5, 115\u00a0Hz, sampled at 1\u00a0ms (zoh)"
    four = "DFS stability: 0.9 m arm, 4 modes at 13.3, 36.5, 115, 241 Hz, sampled at 1 ms (zoh)"
    assert plotting._title_lines(four, 75) == "DFS stability: 0.9\u00a0m arm, 4 modes at 13.3,\n36.5, 115, 241\u00a0Hz, sampled at 1\u00a0ms (zoh)"
    two = "DFS stability: 0.5 m arm, 2 modes at 13.3, 36.5 Hz, sampled at 1 ms (zoh)"  # 73 characters: one line
    assert plotting._title_lines(two, 75) == two.replace("5 m", "5\u00a0m").replace("5 Hz", "5\u00a0Hz").replace("1 ms", "1\u00a0ms")
    assert plotting._title_lines("x" * 100, 75) == "x" * 50 + "\n" + "x" * 50  # a word longer than a line: split, in halves
    assert plotting._title_lines("", 75) == "" and plotting._title_lines("2 modes", 75) == "2 modes"  # "modes" is no unit


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


def test_arm_label_of_one_mode_is_singular():
    # "mode{'s' if n > 1}" -- one mode reads "1 mode", two "2 modes" (docstring's example)
    assert plotting.arm_label(0.6, [15.7]) == "0.6 m arm, 1 mode at 15.7 Hz"
    assert plotting.arm_label(0.6, [13.32, 36.47]) == "0.6 m arm, 2 modes at 13.3, 36.5 Hz"


def test_settling_time_of_zero_is_accepted_and_a_bool_is_refused():
    # the docstring refuses "a time that is not a number >= 0": 0 is allowed, True is not a number
    t = np.arange(10) * 1e-3
    runs = {"dfs": {"q1": np.zeros(10)}}
    fig = plotting.responses(t, runs, [("q1", "q1 (m)")], {}, "t", settling={"dfs": {"q1": 0.0}})
    assert any(list(line.get_xdata()) == [0.0, 0.0] for line in fig.axes[0].get_lines())
    with pytest.raises(ValueError, match=r"settling\['dfs'\]\['q1'\] must be a settling time in s, >= 0; got True"):
        plotting.responses(t, runs, [("q1", "q1 (m)")], {}, "t", settling={"dfs": {"q1": True}})


def test_a_run_settling_between_a_third_and_half_of_the_horizon_keeps_the_whole_horizon():
    # ZOOM_FRACTION = 1/3: a run settling at ~1.2 s of 3 s is not zoomed
    t = np.arange(3000) * 1e-3
    v = _ringing(t, np.log(100) / 1.2)
    settle = _settles(t, v)
    assert 1.0 < settle < 1.5  # past a third, before half
    fig = plotting.responses(t, {"dfs": {"tip": v}}, [("tip", "Tip (m)")], {}, "t")
    assert len(fig.axes) == 1 and fig.axes[0].get_xlim()[1] >= 3.0 and not fig.axes[0].texts


def test_a_settling_time_marks_its_own_signals_row():
    # a settling time of the second signal is drawn on the second row's panels only
    t = np.arange(3000) * 1e-3
    decay = np.exp(-20 * t) * np.cos(80 * t)
    runs = {"open_loop": {"q1": np.cos(80 * t), "tip": np.cos(80 * t)}, "dfs": {"q1": decay, "tip": 2 * decay}}
    fig = plotting.responses(t, runs, [("q1", "q1 (m)"), ("tip", "tip (m)")], {}, "t", settling={"dfs": {"tip": 0.3}})
    axes = np.array(fig.axes).reshape(2, 2)
    marked = [[any(list(line.get_xdata()) == [0.3, 0.3] for line in ax.get_lines()) for ax in row] for row in axes]
    assert marked == [[False, False], [True, True]]


def test_a_settling_time_that_is_not_finite_is_not_drawn():
    # "a time that is not finite is not drawn"
    t = np.arange(3000) * 1e-3
    runs = {"dfs": {"q1": np.cos(80 * t)}}
    fig = plotting.responses(t, runs, [("q1", "q1 (m)")], {}, "t", settling={"dfs": {"q1": float("inf")}})
    lines = fig.axes[0].get_lines()
    assert [line.get_label() for line in lines] == ["DFS"]
    assert fig.axes[0].get_xlim()[1] < 10.0


def test_axes_scaled_to_settled_runs_leave_a_margin():
    # the settled runs' range, padded: their extremes are not on the frame
    t = np.linspace(0.0, 1.0, 101)
    decay = 1e-3 * np.exp(-5 * t) * np.cos(60 * t)
    fig = plotting.responses(t, {"dfs": {"q1": decay}, "open_loop": {"q1": 1e35 * t**40}}, [("q1", "q1 (m)")], {"open_loop": True}, "t")
    lo, hi = fig.axes[0].get_ylim()
    span = decay.max() - decay.min()
    assert lo < decay.min() - 0.05 * span and hi > decay.max() + 0.05 * span


def test_psd_default_upper_frequency_is_150_hz_or_one_and_a_half_times_the_highest_mode():
    # psd_limits hold values up to max(150, 1.5 f_max) and no further
    freqs = np.linspace(0.0, 500.0, 501)
    base = np.full(501, 1e-8)
    spike = base.copy()
    spike[120] = 1.0  # under 150 Hz: held even when the modes are low
    lo, hi = plotting.psd_limits(freqs, [spike], [13.3, 36.5])
    assert hi > 1.0
    spike = base.copy()
    spike[350] = 1.0  # beyond 1.5 * 200 = 300 Hz: not drawn, not held
    lo, hi = plotting.psd_limits(freqs, [spike], [200.0])
    assert hi < 1e-6  # the flat 1e-8 only, with its margin


def test_psds_mark_only_the_modes_drawn_and_name_a_non_finite_run():
    # modes above fmax are not marked; a non-finite run is named, not drawn; log scale
    freqs = np.linspace(0.0, 500.0, 501)
    good, bad = np.full(501, 1e-6), np.full(501, np.nan)
    ax = plotting.psds(freqs, {"open_loop": good, "dfs": bad}, [13.3, 200.0], "PSD", "t", fmax=100.0).axes[0]
    assert ax.get_yscale() == "log"
    verticals = [line for line in ax.get_lines() if line.get_label().startswith("model modes")]
    assert [line.get_xdata()[0] for line in verticals] == [13.3] and verticals[0].get_label() == "model modes (13.3 Hz)"
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert "DFS (non-finite, not drawn)" in labels
    drawn = [line for line in ax.get_lines() if line.get_label() == "DFS (non-finite, not drawn)"]
    assert all(len(line.get_xdata()) == 0 for line in drawn)


def test_paper_bars_do_not_cover_the_estimators_bars():
    # one bar per estimator plus the paper's, side by side in each group
    red = {"hann-1024": {"dfs": [60.0, 50.0], "fuzzy": [40.0, 30.0]}, "hann-256": {"dfs": [55.0, 45.0], "fuzzy": [35.0, 25.0]}}
    ax = plotting.reduction_bars(red, {"dfs": [123.4, 66.9], "fuzzy": [102.2, 23.2]}).axes[0]
    spans = sorted((p.get_x(), p.get_x() + p.get_width()) for p in ax.patches)
    assert len(spans) == 12
    assert all(a[1] <= b[0] + 1e-9 for a, b in zip(spans, spans[1:]))  # no two bars overlap


def test_percentile_band_spans_its_pair_and_the_median_is_its_own_row():
    # the p5-p95 band lies between bands p5 and p95; the median line is the p50 row
    t = np.linspace(0.0, 1.0, 11)
    bands = np.stack([-2.0 - t, 0.5 + 0 * t, 3.0 + t])  # p5, p50, p95
    ax = plotting.percentile_bands(t, bands, [5.0, 50.0, 95.0], "y", "t").axes[0]
    (band,) = ax.collections
    ys = band.get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(-3.0) and ys.max() == pytest.approx(4.0)
    (median,) = [line for line in ax.get_lines() if line.get_label() == "median"]
    np.testing.assert_array_equal(median.get_ydata(), bands[1])


def test_stability_chart_marks_the_operating_point_in_ms_and_no_crossing_off_the_chart():
    # tau is drawn in ms; a first destabilising delay beyond the chart's delays is no dot
    k, tau = np.linspace(0, 60, 7), np.arange(1, 13) * 1e-3
    radius = np.full((12, 7), 0.9)
    fig = plotting.stability_chart(k, tau, radius, -np.ones((12, 7)), np.full(7, 0.5), point=(20.0, 0.004))
    ax = fig.axes[0]
    star = [line for line in ax.get_lines() if line.get_marker() == "*"]
    assert [(float(line.get_xdata()[0]), float(line.get_ydata()[0])) for line in star] == [(20.0, 4.0)]
    assert not [line for line in ax.get_lines() if line.get_marker() == "o"]
    assert "continuous: first destabilising delay (exact crossings)" not in [t.get_text() for t in ax.get_legend().get_texts()]


def test_calibration_frequencies_on_a_log_scale_over_a_decade_and_damping_of_the_measured_modes():
    # "log scale over a decade or more"; P25: measured damping of modes 1..n_d only
    fig = plotting.calibration(np.array([13.0, 140.0]), np.array([13.5, 145.0]), np.array([13.0, 140.0]), "t", np.array([0.01]), np.array([0.01, 0.012]))
    assert fig.axes[0].get_yscale() == "log"
    measured = [line for line in fig.axes[2].get_lines() if line.get_label() == "measured"]
    assert list(measured[0].get_xdata()) == [1]
    fig = plotting.calibration(np.array([13.0, 36.0]), np.array([13.5, 37.0]), np.array([13.0, 36.0]), "t")
    assert fig.axes[0].get_yscale() == "linear"


def test_histograms_log_bins_from_three_decades_and_count_non_finite_values():
    # "three decades or more" get a log axis; non-finite values counted in the title
    fig = plotting.histograms({"a": np.array([1.0, 50.0, 2000.0]), "b": np.array([1.0, 2.0, np.nan, np.inf, 3.0])}, {}, "t")
    assert fig.axes[0].get_xscale() == "log"
    assert fig.axes[1].get_title() == "b (2 non-finite)"


def test_identification_draws_the_model_against_the_record():
    # the "modes identified" line is the model's values, the "record" line the record's
    t = np.linspace(0.0, 1.0, 11)
    record = np.stack([np.sin(t), np.cos(t)], axis=1)
    model = 0.5 * record[3:]
    fig = plotting.identification(t, record, t[3:], model, ["hub", "tip"], "t")
    for ax, col in zip(fig.axes, range(2)):
        lines = {line.get_label(): line for line in ax.get_lines()}
        np.testing.assert_array_equal(lines["record"].get_ydata(), record[:, col])
        np.testing.assert_array_equal(lines["modes identified"].get_ydata(), model[:, col])


def test_identification_ends_where_the_record_settles_and_zooms_on_the_slowest_mode():
    """calibrate --record drew a 100 s record of a decay over about 10 s as one solid band:
    the whole-record column now ends a quarter past the time from which every channel stays
    within 1 % of its largest excursion, and a second column shows 5 periods of the slowest
    mode from the window's start, where the record and the model can be told apart."""
    t = np.arange(0.0, 100.0, 1e-3)
    hub = np.exp(-0.5 * t) * np.cos(2 * np.pi * 13.0 * t) + 0.3 * np.exp(-0.8 * t) * np.cos(2 * np.pi * 36.0 * t)
    tip = 0.5 * np.exp(-0.5 * t) * np.cos(2 * np.pi * 13.0 * t)
    record = np.stack([hub, tip], axis=1)
    start = 0.25
    window = t >= start
    fig = plotting.identification(t, record, t[window], 0.9 * record[window], ["hub", "tip"], "tap.csv", period_s=1 / 13.0)
    whole, zoom = np.array(fig.axes).reshape(2, 2).T
    settle = max(_settles(t, hub), _settles(t, tip))
    assert 8.0 < settle < 10.0  # exp(-0.5 t) falls to 1 % at 9.2 s
    assert whole[0].get_xlim() == pytest.approx((0.0, 1.25 * settle))
    (note,) = whole[1].texts
    assert note.get_text() == f"from {settle:.3g} s to the record's end (100 s) every channel stays within 1% of its largest excursion from its last value"
    assert zoom[0].get_xlim() == pytest.approx((start, start + 5 / 13.0))
    assert zoom[0].get_title() == "5 periods of the slowest mode (0.0769 s each)"
    for ax, y in zip(zoom, (hub, tip)):  # scaled to the stretch shown, not to the whole record
        shown = y[(t >= start) & (t <= start + 5 / 13.0)]
        lo, hi = ax.get_ylim()
        assert lo < shown.min() and shown.max() < hi and hi - lo < 1.5 * (shown.max() - shown.min())
        # it draws its window and a sample either side, not the whole record under a limit
        # (which took as long to draw as the whole-record column)
        lines = {line.get_label(): line for line in ax.get_lines()}
        rec, mod = lines["record"].get_xdata(), lines["modes identified"].get_xdata()
        assert rec[0] < start <= rec[1] and rec[-2] <= start + 5 / 13.0 < rec[-1]
        assert mod[0] == t[window][0] and mod[-2] <= start + 5 / 13.0 < mod[-1]
        np.testing.assert_array_equal(lines["record"].get_ydata(), y[np.isin(t, rec)])
        np.testing.assert_array_equal(lines["modes identified"].get_ydata(), 0.9 * y[np.isin(t, mod)])
    for ax in whole:  # so does the whole-record column, up to its end a quarter past the settling
        lines = {line.get_label(): line for line in ax.get_lines()}
        rec, mod = lines["record"].get_xdata(), lines["modes identified"].get_xdata()
        assert rec[0] == 0.0 and rec[-2] <= 1.25 * settle < rec[-1]
        assert mod[0] == t[window][0] and mod[-2] <= 1.25 * settle < mod[-1]
    # a hub that drifts does not settle: the whole record, no note, and one column without a period
    drift = np.stack([hub + 1e-3 * t, tip], axis=1)
    fig = plotting.identification(t, drift, t, drift, ["hub", "tip"], "tap.csv")
    assert len(fig.axes) == 2 and fig.axes[0].get_xlim()[1] >= 99.9 and not fig.axes[1].texts
    assert {line.get_label(): np.size(line.get_xdata()) for line in fig.axes[0].get_lines()}["record"] == t.size
    # nor is a record whose window identified starts after it settled: the view would hide the model
    late = t >= 50.0
    fig = plotting.identification(t, record, t[late], record[late], ["hub", "tip"], "tap.csv")
    assert fig.axes[0].get_xlim()[1] >= 99.9 and not fig.axes[1].texts
    assert {line.get_label(): np.size(line.get_xdata()) for line in fig.axes[0].get_lines()}["modes identified"] == late.sum()
