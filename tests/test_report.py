"""`jaxflex reproduce` end to end, results.json schema, atomic writes, and the README staying true."""

import copy
import json
import math
import os
import re
import signal
import stat
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex import beam, cli, fileio, plotting
from jaxflex.plant import make_plant
from jaxflex.report import FIGURES, reproduce

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce")
    assert cli.main(["reproduce", "--out", str(out)]) == 0
    return out, json.loads((out / "results.json").read_text())


def test_results_json_has_the_documented_keys(reproduced):
    out, res = reproduced
    assert res["model"]["n_modes"] == 2
    freqs = res["model"]["natural_frequencies_hz"]
    assert freqs == sorted(freqs) and len(freqs) == 2
    np.testing.assert_allclose(freqs, np.asarray(beam.natural_frequencies_hz(beam.BeamParams(), 2)), rtol=1e-6)
    # each mode's damping ratio, as the continuous plant's flexible poles have it (-Re s / |s|): 1 % in the 2-mode model
    with jax.enable_x64(True):
        lam = np.linalg.eigvals(np.asarray(make_plant(beam.BeamParams(), 2).A))
    flexible = sorted(lam[lam.imag > 1.0], key=abs)
    np.testing.assert_allclose(res["model"]["damping_ratios"], [-s.real / abs(s) for s in flexible], rtol=1e-5)
    np.testing.assert_allclose(res["model"]["damping_ratios"], 0.01, rtol=1e-5)
    for run in ("open_loop", "dfs", "fuzzy"):
        for sig in ("q1", "tip_deflection_m", "hub_angle_rad"):
            assert set(res["runs"][run][sig]) >= {"min", "max", "settling_time_s"}
        for sig in ("q1", "hub_angle_rad"):
            assert len(res["runs"][run]["samples"][sig]) == 3
    for run in ("dfs", "fuzzy"):
        assert len(res["vibration_reduction_db"][run]) == 2
        assert all(v > 0 for v in res["vibration_reduction_db"][run])  # both controllers damp the modes
        assert res["runs"][run]["diverged"] is False
    assert set(res["psd"]) >= {"window", "nperseg", "noverlap", "fs_hz"}
    assert len(res["vibration_reduction_db_by_estimator"]) >= 2
    # the open loop starts where the scenario says and the controllers settle well before 3 s
    assert res["runs"]["open_loop"]["q1"]["max"] == pytest.approx(1e-3, rel=1e-9)
    assert res["runs"]["open_loop"]["q1"]["settling_time_s"] is None  # 1 % damping: not settled in 3 s
    assert 0 < res["runs"]["dfs"]["q1"]["settling_time_s"] < 1.0


def test_a_float32_run_writes_float32_digits(tmp_path):
    """results.json of a float32 run (the default; the other tests run float64) wrote the
    paper's q1(0) = 1e-3 m as 0.0010000000474974513, its float64 widening."""
    with jax.enable_x64(False):
        assert cli.main(["reproduce", "--modes", "1", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["model"]["dtype"] == "float32" and res["runs"]["open_loop"]["q1"]["max"] == 0.001
    numbers = [*res["model"]["natural_frequencies_hz"], res["model"]["rayleigh_alpha"], res["model"]["rayleigh_beta"]]
    for run in res["runs"].values():
        numbers += [run["control_effort"], *run["samples"]["q1"], *run["samples"]["hub_angle_rad"]]
        numbers += [v for signal in ("q1", "tip_deflection_m", "hub_angle_rad") for v in run[signal].values() if v is not None]
    numbers += [v for values in res["vibration_reduction_db"].values() for v in values]
    assert len(numbers) > 50 and all(str(np.float32(v)) == repr(v) for v in numbers), numbers


def test_figures_and_report_are_written(reproduced):
    out, res = reproduced
    for name in FIGURES:
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    report = (out / "report.md").read_text()
    assert "| 1 | 16 |" in report and "differs" in report
    assert f"{res['model']['natural_frequencies_hz'][0]:.3f}" in report
    assert not [p for p in os.listdir(out) if p.startswith(".tmp-")]  # no temporary files left


def test_samples_are_the_trajectory_values(reproduced):
    """results.json samples equal an independent rollout read at t = 0.1, 0.5, 1.0 s."""
    import jaxflex as jf
    from jaxflex.controllers import DFSParams, dfs

    _, res = reproduced
    plant = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")
    traj = jf.rollout(plant, dfs(), DFSParams(55.0, 0.005), jf.paper_scenario(plant))
    # To 1e-12 of q1's scale: the report runs the rollout jitted and this test eagerly, whose
    # round-off differs by 6e-16 of the scale; the sample at 1 s lies near a zero crossing
    # (1.5e-8 of a 1e-3 swing), where that is 4e-12 of the sample itself.
    q1 = np.asarray(traj.x[:, 1])
    np.testing.assert_allclose(res["runs"]["dfs"]["samples"]["q1"], q1[[100, 500, 1000]], rtol=1e-12, atol=1e-12 * np.abs(q1).max())
    tip, u = np.asarray(traj.z[:, 1]), np.asarray(traj.u)
    np.testing.assert_allclose(res["runs"]["dfs"]["tip_deflection_m"]["max"], tip.max(), rtol=1e-12)
    np.testing.assert_allclose(res["runs"]["dfs"]["control_effort"], np.sum(u**2) * 1e-3, rtol=1e-10)


def test_reported_numbers_against_independent_computations(reproduced):
    """Every dB figure (tip deflection under each estimator, q1 under the default), the
    settling times, the Rayleigh coefficients and the report's table cells, recomputed
    from independent rollouts with scipy's Welch, the metrics' plain-Python reading and
    the closed-form Rayleigh fit."""
    import scipy.signal

    import jaxflex as jf
    from jaxflex.controllers import by_name
    from jaxflex.report import ESTIMATORS
    from tests.test_metrics import _settling_reference

    out, res = reproduced
    arm = jf.BeamParams()
    plant = jf.discretize(jf.make_plant(arm, 2), 1e-3, "rk4")
    scenario = jf.paper_scenario(plant)
    traj = {name: jf.rollout(plant, *by_name(name, dt=1e-3), scenario) for name in ("open_loop", "dfs", "fuzzy")}
    modes = np.asarray(jf.beam.natural_frequencies_hz(arm, 2))

    def reduction(signal: str, settings) -> dict[str, list[float]]:
        pick = (lambda tr: tr.z[:, 1]) if signal == "tip" else (lambda tr: tr.x[:, 1])
        spectra = {
            name: scipy.signal.welch(np.asarray(pick(tr)), fs=1e3, window=settings.window, nperseg=settings.nperseg, noverlap=settings.noverlap, detrend=settings.detrend)
            for name, tr in traj.items()
        }
        f, open_psd = spectra["open_loop"]
        out = {}
        for run in ("dfs", "fuzzy"):
            values = []
            for mode in modes:  # the open loop's peak bin within 15 % of the model's frequency
                band = np.flatnonzero(np.abs(f - mode) <= 0.15 * mode)
                peak = band[np.argmax(open_psd[band])]
                values.append(10 * np.log10(open_psd[peak] / spectra[run][1][peak]))
            out[run] = values
        return out

    for name, settings in ESTIMATORS.items():
        expected = reduction("tip", settings)
        for run in ("dfs", "fuzzy"):
            np.testing.assert_allclose(res["vibration_reduction_db_by_estimator"][name][run], expected[run], rtol=1e-6, err_msg=name)
    first = next(iter(ESTIMATORS))
    assert res["vibration_reduction_db"] == res["vibration_reduction_db_by_estimator"][first] and first == "hann-1024"
    q1 = reduction("q1", ESTIMATORS[first])
    for run in ("dfs", "fuzzy"):
        np.testing.assert_allclose(res["vibration_reduction_db_q1"][run], q1[run], rtol=1e-6)
    # the least reduction over each mode's region: the open loop's peak bin against the closed
    # loop's highest bin from f1 / 2, through the geometric midpoints, to 2 fn
    settings = ESTIMATORS[first]
    # the default estimator as README's table states it: Hann, 1024 samples, half overlap
    assert (settings.window, settings.nperseg, settings.noverlap, settings.detrend) == ("hann", 1024, 512, "constant")
    spectra = {name: scipy.signal.welch(np.asarray(tr.z[:, 1]), fs=1e3, window=settings.window, nperseg=settings.nperseg, noverlap=settings.noverlap, detrend=settings.detrend) for name, tr in traj.items()}
    f, open_psd = spectra["open_loop"]
    edges = [modes[0] / 2, float(np.sqrt(modes[0] * modes[1])), 2 * modes[1]]
    for run in ("dfs", "fuzzy"):
        closed = spectra[run][1]
        for m, mode in enumerate(modes):
            band = np.flatnonzero(np.abs(f - mode) <= 0.15 * mode)
            region = np.flatnonzero((f >= edges[m]) & (f < edges[m + 1]))
            top = region[np.argmax(closed[region])]
            assert res["region_reduction_db"][run]["db"][m] == pytest.approx(10 * np.log10(open_psd[band].max() / closed[top]), rel=1e-5)
            assert res["region_reduction_db"][run]["closed_loop_highest_hz"][m] == pytest.approx(f[top])
            assert res["region_reduction_db"][run]["is_peak"][m] == bool(closed[top] >= max(closed[top - 1], closed[top + 1]))
    # DFS moves mode 1 from 13.3 to 17.6 Hz, 12 dB less reduced there than at the open loop's bin, and the report says so
    assert res["region_reduction_db"]["dfs"]["is_peak"][0] and res["region_reduction_db"]["dfs"]["closed_loop_highest_hz"][0] == pytest.approx(17.578125)
    assert res["vibration_reduction_db"]["dfs"][0] - res["region_reduction_db"]["dfs"]["db"][0] > 10
    assert f"DFS moves mode 1's resonance from 13.32 to 17.6 Hz, where it is {res['region_reduction_db']['dfs']['db'][0]:.1f} dB below the open-loop peak" in (out / "report.md").read_text()

    # settling times: the 2 % band of the README
    for run in ("dfs", "fuzzy"):
        for name, values in (("q1", traj[run].x[:, 1]), ("tip_deflection_m", traj[run].z[:, 1])):
            assert res["runs"][run][name]["settling_time_s"] == pytest.approx(_settling_reference(np.asarray(values), 1e-3), abs=1e-12)

    # Rayleigh: both flexible modes of the 2-mode model at the damping ratio
    w1, w2 = 2 * np.pi * modes
    zeta = arm.damping_ratio
    np.testing.assert_allclose([res["model"]["rayleigh_alpha"], res["model"]["rayleigh_beta"]], [2 * zeta * w1 * w2 / (w1 + w2), 2 * zeta / (w1 + w2)], rtol=1e-9)

    # report.md's cells are those numbers, in their columns
    report = (out / "report.md").read_text()
    exact, zeta = res["model"]["exact_natural_frequencies_hz"], res["model"]["damping_ratios"]  # the ratios checked against the plant's poles above
    assert f"| 1 | 16 | {modes[0]:.3f} | {zeta[0]:.3g} | {exact[0]:.3f} |" in report
    assert f"| 2 | 55 | {modes[1]:.3f} | {zeta[1]:.3g} | {exact[1]:.3f} |" in report
    dfs = res["runs"]["dfs"]
    assert f"| DFS | settling time | 0.25 s | {dfs['q1']['settling_time_s']:.3f} s | {dfs['tip_deflection_m']['settling_time_s']:.3f} s |" in report


def test_report_states_whether_the_papers_ordering_holds(reproduced):
    """The paper concludes that DFS reduces vibration more than the fuzzy controller; the
    report says "agrees" only when jaxflex's DFS reduction is the larger at every mode."""
    from jaxflex.report import _report_md

    _, res = reproduced
    for dfs_db, fuzzy_db, word in (([20.0, 20.0], [10.0, 10.0], "agrees"), ([20.0, 5.0], [10.0, 10.0], "does not agree"), ([5.0, 5.0], [10.0, 10.0], "does not agree")):
        text = _report_md({**res, "vibration_reduction_db": {**res["vibration_reduction_db"], "dfs": dfs_db, "fuzzy": fuzzy_db}})
        assert f"than the fuzzy controller at both modes {word} with" in text, (dfs_db, fuzzy_db)


def test_frequency_notes_say_whose_value_is_above_the_pinned_free_bound(reproduced):
    """The paper's 16 Hz is above the pinned-free bound (14.33 Hz); the 2-mode model's 13.32 is
    not; a 1-mode model's 15.70 is too, and the note said only "above the bound" beside it."""
    from jaxflex.beam import BeamParams, exact_natural_frequencies_hz, natural_frequencies_hz
    from jaxflex.report import _report_md

    _, res = reproduced
    bound = res["model"]["pinned_free_bound_hz"]
    two = _report_md(res)
    assert "| differs: the paper's is above the pinned-free bound |" in two and "model's too" not in two
    one = float(natural_frequencies_hz(BeamParams(), 1)[0])
    assert one > bound > float(exact_natural_frequencies_hz(BeamParams(), 1)[0])
    model = {**res["model"], "n_modes": 1, "natural_frequencies_hz": [one]}
    text = _report_md({**res, "model": model})
    assert "| differs: the paper's is above the pinned-free bound; the 1-mode model's too: assumed-mode frequencies converge to the exact ones from above |" in text


def test_an_amplified_mode_is_said_to_be(reproduced):
    """A negative reduction (DFS at mode 4 of the 4-mode model: -16.5 dB) is named as an amplification."""
    from jaxflex import plotting
    from jaxflex.report import _report_md

    _, res = reproduced
    assert "amplification" not in _report_md(res)  # the paper's 2-mode run damps both modes
    for dfs_db, by in (([10.0, -16.46], "16.5"), ([10.0, -0.3], "0.3")):  # any negative value, however small
        text = _report_md({**res, "vibration_reduction_db": {**res["vibration_reduction_db"], "dfs": dfs_db}})
        assert f"A negative reduction is an amplification, the closed loop raising the vibration; with the default estimator: {plotting.LABELS['dfs']} at mode 2 (by {by} dB)." in text
    assert "amplification" not in _report_md({**res, "vibration_reduction_db": {**res["vibration_reduction_db"], "dfs": [10.0, 0.0]}})


def test_bad_modes_is_refused(capsys):
    with pytest.raises(SystemExit):
        cli.main(["reproduce", "--modes", "0"])
    assert "expected an integer >= 1" in capsys.readouterr().err


def test_modes_the_papers_rk4_step_cannot_hold_are_refused_before_any_work(tmp_path, capsys):
    """At 8 modes the highest (516 Hz) has omega dt = 3.25 > 2.8 at 1 ms: every RK4 run blew
    up and the figure code crashed on the missing dB values. Refused by name, nothing written."""
    from jaxflex.beam import BeamParams, natural_frequencies_hz

    assert cli.main(["reproduce", "--modes", "8", "--out", str(tmp_path / "r8")]) == 2
    err = capsys.readouterr().err
    # the mode named is the 8-mode model's highest: |lambda| of a damped pair is its undamped
    # frequency, and RK4's stability edge for it is omega dt ~ 2.83 (mode 7 at 1 ms is below)
    highest = np.asarray(natural_frequencies_hz(BeamParams(), 8), float)
    assert 2 * np.pi * highest[-1] * 1e-3 > 2.83 > 2 * np.pi * np.asarray(natural_frequencies_hz(BeamParams(), 7), float)[-1] * 1e-3
    assert "n_modes = 8 (--modes)" in err and f"|s| = 2 pi x {highest[-1]:.4g} Hz" in err and "n_modes <= 7" in err
    assert not (tmp_path / "r8").exists()
    assert cli.main(["reproduce", "--modes", "30", "--out", str(tmp_path / "r30")]) == 2  # the same largest count, searched from 1 up (from 29 down, 100 modes took 2 min)
    err = capsys.readouterr().err
    assert "n_modes = 30 (--modes)" in err and "n_modes <= 7" in err and not (tmp_path / "r30").exists()


def test_reduction_bars_leave_out_a_diverged_run():
    from jaxflex import plotting

    fig = plotting.reduction_bars({"hann-1024": {"dfs": [60.0, 70.0], "fuzzy": [None, None]}})
    heights = [p.get_height() for p in fig.axes[0].patches]
    plotting.plt.close(fig)
    assert heights == [60.0, 70.0, 0.0, 0.0]


def test_reduction_bars_legend_hides_no_bar():
    from jaxflex import plotting

    # the reproduction's figure: four estimators and the paper's bars, the tallest 123.4 dB
    db = {"hann-1024": ([68.0, 82.8], [89.0, 86.7]), "hann-256": ([52.9, 55.1], [42.6, 63.8]), "hann-3000": ([90.0, 96.5], [95.8, 97.3]), "boxcar-3000": ([28.8, 22.0], [28.8, 20.9])}
    fig = plotting.reduction_bars({est: {"dfs": d, "fuzzy": f} for est, (d, f) in db.items()}, {"dfs": [123.4, 66.9], "fuzzy": [102.2, 23.2]})
    fig.canvas.draw()
    ax = fig.axes[0]
    legend = ax.get_legend().get_window_extent()
    hidden = [p.get_height() for p in ax.patches if p.get_window_extent().overlaps(legend)]
    plotting.plt.close(fig)
    assert hidden == []


@pytest.mark.parametrize("low, scale", [(0.87, "linear"), (0.05, "log")])
def test_loss_curves_use_a_log_axis_over_a_decade_or_more(low, scale):
    from jaxflex import plotting

    steps = np.arange(20)
    fig = plotting.loss_curves(steps, np.linspace(1.0, low, 20), np.array([0, 10, 19]), np.array([1.8, 2.2, 2.0]), "t", best_step=10)
    assert fig.axes[0].get_yscale() == scale
    kept = [line for line in fig.axes[0].get_lines() if line.get_label().startswith("kept")]
    assert [line.get_label() for line in kept] == ["kept: the parameters after 10 updates"] and list(kept[0].get_xdata()) == [10, 10]
    # the held-out objective on its own axis, with its own scale (on the training loss's, a
    # 10 % fall from 1 read flat beside held-out values near 3), the kept step marked there too
    held_out = fig.axes[1]
    assert [line.get_label() for line in held_out.get_lines()][0] == "held-out objective" and held_out.get_yscale() == "linear"
    assert held_out.get_ylim()[0] > 1.5 and fig.axes[0].get_ylim()[1] < 1.5
    assert [list(line.get_xdata()) for line in held_out.get_lines()[1:]] == [[10], [10, 10]]  # the ring and the line
    plotting.plt.close(fig)


def test_loss_curves_name_the_paper_gains_objective_and_whole_steps():
    """The paper gains score 1 only for the mean of one unit weight: under the CVaR with an
    effort term they scored 3.69, on an axis that said '1 = paper gains'."""
    from jaxflex import plotting

    fig = plotting.loss_curves(np.arange(3), np.array([3.69, 3.68, 3.68]), np.array([0, 2]), np.array([4.9, 5.2]), "t", best_step=0, reference=("paper", 3.69))
    ax = fig.axes[0]
    assert ax.get_ylabel() == "Training objective\n(the paper gains score 3.69)"
    fig.canvas.draw()
    assert all(float(tick) == int(tick) for tick in ax.get_xticks())  # no step 0.25 over 2 updates
    assert ax.get_xlim() == (0.0, 2.0)  # it ran to 2.1: past the last update
    plotting.plt.close(fig)
    assert plotting.loss_curves(np.arange(3), np.ones(3), np.array([]), np.array([]), "t").axes[0].get_ylabel() == "Training objective"
    # the legend names the stability penalty only where the loss holds it (DFS alone): a fuzzy run's named one
    for penalised, label in ((False, "training loss (objective)"), (True, "training loss (objective + stability penalty)")):
        legend = plotting.loss_curves(np.arange(3), np.ones(3), np.array([]), np.array([]), "t", penalised=penalised).axes[0].get_legend()
        assert legend.get_texts()[0].get_text() == label
    plotting.plt.close("all")


def test_failed_write_keeps_the_previous_file(tmp_path):
    path = tmp_path / "results.json"
    fileio.write_json(path, {"good": 1})

    def broken(tmp):
        Path(tmp).write_text('{"half": ')
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        fileio.atomic_write(path, broken)
    assert json.loads(path.read_text()) == {"good": 1}
    assert os.listdir(tmp_path) == ["results.json"]
    fileio.write_json(path, {"x": float("nan"), "y": np.float32(2.5), "z": np.arange(2)})
    assert json.loads(path.read_text()) == {"x": None, "y": 2.5, "z": [0, 1]}


def test_atomic_writes_get_the_permissions_of_a_plain_write(tmp_path):
    plain, atomic = tmp_path / "plain.md", tmp_path / "atomic.md"
    plain.write_text("x")
    fileio.write_text(atomic, "x")  # new file: the umask's default, not the temporary file's 0o600
    assert stat.S_IMODE(atomic.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode)
    atomic.chmod(0o640)
    fileio.write_text(atomic, "y")  # replacing a file keeps its permissions
    assert stat.S_IMODE(atomic.stat().st_mode) == 0o640 and atomic.read_text() == "y"


def test_replace_outputs_renames_last_last_and_removes_stale_owned_files(tmp_path, monkeypatch):
    (tmp_path / "old_figure.png").write_text("stale")
    (tmp_path / "notes.txt").write_text("the user's")
    renamed = []
    real_replace = os.replace
    monkeypatch.setattr(fileio.os, "replace", lambda src, dst: (renamed.append(os.path.basename(dst)), real_replace(src, dst)))
    with fileio.replace_outputs(tmp_path, owned=["old_figure.png", "a.png", "results.json", "z.md"], last="results.json") as stage:
        for name in ("results.json", "z.md", "a.png"):
            Path(stage, name).write_text(name)
        assert sorted(os.listdir(tmp_path)) == sorted(["notes.txt", "old_figure.png", os.path.basename(stage)])
    assert renamed[-1] == "results.json" and sorted(renamed) == ["a.png", "results.json", "z.md"]
    assert sorted(os.listdir(tmp_path)) == ["a.png", "notes.txt", "results.json", "z.md"]


def test_json_values_inside_tuples_are_converted(tmp_path):
    fileio.write_json(tmp_path / "t.json", {"t": (float("inf"), np.float32(1.5), (np.int64(2),))})
    assert json.loads((tmp_path / "t.json").read_text()) == {"t": [None, 1.5, [2]]}


def test_atomic_writes_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        fileio.write_text(tmp_path / "new.md", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "new.md").stat().st_mode) == 0o640


def _age(path, seconds):
    """Set back a file's or folder's modification time by ``seconds``."""
    past = os.stat(path).st_mtime - seconds
    os.utime(path, (past, past))


@pytest.mark.skipif(fileio.fcntl is None, reason="the sweep needs POSIX locks")
def test_writes_sweep_the_temporaries_of_killed_runs_only(tmp_path):
    """A run killed by SIGKILL inside replace_outputs and atomic_write leaves its .tmp-*
    folder and file; the next write into the folder removes them. A temporary that a living
    process holds, one made in the last seconds, and every other file are kept."""
    script = (
        "import os, signal, sys\n"
        "from jaxflex import fileio\n"
        "folder = sys.argv[1]\n"
        "def killed(tmp):\n"
        "    open(tmp, 'w').write('half')\n"
        "    with fileio.replace_outputs(folder, ['a.png']) as stage:\n"
        "        open(os.path.join(stage, 'a.png'), 'w').write('half')\n"
        "        os.kill(os.getpid(), signal.SIGKILL)\n"
        "fileio.atomic_write(os.path.join(folder, 'results.json'), killed)\n"
    )
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path)], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == -9, run.stderr
    left = sorted(p.name for p in tmp_path.iterdir())
    assert len(left) == 2 and all(name.startswith(".tmp-") for name in left)  # the folder and the file
    for name in left:
        _age(tmp_path / name, 60)
    (tmp_path / "keep.txt").write_text("mine")
    held = tmp_path / ".tmp-held"
    held.write_text("a living writer's")
    _age(held, 60)
    young = tmp_path / ".tmp-young"
    young.mkdir()
    fd = os.open(held, os.O_RDONLY)
    try:
        assert fileio._lock(fd)
        fileio.write_text(tmp_path / "new.md", "x")
        assert sorted(p.name for p in tmp_path.iterdir()) == [".tmp-held", ".tmp-young", "keep.txt", "new.md"]
    finally:
        os.close(fd)
    _age(young, 60)
    with fileio.replace_outputs(tmp_path, []) as stage:  # the held file is free now; the stage is not swept by the write inside
        fileio.write_text(tmp_path / "other.md", "y")
        assert os.path.isdir(stage)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt", "new.md", "other.md"]


def test_atomic_write_puts_the_data_on_disk_before_the_rename(tmp_path, monkeypatch):
    """After a power loss the file is the old or the new one: the temporary file's data is
    synced (fsync) before it is renamed over the path, not after."""
    events, real_fsync, real_replace = [], os.fsync, os.replace
    monkeypatch.setattr(fileio.os, "fsync", lambda fd: (events.append(("fsync", os.fstat(fd).st_ino)), real_fsync(fd))[1])
    monkeypatch.setattr(fileio.os, "replace", lambda src, dst: (events.append(("replace", os.stat(src).st_ino)), real_replace(src, dst))[1])
    fileio.write_text(tmp_path / "results.json", "{}")
    monkeypatch.undo()
    inode = (tmp_path / "results.json").stat().st_ino
    assert events == [("fsync", inode), ("replace", inode)]


def test_replace_outputs_keeps_the_permissions_of_the_files_it_replaces(tmp_path):
    """As atomic_write: a replaced file keeps its mode, a new one gets the umask's default."""
    (tmp_path / "results.json").write_text("old")
    (tmp_path / "results.json").chmod(0o600)
    old = os.umask(0o022)
    try:
        with fileio.replace_outputs(tmp_path, ["results.json", "new.md"]) as stage:
            Path(stage, "results.json").write_text("new")
            Path(stage, "new.md").write_text("new")
            os.chmod(os.path.join(stage, "new.md"), 0o600)  # as a temporary file is made
    finally:
        os.umask(old)
    assert (tmp_path / "results.json").read_text() == "new"
    assert stat.S_IMODE((tmp_path / "results.json").stat().st_mode) == 0o600
    assert stat.S_IMODE((tmp_path / "new.md").stat().st_mode) == 0o644


@pytest.mark.skipif(fileio.fcntl is None, reason="the run lock needs POSIX locks")
def test_run_lock_is_held_in_the_block_taken_again_inside_and_released_after(tmp_path):
    """The lock is an flock another open file cannot take while a block holds it; a block
    inside it on the same folder (another spelling of it) is let through; after the block it
    is free, and the next block holds it again (not only the first one of a process)."""
    import fcntl

    def free() -> bool:
        fd = os.open(tmp_path / fileio.RUN_LOCK, os.O_RDWR)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        finally:
            os.close(fd)
        return True

    for _ in range(2):
        with fileio.run_lock(tmp_path):
            assert not free()
            with fileio.run_lock(tmp_path / "."):
                assert not free()
            assert not free()  # the inner block leaves the outer one's lock
        assert free()


def test_a_run_into_a_file_is_refused_by_name(tmp_path):
    """tune and run_montecarlo (through run_lock) said only 'FileExistsError: [Errno 17]'."""
    from jaxflex.montecarlo import MCConfig, run_montecarlo

    (tmp_path / "f").write_text("")
    with pytest.raises(ValueError, match=f"out_dir \\(--out\\) {re.escape(repr(str(tmp_path / 'f')))} is a file, not a folder"):
        run_montecarlo(MCConfig(n_scenarios=1), tmp_path / "f", progress=False)


def test_digest_ignores_key_order_and_changed_fields_names_what_differs():
    a = {"seed": 0, "scenarios": {"dt": 0.001, "horizon_s": 3.0}, "controller": "dfs"}
    b = {"controller": "dfs", "scenarios": {"horizon_s": 3.0, "dt": 0.001}, "seed": 0}
    assert fileio.digest(a) == fileio.digest(b) and re.fullmatch(r"[0-9a-f]{16}", fileio.digest(a))
    assert fileio.digest({**a, "seed": 1}) != fileio.digest(a)
    # a key the folder's record lacks (written by an older version) is no change named, nor a KeyError
    assert fileio.changed_fields(a, {**b, "seed": 3, "new_option": 1}) == "changed: seed: 0 -> 3"
    assert fileio.changed_fields(a, {**b, "new_option": 1}) == "the configuration changed"
    assert fileio.changed_fields(None, a) == "the configuration changed"
    assert fileio.changed_fields("damaged", a) == "the configuration changed"  # a record that is no table names no field
    # another program (an upgrade, an edited source) is no option to change back: it says so
    assert fileio.changed_fields({**a, "program": "x"}, {**a, "program": "y", "seed": 2}) == (
        "changed: program: 'x' -> 'y', seed: 0 -> 2; no option matches another program: start again in another --out, or resume with the program that wrote it")
    # each side of each change, into nested tables (it said "changed: n_scenarios, scenarios")
    now = {**a, "scenarios": {"dt": 0.002, "horizon_s": 3.0, "new": 1}, "percentiles": [5, 95], "beam": None}
    assert fileio.changed_fields({**a, "percentiles": [5, 50, 95], "beam": {"length_m": 1.0}}, now) == (
        "changed: beam: {'length_m': 1.0} -> None, percentiles: [5, 50, 95] -> [5, 95], scenarios.dt: 0.001 -> 0.002")
    assert fileio.changed_fields({**a, "beam": None}, {**a, "beam": {"length_m": 1.0}}) == "changed: beam: None -> {'length_m': 1.0}"  # not a TypeError


def test_to_jsonable_keeps_non_finite_numbers_when_asked():
    value = {"a": np.array([np.inf, 1.5]), "b": (np.float64(np.nan), -math.inf), 1: np.int64(2)}
    kept = fileio.to_jsonable(value, finite=False)
    assert kept["a"] == [math.inf, 1.5] and math.isnan(kept["b"][0]) and kept["b"][1] == -math.inf and kept["1"] == 2
    assert fileio.to_jsonable(value) == {"a": [None, 1.5], "b": [None, None], "1": 2}


def test_files_show_a_narrow_float_with_its_own_digits():
    # float32 values, as the runs compute them, read back exactly but print short; float64 and
    # integers pass unchanged, and non-finite values still become None
    above_55 = np.float32(55) + 2 * np.spacing(np.float32(55))  # exp(log(55)) in float32
    value = {"k": above_55, "c": jnp.asarray([[0.1, np.inf]], jnp.float32), "d": np.float64(0.1) + 1e-17 * 3, "n": np.arange(2)}
    out = fileio.to_jsonable(value)
    assert out == {"k": 55.000008, "c": [[0.1, None]], "d": float(np.float64(0.1) + 1e-17 * 3), "n": [0, 1]}
    assert np.float32(out["k"]) == above_55 and float(above_55) == 55.00000762939453
    assert json.loads(json.dumps(out))["c"] == [[0.1, None]]
    # float16 and bfloat16 too (bfloat16's 0.1 widened is 0.10009765625)
    assert fileio.shortest(jnp.asarray([0.1, -0.0, np.nan], jnp.bfloat16))[:2] == [0.1, -0.0] and fileio.shortest(np.float16(0.1)) == 0.1
    # a fingerprint keeps them apart: a float32 gain and the float64 number it prints as differ
    wide, narrow = (fileio.to_jsonable({"k": k}, exact=True) for k in (55.000008, np.float32(55.000008)))
    assert wide == {"k": 55.000008} and narrow == {"k": 55.00000762939453}


def test_program_changes_with_the_source_of_either_package(tmp_path, monkeypatch):
    """A resume is refused when the code of jaxflex or of tuning (the tuner, the objectives)
    changed: the fingerprint hashes every .py file of both, and no other file."""
    for name in ("jaxflex/fileio.py", "jaxflex/sub/a.py", "tuning/tuner.py"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("x = 1\n")
    monkeypatch.setattr(fileio, "__file__", str(tmp_path / "jaxflex" / "fileio.py"))

    def program() -> str:
        fileio.program.cache_clear()
        return fileio.program()

    try:
        first = program()
        (tmp_path / "tuning" / "notes.txt").write_text("not code")
        assert program() == first
        seen = {first}
        for name in ("tuning/tuner.py", "jaxflex/sub/a.py"):
            (tmp_path / name).write_text("x = 2\n")
            seen.add(program())
        assert len(seen) == 3
    finally:
        monkeypatch.undo()
        fileio.program.cache_clear()
    assert fileio.program() != first


def test_version_is_one_value_the_cli_and_the_installed_package_report(capsys):
    """``jaxflex --version`` prints the package's version, which pyproject.toml reads from
    jaxflex/__init__.py (one place), so the installed metadata says the same."""
    import importlib.metadata

    import jaxflex

    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out == f"jaxflex {jaxflex.__version__}\n"
    assert re.fullmatch(r"\d+\.\d+\.\d+", jaxflex.__version__)
    assert importlib.metadata.version("jaxflex") == jaxflex.__version__
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'dynamic = ["version"]' in pyproject and "\nversion =" not in pyproject.split("[tool.setuptools.dynamic]")[0]


def test_an_unknown_option_is_reported_with_its_commands_usage(capsys):
    """argparse reported it with the top-level usage, which lists no command's options."""
    for command in ("tune", "reproduce"):
        with pytest.raises(SystemExit) as exit_info:
            cli.main([command, "--bogus", "3"])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith(f"usage: jaxflex {command} [-h]") and err.endswith(f"jaxflex {command}: error: unrecognized arguments: --bogus 3\n")


def test_as_typed_renames_a_refusal_of_the_name_itself_only():
    """A refusal is renamed when its first word is the parameter's name: not when that name
    only begins the word (k inside "k1 must ..."), and never for unknown keys, whose first
    word is "unknown" even when a misspelt key is called that."""
    source = {"k": "[initial] k of f.toml", "unknown": "unknown of f.toml"}
    for message, said in (("k must be > 0", "[initial] k of f.toml must be > 0"), ("k1 must be > 0", "k1 must be > 0")):
        with pytest.raises(ValueError) as refused, cli._as_typed(source):
            raise ValueError(message)
        assert str(refused.value) == said
    with pytest.raises(fileio.UnknownKeys) as refused, cli._as_typed(source):
        raise fileio.UnknownKeys("config key(s)", ["unknown"], ["k"])
    assert str(refused.value) == "unknown config key(s) ['unknown']; accepted: ['k']"


def test_a_refused_option_is_named_as_typed(tmp_path, capsys):
    """The library names its parameter (learning_rate, tau_s); a value typed as an option is
    refused under the option's name, and one read from --config under its key and the file's
    name (it kept the library's name, which named no file)."""
    cases = [
        (["tune", "--lr", "nan"], "jaxflex tune: error: --lr must be a finite number > 0; got nan"),
        (["stability", "--k", "nan"], "jaxflex stability: error: --k must be finite; got nan"),
        (["stability", "--tau", "0.0055"], "jaxflex stability: error: --tau must be a whole number >= 1 of samples of dt = 0.001 s; got 0.0055 s (5.5 samples): the nearest are 0.005 s and 0.006 s"),
        (["stability", "--tau-max", "0.002"], "jaxflex stability: error: --tau-max must be at least the delay analysed, tau_s = 0.005 s, so that the chart holds that point; got 0.002 s"),
        (["stability", "--dt", "0"], "jaxflex stability: error: --dt must be a finite scalar > 0 (seconds); got 0.0"),  # it said "dt"
        (["montecarlo", "--unroll", "65"], "jaxflex montecarlo: error: --unroll must be an integer in [1, 64]; got 65"),  # it said "unroll"
        (["montecarlo", "--seed", str(2**63)], f"jaxflex montecarlo: error: --seed must be an integer in [-2**63, 2**63); got {2**63}"),
        (["tune", "--seed", str(2**63)], f"jaxflex tune: error: --seed must be an integer in [-2**63, 2**63); got {2**63}"),
    ]
    for argv, said in cases:
        assert cli.main([*argv, "--out", str(tmp_path / "o")]) == 2
        assert said + "\n" == capsys.readouterr().err.splitlines(keepends=True)[-1]  # after the model line, where one is printed
    config = tmp_path / "lr.toml"
    config.write_text("learning_rate = -1.0\n")
    assert cli.main(["tune", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == f"jaxflex tune: error: learning_rate of {config} must be a finite number > 0; got -1.0"
    # a value from --config beside a typed option of the same name is not blamed on the option
    for text, argv, said in (
        ("[scenarios]\ndt = -1.0\n", ["--dt", "0.001"], f"error: [scenarios] dt of {config} must be a finite number > 0; got -1.0"),
        ("n_modes = 0\n", ["--modes", "2"], f"error: n_modes of {config} must be an integer in [1, 100]; got 0"),  # it said ">= 1"
        ("n_modes = 101\n", [], f"error: n_modes of {config} must be an integer in [1, 100]; got 101"),  # it named no file
        ("[beam]\nlength_m = -1.0\n", [], f"error: [beam] length_m of {config} must be a finite number > 0; got -1.0"),
    ):
        config.write_text(text)
        assert cli.main(["stability", "--config", str(config), *argv, "--out", str(tmp_path / "o")]) == 2
        assert capsys.readouterr().err.splitlines()[-1] == f"jaxflex stability: {said}"
    # every command that reads a config names the file and the key: tune's, montecarlo's
    # tables and top-level keys, and calibrate's [scenarios] dt (it said "dt must be ...")
    for command, text, said in (
        (["tune"], "[scenarios]\ndt = \"x\"\n", f"[scenarios] dt of {config} must be a finite number > 0; got 'x'"),
        (["tune"], "[objective]\ntip_ise = -1.0\n", f"[objective] tip_ise of {config} must be a finite number >= 0; got -1.0"),
        (["montecarlo"], "[scenarios]\ndt = \"x\"\n", f"[scenarios] dt of {config} must be a finite number > 0; got 'x'"),
        (["montecarlo"], "unroll = 70\n", f"unroll of {config} must be an integer in [1, 64]; got 70"),
        (["calibrate", "--freqs", "14"], "[scenarios]\ndt = \"x\"\n", f"[scenarios] dt of {config} must be a finite number > 0; got 'x'"),
    ):
        config.write_text(text)
        assert cli.main([*command, "--config", str(config), "--out", str(tmp_path / "o")]) == 2
        assert capsys.readouterr().err.splitlines()[-1] == f"jaxflex {command[0]}: error: {said}"
    assert not (tmp_path / "o").exists()
    # --modes beyond the model's 100 is refused as typed (it said "n_modes must be ...")
    for argv in (["reproduce"], ["stability"], ["calibrate", "--freqs", "14"]):
        with pytest.raises(SystemExit):
            cli.main([*argv, "--modes", "101", "--out", str(tmp_path / "o")])
        assert capsys.readouterr().err.endswith(f"jaxflex {argv[0]}: error: argument --modes: expected an integer from 1 to 100; got 101\n")


def test_readme_quick_start_matches_ci():
    readme = (ROOT / "README.md").read_text()
    quick_start = readme.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)\n```", quick_start, re.S)
    assert len(blocks) == 2 and "jaxflex reproduce" in blocks[0] and "pytest" in blocks[1]
    assert blocks[1] in (ROOT / ".ci" / "run").read_text()


def test_readme_api_tour_runs(tmp_path):
    readme = (ROOT / "README.md").read_text()
    tour = readme.split("## A short tour of the API", 1)[1]  # the calibrate section has a block of its own before it
    code = re.findall(r"```python\n(.*?)\n```", tour, re.S)[0]
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "(8, 3000, 3)" in result.stdout and "(3000, 1)" in result.stdout


def test_reproduce_prints_rounded_figures_beside_the_papers(reproduced):
    _, res = reproduced
    freqs_line, db_line, moved_line = cli._reproduce_summary(res).split("\n")
    assert freqs_line.startswith("model natural frequencies: ") and freqs_line.endswith("(paper: 16, 55 Hz)")
    for f in res["model"]["natural_frequencies_hz"]:
        assert f"{f:.2f}" in freqs_line
    db = res["vibration_reduction_db"]
    expected = "DFS {:.1f}, {:.1f}; fuzzy {:.1f}, {:.1f}".format(*db["dfs"], *db["fuzzy"])
    assert db_line == f"vibration reduction (dB, {res['psd']['name']}) at modes 1, 2: {expected} (paper, modes 1, 2: DFS 123.4, 66.9; fuzzy 102.2, 23.2)"
    # the peak DFS moved off the open loop's bin, said where the 68 dB is read (only report.md said it)
    assert moved_line.startswith(f"note: DFS moves mode 1's resonance from 13.32 to 17.6 Hz, where it is {res['region_reduction_db']['dfs']['db'][0]:.1f} dB below") and moved_line.endswith("(report.md)")


def test_reproduce_summary_of_one_mode_and_a_diverged_run():
    res = {"model": {"natural_frequencies_hz": [13.3]}, "psd": {"name": "hann-1024"}, "vibration_reduction_db": {"dfs": [60.06], "fuzzy": [None]}}
    db_line = cli._reproduce_summary(res).split("\n")[1]
    assert db_line.startswith("vibration reduction (dB, hann-1024) at mode 1: DFS 60.1; fuzzy n/a (paper, modes 1, 2: ")


def test_cli_refuses_bad_outputs_before_any_work(tmp_path, capsys):
    """A file where a folder is wanted, an empty --out, a --json that is a folder, and
    distributed options without --distributed: exit 2 and one line naming the option, no
    traceback and no work done first."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        (["reproduce", "--out", str(afile)], "is a file, not a folder"),
        (["stability", "--out", str(afile)], "is a file, not a folder"),
        (["tune", "--out", ""], "--out must name a folder"),
        (["bench", "--json", str(tmp_path)], "--json must name a file"),
        (["bench", "--json", str(tmp_path / "missing" / "rows.jsonl")], "does not exist or is not writable"),
        (["montecarlo", "--coordinator", "host:1234", "--out", str(tmp_path / "m")], "--coordinator only applies with --distributed"),
    ]
    for argv, message in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)
    assert [p.name for p in tmp_path.iterdir()] == ["afile"]  # nothing was made or written


def test_cli_refuses_a_folder_it_cannot_write_in_before_any_work(tmp_path, capsys, monkeypatch):
    """An --out that exists but takes no files (read-only; faked, since root may write
    anywhere) is refused by name at once, by every command that writes one; it was found
    only when the results were written, after the work, with a bare errno message."""
    ro = tmp_path / "ro"
    ro.mkdir()

    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(cli.tempfile, "mkstemp", refused)
    for command in (["reproduce"], ["tune"], ["montecarlo"], ["stability"], ["calibrate", "--freqs", "15.5", "46.2"]):
        assert cli.main([*command, "--out", str(ro)]) == 2, command
        err = capsys.readouterr().err
        assert f"--out {str(ro)!r}: cannot write in the folder (Permission denied)" in err and "Traceback" not in err, (command, err)
    assert os.listdir(ro) == []


def test_cli_cpu_devices_has_a_ceiling_per_core(monkeypatch, capsys):
    """Hundreds of CPU devices on a few cores stalled XLA's collectives for minutes and then
    aborted the process; --cpu-devices takes at most 8 per usable core."""
    import jaxflex.bench

    monkeypatch.setattr(jaxflex.bench, "usable_cores", lambda: 2)
    assert cli._cpu_devices("16") == 16
    for command in ("tune", "montecarlo", "bench"):
        with pytest.raises(SystemExit):
            cli.main([command, "--cpu-devices", "17"])
        assert "--cpu-devices: expected an integer from 1 to 16 (8 per core this process may use); got 17" in capsys.readouterr().err


def test_cli_interrupt_exits_130_with_a_resume_hint(tmp_path, capsys, monkeypatch):
    import tuning.run

    def interrupted(config, out, **kwargs):
        if checkpointed:
            os.makedirs(out, exist_ok=True)
            (tmp_path / "t" / "checkpoint.npz").write_bytes(b"")
        raise KeyboardInterrupt

    monkeypatch.setattr(tuning.run, "run_tune", interrupted)
    checkpointed = True
    assert cli.main(["tune", "--out", str(tmp_path / "t"), "--no-progress"]) == 130
    assert "jaxflex tune: interrupted; the same command with --resume continues from the last checkpoint" in capsys.readouterr().err
    # interrupted before its first checkpoint (while compiling): nothing to resume
    checkpointed = False
    assert cli.main(["tune", "--out", str(tmp_path / "u"), "--no-progress"]) == 130
    assert "jaxflex tune: interrupted; nothing was written to resume from: run it again without --resume" in capsys.readouterr().err
    assert not (tmp_path / "u").exists()


def test_cli_sigterm_ends_a_run_as_ctrl_c_does(tmp_path, capsys, monkeypatch):
    """SIGTERM (a scheduler's time limit, kill) ends a run as Ctrl-C does: staging files
    removed, the resume hint, status 143; it killed the process at once, leaving a .tmp-*
    folder and the progress bar's line unfinished, with no word on resuming."""
    import time

    import tuning.run

    def terminated(config, out, **kwargs):
        with fileio.replace_outputs(out, ["tuned.json"]) as stage:
            fileio.write_text(os.path.join(out, "checkpoint.npz"), "")
            fileio.write_text(os.path.join(stage, "tuned.json"), "{}")
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(2)  # the handler raises here
        raise AssertionError("SIGTERM did not end the run")

    monkeypatch.setattr(tuning.run, "run_tune", terminated)
    ignored = []
    before = signal.signal(signal.SIGTERM, lambda *args: ignored.append(args))  # stands in for the default, which ends pytest
    try:
        assert cli.main(["tune", "--out", str(tmp_path / "t"), "--no-progress"]) == 143
        assert signal.getsignal(signal.SIGTERM) is not cli._on_signal  # restored
    finally:
        signal.signal(signal.SIGTERM, before)
    assert not ignored
    assert "jaxflex tune: terminated (SIGTERM); the same command with --resume continues from the last checkpoint" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path / "t")) == ["checkpoint.npz"]  # no staging folder left


def _drop_a_signal(signum):
    """Send ``signum`` to this process so that its handler runs inside a garbage-collection
    callback, where Python prints the handler's exception and drops it."""
    import gc

    sent = []

    def callback(phase, info):
        if phase == "start" and not sent:
            sent.append(signum)
            os.kill(os.getpid(), signum)  # handled before the callback returns: inside it

    gc.callbacks.append(callback)
    try:
        gc.collect()
    finally:
        gc.callbacks.remove(callback)
    assert sent == [signum]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_cli_a_signal_dropped_in_a_gc_callback_still_ends_the_run(tmp_path, capsys, monkeypatch):
    """A signal that lands while JAX's garbage-collection callback runs is raised inside that
    callback, where Python prints the exception and drops it: the run went on to the end and
    exited 0 (twice in about 45 interrupted tunes). The runs' loops raise it again after the
    step or chunk (tune's on_step, montecarlo's on_chunk), and main once the command is done."""
    import jaxflex.montecarlo
    import tuning.run

    def loop_of(name):
        def run(config, out, **kwargs):
            _drop_a_signal(signal.SIGTERM)
            kwargs[name](1)  # the loop's check after a step or chunk
            raise AssertionError(f"{name} did not raise the dropped SIGTERM")

        return run

    def command_to_the_end(args):
        _drop_a_signal(signal.SIGINT)
        return 0

    ignored = []
    before = signal.signal(signal.SIGTERM, lambda *args: ignored.append(args))  # stands in for the default, which ends pytest
    before_int = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a background job ignores it)
    try:
        monkeypatch.setattr(tuning.run, "run_tune", loop_of("on_step"))
        assert cli.main(["tune", "--out", str(tmp_path / "t"), "--no-progress"]) == 143
        monkeypatch.setattr(jaxflex.montecarlo, "run_montecarlo", loop_of("on_chunk"))
        assert cli.main(["montecarlo", "--out", str(tmp_path / "m"), "--no-progress"]) == 143
        assert capsys.readouterr().err.count("terminated (SIGTERM)") == 2
        monkeypatch.setattr(cli, "_run", command_to_the_end)
        assert cli.main(["reproduce", "--out", str(tmp_path / "r")]) == 130
        assert "jaxflex reproduce: interrupted" in capsys.readouterr().err
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # nohup: Ctrl-C stays ignored
        assert cli.main(["reproduce", "--out", str(tmp_path / "r")]) == 0
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)
        signal.signal(signal.SIGINT, before_int)
    assert not ignored


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_cli_a_signal_dropped_while_drawing_leaves_the_folder_as_it_was(tmp_path, capsys, monkeypatch):
    """A Ctrl-C dropped while a figure was drawn (1 in about 17 interrupts of reproduce
    there) let the run replace every file of the folder, and then exit 130 as interrupted.
    The commands that write their files at the end check for it before the files replace
    the old ones."""
    from jaxflex import plotting

    save, drawn = plotting.save, []

    def save_and_drop(fig, path):
        save(fig, path)
        if not drawn:
            drawn.append(os.path.basename(path))
            _drop_a_signal(signal.SIGINT)

    monkeypatch.setattr(plotting, "save", save_and_drop)
    before_int = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        for command, last in ((["calibrate", "--freqs", "15.5", "46.2"], "calibration.json"),
                              (["stability"], "stability.json"),
                              (["reproduce", "--modes", "1"], "results.json")):
            out = tmp_path / command[0]
            out.mkdir()
            (out / last).write_text("an earlier run's")
            drawn.clear()
            assert cli.main([*command, "--out", str(out)]) == 130, command
            assert drawn, command
            assert f"jaxflex {command[0]}: interrupted" in capsys.readouterr().err
            assert os.listdir(out) == [last] and (out / last).read_text() == "an earlier run's", command
    finally:
        signal.signal(signal.SIGINT, before_int)


def test_console_script_ends_at_once_after_an_interrupt(monkeypatch):
    """The installed `jaxflex` ends an interrupted run with os._exit(130), skipping the
    interpreter's shutdown (which crashed while XLA was still compiling); other statuses
    leave through sys.exit."""
    ended = []

    def fake_exit(code):
        ended.append(("os._exit", code))
        raise SystemExit(code)

    monkeypatch.setattr(cli.os, "_exit", fake_exit)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        for status in (130, 143, 2, 0):
            signal.signal(signal.SIGINT, signal.default_int_handler)
            monkeypatch.setattr(cli, "main", lambda status=status: status)
            with pytest.raises(SystemExit) as info:
                cli.console()
            assert info.value.code == status
            # a finished command ignores Ctrl-C while the interpreter shuts down: JAX's exit
            # callback printed a KeyboardInterrupt traceback, and the status stayed 0
            assert (signal.getsignal(signal.SIGINT) is signal.SIG_IGN) == (status in (2, 0)), status
    finally:
        signal.signal(signal.SIGINT, before)
    assert ended == [("os._exit", 130), ("os._exit", 143)]
    scripts = fileio.read_toml(ROOT / "pyproject.toml")["project"]["scripts"]
    assert scripts == {"jaxflex": "jaxflex.cli:console"}


def test_cli_failed_run_leaves_no_empty_out_folder(tmp_path, capsys, monkeypatch):
    """An --out the run created and wrote no file in is removed on error or Ctrl-C; one that
    existed before, or that holds a file (a checkpoint to resume from), is kept."""
    import tuning.run

    def fails_after(write: bool, error: BaseException):
        def run_tune(config, out, **kwargs):
            os.makedirs(os.path.join(out, "sub"))
            if write:
                open(os.path.join(out, "sub", "checkpoint"), "w").close()
            raise error

        return run_tune

    existing = tmp_path / "existing"
    existing.mkdir()
    cases = [
        ("new", False, ValueError("bad"), 2, False),
        ("interrupted", False, KeyboardInterrupt(), 130, False),
        ("checkpointed", True, KeyboardInterrupt(), 130, True),
        ("existing", False, ValueError("bad"), 2, True),
    ]
    for name, write, error, code, kept in cases:
        monkeypatch.setattr(tuning.run, "run_tune", fails_after(write, error))
        assert cli.main(["tune", "--out", str(tmp_path / name), "--no-progress"]) == code, name
        assert (tmp_path / name).is_dir() == kept, name
    capsys.readouterr()


def test_cli_unreadable_config_is_named(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("k = [\n")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b'x = "\xff"\n')  # not UTF-8
    tuned = tmp_path / "tuned.json"  # what tune wrote, passed where its config went
    tuned.write_text('{"controller": "dfs", "params": {"k": 55.0}}\n')
    cases = ((tmp_path / "missing.toml", "cannot read .*missing.toml: No such file or directory"), (bad, ".*bad.toml is not valid TOML"), (binary, ".*binary.toml is not valid TOML: 'utf-8' codec"),
             (tuned, r".*tuned.json is JSON, not TOML \(a tuned.json from `jaxflex tune` goes to --params of reproduce or montecarlo"))
    for command in ("tune", "montecarlo", "stability"):
        for path, reason in cases:
            assert cli.main([command, "--config", str(path), "--out", str(tmp_path / command)]) == 2
            assert re.search(f"jaxflex {command}: error: --config: {reason}", capsys.readouterr().err), (command, path)
            assert not (tmp_path / command).exists()
    for command in ("reproduce", "montecarlo"):  # --params: a file that is not tuned.json, text or not
        for path in (tmp_path / "bad.toml", binary):
            assert cli.main([command, "--params", str(path), "--out", str(tmp_path / command)]) == 2
            assert re.search(f"jaxflex {command}: error: --params: cannot read .*{path.name} as tuned.json", capsys.readouterr().err), (command, path)
            assert not (tmp_path / command).exists()
        # the tune run's folder: the refusal names the file in it ("Is a directory" alone did not)
        assert cli.main([command, "--params", str(tmp_path), "--out", str(tmp_path / command)]) == 2
        assert f"as tuned.json: [Errno 21] Is a directory: '{tmp_path}' (the tune run's folder: pass {tuned})\n" in capsys.readouterr().err


def test_cli_montecarlo_refuses_params_of_another_controller(tmp_path, capsys):
    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": 60.0, "tau_s": 0.005}}))
    assert cli.main(["montecarlo", "--controller", "fuzzy", "--params", str(tuned), "--out", str(tmp_path / "m")]) == 2
    assert "holds tuned dfs parameters; the controller asked for is fuzzy" in capsys.readouterr().err
    # a Monte Carlo summary holds controller and params too, but not the arm they were tuned for
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"controller": "dfs", "params": {"k": 60.0, "tau_s": 0.005}, "n_scenarios": 8, "metrics": {}, "beam": {"length_m": 1.2}}))
    assert cli.main(["reproduce", "--params", str(summary), "--out", str(tmp_path / "r")]) == 2
    assert f"--params: {summary} is a jaxflex montecarlo summary.json; pass the tuned.json that jaxflex tune wrote" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_reproduce_with_params_simulates_the_tuned_gains(tmp_path, capsys, monkeypatch):
    """`reproduce --params tuned.json`: tuned gains equal to the paper's give the paper's DFS run
    (a linear delay read at a whole number of samples is the nearest read), the table and the
    figure are written, and gains tuned for another arm say so."""
    tuned = tmp_path / "tuned.json"
    config = {"beam": {"length_m": 0.6, "rayleigh_alpha": None}, "n_modes": 3, "method": "zoh", "scenarios": {"dt": 5e-4}}
    tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": 55.0, "tau_s": 0.005}, "config": config}))
    out = tmp_path / "o"
    drawn, responses = [], plotting.responses

    def recorded(t, runs, *args, **kwargs):
        drawn.append((list(runs), kwargs.get("style_of")))
        return responses(t, runs, *args, **kwargs)

    monkeypatch.setattr(plotting, "responses", recorded)
    scales, psds = [], plotting.psds

    def recorded_psds(freqs, runs, modes, *args, **kwargs):
        scales.append((kwargs.get("ylim"), [np.asarray(c)[np.asarray(freqs) <= 150.0] for c in runs.values()]))
        return psds(freqs, runs, modes, *args, **kwargs)

    monkeypatch.setattr(plotting, "psds", recorded_psds)
    assert cli.main(["reproduce", "--out", str(out), "--params", str(tuned)]) == 0
    # fig6 and fig8 on one scale that holds every curve of both (they each had their own decades)
    (ylim6, curves6), (ylim8, curves8) = scales
    assert ylim6 == ylim8 and ylim6 is not None
    every = np.concatenate(curves6 + curves8)
    assert ylim6[0] < every.min() <= every.max() < ylim6[1] < 10 * every.max()
    # the tuned figure's legend: the paper gains in DFS's look (it read "DFS" beside "tuned dfs"), each with its gains
    paper_gains = "DFS, paper gains (k = 55, tau_s = 0.005)"
    assert drawn[-1] == (["open_loop", paper_gains, "tuned dfs (k = 55, tau_s = 0.005)"], {paper_gains: "dfs"})
    tuned_for = "another arm (length_m = 0.6), 3 modes (here 2), dt = 0.0005 s (here 0.001 s), method = 'zoh' (here 'rk4')"
    # said on the console too, not only in one sentence of report.md
    printed = capsys.readouterr()
    assert f"note: {tuned} was tuned for {tuned_for}; its gains ran here on the paper's arm, 2 modes, RK4 at 1 ms" in printed.out
    # the model line the other commands print, with the damping each mode gets
    assert "model: 2 mode(s) at 13.32, 36.47 Hz with damping ratios 0.01, 0.01 in flexible modes 1-2 (damping_ratio = 0.01 of the 2-mode model), sampled every 0.001 s" in printed.err
    res = json.loads((out / "results.json").read_text())
    ours, paper = res["tuned"]["run"], res["runs"]["dfs"]
    for name in ("q1", "tip_deflection_m"):
        for key, value in paper[name].items():
            if isinstance(value, float):
                np.testing.assert_allclose(ours[name][key], value, rtol=1e-12, err_msg=f"{name}.{key}")
    assert res["tuned"]["beam"]["length_m"] == 0.6
    # report.md's comparison on the console too (see test_tuned_line_puts_each_side_in_its_place)
    assert f"tuned dfs ({tuned}): k = 55, tau_s = 0.005 (paper: k = 55, tau_s = 0.005); q1 settling " in printed.out
    report = (out / "report.md").read_text()
    assert "## Tuned gains (dfs) beside the paper's, on the paper scenario" in report
    assert re.search(rf"Command: `jaxflex reproduce --modes 2( --x64)? --params {re.escape(str(tuned))}`", report)  # the tests run in float64
    assert f"These gains were tuned for {tuned_for}; they are shown here on the paper's arm, model and sampling." in report
    assert (out / "fig_tuned_response.png").read_bytes()[:4] == b"\x89PNG"


def test_tuned_line_puts_each_side_in_its_place():
    """reproduce --params' printout: the tuned side first, the paper's second, a run that never
    settled said so (format_value's n/a is a diverged run's), a diverged run "diverged"."""
    from jaxflex.report import tuned_comparison

    def run(settling, ise, diverged=False):
        return {"diverged": diverged, "q1": {"settling_time_s": settling}, "tip_deflection_m": {"min": -1e-3, "max": 2e-3, "ise": ise}}

    tuned = {"controller": "dfs", "file": "t.json", "params": {"k": 117.9, "tau_s": 0.0043}, "paper_params": {"k": 55.0, "tau_s": 0.005},
             "run": run(math.inf, 6.5e-8), "paper_run": run(0.2321, 4.6e-8)}
    assert cli._tuned_line(tuned) == ("tuned dfs (t.json): k = 117.9, tau_s = 0.0043 (paper: k = 55, tau_s = 0.005); "
                                      "q1 settling not settled against 0.232 s, tip ISE 6.5e-08 against 4.6e-08 (m^2 s) with the paper's gains")
    tuned["run"] = run(None, None, diverged=True)
    assert "q1 settling diverged against 0.232 s, tip ISE diverged against 4.6e-08 (m^2 s)" in cli._tuned_line(tuned)
    assert [row[0] for row in tuned_comparison(tuned)] == ["paper", "tuned"]


def test_reproduce_with_dfs_fuzzy_params_compares_the_same_loop(tmp_path):
    """The paper runs no DFS + fuzzy loop: tuned dfs+fuzzy gains were set beside the paper's
    fuzzy controller alone, so the paper's own gains, passed as tuned, read as a different
    run. The paper row is now the paper's gains in the DFS + fuzzy loop, and equals them."""
    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"controller": "dfs+fuzzy", "params": {"k": 55.0, "tau_s": 0.005, "k1": 1.02, "k2": 0.3, "k3": 1.0}}))
    out = tmp_path / "o"
    assert cli.main(["reproduce", "--out", str(out), "--params", str(tuned)]) == 0
    res = json.loads((out / "results.json").read_text())
    ours, paper = res["tuned"]["run"], res["tuned"]["paper_run"]
    assert res["tuned"]["paper_params"] == {"k": 55.0, "tau_s": 0.005, "k1": 1.02, "k2": 0.3, "k3": 1.0}
    for name in ("q1", "tip_deflection_m"):
        for key, value in paper[name].items():
            np.testing.assert_allclose(ours[name][key], value, rtol=1e-12, err_msg=f"{name}.{key}")
    assert paper["tip_deflection_m"]["ise"] != res["runs"]["fuzzy"]["tip_deflection_m"]["ise"]  # another loop than fuzzy alone
    rows = [line for line in (out / "report.md").read_text().splitlines() if line.startswith(("| paper | k = 55", "| tuned | k = 55"))]
    assert len(rows) == 2 and rows[0].removeprefix("| paper") == rows[1].removeprefix("| tuned"), rows


def test_reproduce_says_when_the_tuned_gains_diverge(tmp_path, capsys):
    """Diverging tuned gains were shown as a row of n/a, with nothing on the console."""
    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": -400.0, "tau_s": 0.005}}))
    out = tmp_path / "o"
    assert cli.main(["reproduce", "--out", str(out), "--params", str(tuned)]) == 0
    assert f"note: the tuned dfs gains of {tuned} diverge on the paper scenario (see report.md)" in capsys.readouterr().out
    report = (out / "report.md").read_text()
    assert "**The tuned gains' closed loop diverged on this scenario.**" in report
    assert "| tuned | k = -400, tau_s = 0.005 | diverged | diverged | diverged |" in report
    assert re.search(r"\| paper \| k = 55, tau_s = 0.005 \| 0\.\d{3} s \| ", report)


def test_reproduce_says_when_the_tune_run_kept_its_starting_gains(tmp_path, capsys, monkeypatch):
    """A tune run whose updates never improved its held-out objective keeps the gains it
    started from (best_step 0). Started from the paper's gains, its tuned row equalled the
    paper's row with nothing to say why; montecarlo --params says it too. A run that moved its
    gains says nothing of it, and a best_step that is not a count of updates is refused by name."""
    from jaxflex import montecarlo

    tuned = tmp_path / "tuned.json"
    out = tmp_path / "o"
    kept = "jaxflex tune kept the gains it started from: no update improved its held-out objective"
    tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": 55.0, "tau_s": 0.005}, "best_step": 0}))
    assert cli.main(["reproduce", "--out", str(out), "--params", str(tuned)]) == 0
    assert f"note: {tuned}: {kept}\n" in capsys.readouterr().out
    report = (out / "report.md").read_text()
    assert f"\n{kept}.\n" in report
    assert json.loads((out / "results.json").read_text())["tuned"]["kept_start"] is True
    with monkeypatch.context() as patch:
        patch.setattr(montecarlo, "run_montecarlo", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
        assert cli.main(["montecarlo", "--params", str(tuned), "--out", str(tmp_path / "m"), "--no-progress"]) == 130
    assert f"note: {tuned}: {kept}\n" in capsys.readouterr().err
    tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": 60.0, "tau_s": 0.005}, "best_step": 7}))
    assert cli.main(["reproduce", "--out", str(out), "--params", str(tuned)]) == 0
    assert kept not in capsys.readouterr().out and kept not in (out / "report.md").read_text()
    for bad in (-1, 2.5, "0"):
        tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": 55.0, "tau_s": 0.005}, "best_step": bad}))
        assert cli.main(["reproduce", "--out", str(tmp_path / "bad"), "--params", str(tuned)]) == 2
        assert f"--params: {tuned}'s best_step must be an integer >= 0; got {bad!r}" in capsys.readouterr().err


def test_report_says_by_estimator_where_dfs_is_ahead(reproduced):
    """The paper's ordering (DFS ahead of fuzzy) is judged with the default estimator; the
    sentence also says where each other estimator puts DFS ahead, at the paper's two modes."""
    from jaxflex.report import _report_md

    _, res = copy.deepcopy(reproduced)
    tables = res["vibration_reduction_db_by_estimator"]
    names = list(tables)
    verdicts = ([90.0, 90.0], [80.0, 80.0]), ([90.0, 10.0], [80.0, 80.0]), ([10.0, 90.0], [80.0, 80.0]), ([10.0, 10.0, 99.0], [80.0, 80.0, 1.0])
    for name, (dfs_db, fuzzy_db) in zip(names, verdicts):
        tables[name] = {"dfs": dfs_db, "fuzzy": fuzzy_db}
    res["vibration_reduction_db"] = tables[names[0]]
    expected = f"agrees with jaxflex's default estimator. Comparing modes 1-2, as the paper does, DFS is ahead, by estimator: {names[0]} at modes 1, 2; {names[1]} at mode 1; {names[2]} at mode 2; {names[3]} at no mode."
    assert expected in _report_md(res)


def test_report_tells_a_run_that_never_settled_and_a_third_mode(reproduced):
    """A settling time of +inf (still outside the band at the end) read n/a, as a diverged run
    does. A third model mode has no paper value and stays out of the paper's comparison."""
    from jaxflex.report import _report_md

    _, res = copy.deepcopy(reproduced)
    res["runs"]["dfs"]["q1"]["settling_time_s"] = math.inf
    for table in (res["vibration_reduction_db_q1"], *res["vibration_reduction_db_by_estimator"].values()):
        table["dfs"].append(1.0)
        table["fuzzy"].append(99.0)
    for run in ("dfs", "fuzzy"):
        for key, value in (("db", 1.0), ("closed_loop_highest_hz", 60.0), ("is_peak", False)):
            res["region_reduction_db"][run][key].append(value)
    # DFS ahead at the paper's two modes, behind at the third: compared, it would not agree
    res["vibration_reduction_db"] = {"dfs": [90.0, 90.0, 1.0], "fuzzy": [80.0, 80.0, 99.0]}
    report = _report_md(res)
    assert "| DFS | settling time | 0.25 s | not settled | " in report
    assert "| DFS | 3 | - | 1.0 |" in report and "| PD-type fuzzy | 3 | - | 99.0 |" in report
    assert "than the fuzzy controller at both modes agrees with" in report
    # the by-estimator sentence says which modes it compares: its "at no mode" read as if
    # the table's third-mode rows, DFS ahead there in some model, were not there
    assert "Comparing modes 1-2, as the paper does, DFS is ahead, by estimator: " in report
    one = copy.deepcopy(res)
    one["model"]["n_modes"] = 1
    for key in ("natural_frequencies_hz", "exact_natural_frequencies_hz"):
        one["model"][key] = one["model"][key][:1]
    for table in (one["vibration_reduction_db"], one["vibration_reduction_db_q1"], *one["vibration_reduction_db_by_estimator"].values()):
        for run in ("dfs", "fuzzy"):
            table[run] = table[run][:1]
    for run in ("dfs", "fuzzy"):
        one["region_reduction_db"][run] = {key: values[:1] for key, values in one["region_reduction_db"][run].items()}
    one_report = _report_md(one)
    assert "| 2 | 55 | n/a | " in one_report and "| not in the 1-mode model |" in one_report  # it said "differs"
    assert "Comparing mode 1 (the paper compares modes 1-2), DFS is ahead, by estimator: " in one_report
    res["model"]["natural_frequencies_hz"].append(65.09)
    assert cli._reproduce_summary(res).split("\n")[0].startswith(f"model natural frequencies: {res['model']['natural_frequencies_hz'][0]:.2f}, {res['model']['natural_frequencies_hz'][1]:.2f}, 65.09 Hz")


def test_tuned_differences_name_each_field_that_differs():
    """Tuned.differences against a model: the arm's fields (a derived Rayleigh pair included:
    it was formatted as a number and crashed), the mode count, dt and method."""
    from jaxflex.beam import BeamParams
    from jaxflex.report import Tuned

    tuned = Tuned("dfs", {"k": 55.0, "tau_s": 0.005}, {}, BeamParams(length_m=1.2), 1e-3, 2, "rk4")
    assert tuned.differences(BeamParams(length_m=1.2), 2, 1e-3, "rk4") == []
    assert tuned.differences(BeamParams(length_m=1.2), 2, 1e-3 * (1 + 1e-9), "rk4") == []  # float32 round-off of dt
    given = BeamParams(length_m=1.2, rayleigh_alpha=0.5, rayleigh_beta=1e-5)
    assert tuned.differences(given, 3, 2e-3, "zoh") == [
        "another arm (rayleigh_alpha = derived, rayleigh_beta = derived)",
        "2 modes (here 3)",
        "dt = 0.001 s (here 0.002 s)",
        "method = 'rk4' (here 'zoh')",
    ]


def test_one_mode_report_says_which_modes_it_compared(tmp_path, monkeypatch):
    """With one mode only mode 1 is compared; the report once said 'at both modes'. The
    folder's files are replaced together: an interrupted run leaves it as it was, and a
    finished one removes the tuned figure of an earlier run with --params."""
    from jaxflex import plotting

    (tmp_path / "fig_tuned_response.png").write_bytes(b"stale")
    (tmp_path / "report.md").write_text("earlier run")
    (tmp_path / "notes.txt").write_text("the user's")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(plotting, "surface", interrupted)  # drawn after four other figures
        with pytest.raises(KeyboardInterrupt):
            reproduce(tmp_path, n_modes=1)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    results = reproduce(tmp_path, n_modes=1)
    names = {p.name for p in tmp_path.iterdir()}
    assert "fig_tuned_response.png" not in names and "notes.txt" in names
    assert names == {"notes.txt", "report.md", "results.json", *FIGURES}
    assert len(results["vibration_reduction_db"]["dfs"]) == 1
    text = (tmp_path / "report.md").read_text()
    assert "at both modes" not in text
    assert "than the fuzzy controller at mode 1 (the only mode of this 1-mode model; the paper also compares mode 2)" in text


def test_response_figure_tells_runs_apart_and_scales_to_the_settled_ones():
    """The tuned run took matplotlib's first colour, DFS's own, so the two curves could not be
    told apart; and a diverged run (1e35 by its end) flattened every other curve to a line."""
    import matplotlib.pyplot as plt

    from jaxflex import plotting

    t = np.linspace(0.0, 1.0, 101)
    decay = 1e-3 * np.exp(-5 * t) * np.cos(60 * t)
    runs = {"dfs": {"q1": decay}, "tuned dfs": {"q1": 0.5 * decay}, "open_loop": {"q1": 1e35 * t**40}}
    fig = plotting.responses(t, runs, [("q1", "q1 (m)")], {"open_loop": True}, "title")
    ax = fig.axes[0]
    colours = [line.get_color() for line in ax.get_lines()]
    lo, hi = ax.get_ylim()
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    plt.close(fig)
    assert len(set(colours)) == 3
    assert -2e-3 < lo < -5e-4 and 1e-3 <= hi < 2e-3  # the settled runs' range, padded
    assert "Open loop (diverged)" in labels
    # a diverged run that swings about zero is drawn until it leaves the axes, not over them
    # (it drew a solid block); here it leaves the settled range at t = 0.5 s
    swing = np.where(t < 0.5, 1e-4, 1e-2) * np.cos(np.pi * 100 * t)
    fig = plotting.responses(t, {"dfs": {"q1": decay}, "tuned dfs": {"q1": swing}}, [("q1", "q1 (m)")], {"tuned dfs": True}, "title")
    drawn = {line.get_label(): line.get_xdata() for line in fig.axes[0].get_lines()}
    plt.close(fig)
    assert drawn["DFS"].size == t.size and drawn["tuned dfs (diverged)"][-1] == pytest.approx(0.5)
    # jaxflex tune's two runs, neither a paper run, get two styles too (they once shared one)
    for draw in (lambda: plotting.responses(t, {"paper gains": {"q1": decay}, "tuned": {"q1": decay}}, [("q1", "q1 (m)")], {}, "title"),
                 lambda: plotting.psds(t, {"paper gains": decay + 1.0, "tuned": decay + 1.0}, (), "y", "title")):
        fig = draw()
        styles = {(line.get_color(), line.get_linestyle()) for line in fig.axes[0].get_lines()}
        plt.close(fig)
        assert len(styles) == 2


def test_histograms_name_an_axis_offset_in_the_label_instead_of_over_it():
    """Matplotlib draws an axis' offset ('+1e5') at its lower right, where the wrapped metric
    label sits: montecarlo's histograms.png printed one over the other."""
    from jaxflex import plotting

    rng = np.random.default_rng(0)
    data = {"settle_s": 1e5 + rng.standard_normal(200), "reduction_db": 60 + rng.standard_normal(200)}
    fig = plotting.histograms(data, {"settle_s": "settling time (s)"}, "t")
    fig.canvas.draw()
    shifted, plain = fig.axes[:2]
    assert shifted.get_xlabel() == "settling time (s) (ticks: +1e5)" and not shifted.xaxis.get_offset_text().get_visible()
    assert plain.get_xlabel() == "reduction_db"
    plotting.plt.close(fig)


def test_report_with_a_diverged_run_has_no_region_cell_to_format(reproduced):
    """A diverged run's region reduction is None throughout: report.md formatted its frequency
    before checking it (TypeError), and reads n/a."""
    from jaxflex.report import _report_md

    _, res = copy.deepcopy(reproduced)
    res["region_reduction_db"]["fuzzy"] = {key: [None, None] for key in ("db", "closed_loop_highest_hz", "is_peak")}
    assert "| PD-type fuzzy | 1 | 102.24 |" in _report_md(res) and _report_md(res).count("| n/a |") >= 2


@pytest.mark.skipif(fileio.fcntl is None, reason="POSIX locks")
def test_a_run_lock_inside_itself_under_another_spelling_of_the_folder(tmp_path):
    """A block inside another on the same folder, spelt "dir/.", "dir/" or relative, is the
    same run, not one 'in use by another run' (pathlib drops a trailing "." from tmp_path / ".",
    so only strings show it)."""
    with fileio.run_lock(tmp_path):
        with fileio.run_lock(os.path.join(str(tmp_path), ".")):
            pass
        with fileio.run_lock(str(tmp_path) + os.sep):
            pass
        old = os.getcwd()
        os.chdir(tmp_path.parent)
        try:
            with fileio.run_lock(tmp_path.name):
                pass
        finally:
            os.chdir(old)


@pytest.mark.skipif(fileio.fcntl is None, reason="POSIX locks")
def test_the_sweep_leaves_an_old_tmp_symlink_and_its_target_alone(tmp_path):
    """A .tmp-* symlink, however old, is not removed by the next write's sweep of stale
    temporary files (nor is what it points to)."""
    target = tmp_path / "target.txt"
    target.write_text("data")
    link = tmp_path / ".tmp-link"
    os.symlink(target, link)
    past = os.lstat(link).st_mtime - 60
    os.utime(link, (past, past), follow_symlinks=False)
    fileio.write_text(tmp_path / "new.md", "x")
    assert os.path.islink(link) and target.read_text() == "data"


def test_check_path_refuses_an_empty_path():
    with pytest.raises(ValueError, match=r"out_dir must be a folder's path \(a non-empty str or os.PathLike\); got ''"):
        fileio.check_path("out_dir", "", "folder")
    with pytest.raises(ValueError, match=r"--config must be a file's path"):
        fileio.read_toml("")


def _row(text, prefix):
    """The one line of report.md that starts with ``prefix``."""
    rows = [line for line in text.splitlines() if line.startswith(prefix)]
    assert len(rows) == 1, (prefix, rows)
    return rows[0]


def test_format_value_says_n_a_for_non_finite():
    """format_value: "n/a for a missing (diverged run) or non-finite value"."""
    from jaxflex.report import format_value

    assert [format_value(v) for v in (float("nan"), float("inf"), None, 1.5)] == ["n/a", "n/a", "n/a", "1.5"]


def test_only_the_first_frequency_is_said_above_the_pinned_free_bound(reproduced):
    """The bound is on the first flexible frequency; the paper's 55 Hz row says only "differs"."""
    from jaxflex.report import _report_md

    assert _row(_report_md(reproduced[1]), "| 2 | 55 |").endswith("| differs |")


def test_time_response_rows_show_each_signals_own_range(reproduced):
    """Every range cell is min .. max of its own signal; the paper column its run's."""
    from jaxflex.report import _report_md

    res = copy.deepcopy(reproduced[1])
    res["runs"]["open_loop"]["q1"].update(min=-0.111, max=0.222)
    res["runs"]["open_loop"]["tip_deflection_m"].update(min=-0.333, max=0.444)
    res["runs"]["fuzzy"]["q1"].update(min=-0.0123, max=0.0456)
    res["runs"]["fuzzy"]["tip_deflection_m"].update(min=-0.0789, max=0.0987)
    text = _report_md(res)
    assert _row(text, "| open loop | range |").startswith("| open loop | range | -0.03 .. 0.03 m | -0.111 .. 0.222 | -0.333 .. 0.444 |")
    assert _row(text, "| PD-type fuzzy | range |").startswith("| PD-type fuzzy | range | -0.006 .. 0.025 m | -0.0123 .. 0.0456 | -0.0789 .. 0.0987 |")


def test_a_diverged_run_has_one_row_that_says_so(reproduced):
    from jaxflex.report import _report_md

    res = copy.deepcopy(reproduced[1])
    res["runs"]["dfs"]["diverged"] = True
    text = _report_md(res)
    assert "| DFS | all | | diverged | diverged | the closed loop diverged |" in text
    assert "| DFS | settling time |" not in text


def test_reduction_rows_q1_column_and_peak_or_skirt(reproduced):
    """The q1 column holds vibration_reduction_db_q1; a region's highest bin is called a peak or a skirt as is_peak says."""
    from jaxflex.report import _report_md

    res = copy.deepcopy(reproduced[1])
    res["vibration_reduction_db_q1"]["dfs"] = [11.1, 22.2]
    res["region_reduction_db"]["dfs"] = {"db": [5.0, 6.0], "closed_loop_highest_hz": [17.5, 30.0], "is_peak": [True, False]}
    text = _report_md(res)
    assert _row(text, "| DFS | 1 |").endswith("| 11.1 | 5.0 (a peak at 17.5 Hz) |")
    assert _row(text, "| DFS | 2 |").endswith("| 22.2 | 6.0 (at 30.0 Hz, a skirt) |")


def test_equal_reductions_do_not_agree_with_the_papers_ordering(reproduced):
    """The paper's ordering "agrees" only when DFS's reduction is the larger at every mode: a tie does not."""
    from jaxflex.report import _report_md

    res = copy.deepcopy(reproduced[1])
    res["vibration_reduction_db"] = {**res["vibration_reduction_db"], "dfs": [20.0, 20.0], "fuzzy": [20.0, 10.0]}
    assert "than the fuzzy controller at both modes does not agree with" in _report_md(res)


def test_tuned_comparison_range_reads_min_to_max():
    """The tip range "min .. max" (m)."""
    from jaxflex.report import tuned_comparison

    run = {"diverged": False, "q1": {"settling_time_s": 0.2}, "tip_deflection_m": {"min": -1e-3, "max": 2e-3, "ise": 4e-8}}
    tuned = {"params": {"k": 60.0, "tau_s": 0.004}, "paper_params": {"k": 55.0, "tau_s": 0.005}, "run": run, "paper_run": run}
    rows = tuned_comparison(tuned)
    assert [row.tip_range for row in rows] == ["-0.001 .. 0.002"] * 2
    assert [row.gains for row in rows] == ["k = 55, tau_s = 0.005", "k = 60, tau_s = 0.004"]


def test_command_line_names_x64_only_for_float64_and_the_delay_in_ms(reproduced):
    """--x64 for a float64 run only; tau in ms; the default estimator named first."""
    from jaxflex.report import _report_md

    for dtype, flag in (("float64", " --x64"), ("float32", "")):
        res = copy.deepcopy(reproduced[1])
        res["model"]["dtype"] = dtype
        text = _report_md(res)
        assert f"Command: `jaxflex reproduce --modes 2{flag}`." in text
    assert "DFS u = -k (theta(t) - theta(t - tau)), k = 55 N*m/rad, tau = 5 ms" in text
    assert "Default estimator: hann-1024 (Welch, hann window, 1024-sample segments, 512 overlap" in text
