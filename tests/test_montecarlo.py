"""Monte Carlo: statistics against NumPy on the same rollouts, device-count independence,
resume equals an uninterrupted run, and refusal of impossible descriptions."""

import dataclasses
import functools
import hashlib
import json
import os
import re
import subprocess
import sys

import jax
import numpy as np
import pytest

import jaxflex as jf
from jaxflex import beam, fileio, montecarlo, plotting
from jaxflex.controllers import OpenLoopParams, open_loop
from jaxflex.controllers.registry import PAPER_PARAMS
from jaxflex.heartbeat import Heartbeat
from jaxflex.beam import BeamParams
from jaxflex.montecarlo import MCConfig, controller_and_params, run_montecarlo
from jaxflex.plant import discretize, make_plant
from jaxflex.scenarios import ScenarioSpec, batch_plant, sample_scenarios

SPEC = ScenarioSpec(horizon_s=0.3, impulse_max_n=0.5, youngs_modulus_rel=0.1, noise_angle_rad=1e-6)


def test_a_run_into_a_folder_another_run_holds_is_refused(tmp_path):
    """Two runs started into one folder at once both passed its checks before either wrote a
    file, then wrote their chunks (and tune its checkpoints and figures) over each other's,
    and a later resume summed chunks of both. A run holds the folder's run lock while it goes;
    here another process's lock stands in for a run still going (flock: another open file)."""
    fcntl = pytest.importorskip("fcntl")
    from jaxflex import fileio
    from tuning.run import run_tune
    from tuning.tuner import TuneConfig

    out = tmp_path / "busy"
    out.mkdir()
    fd = os.open(out / fileio.RUN_LOCK, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        busy = r"out_dir \(--out\) .*busy is in use by another run still going: wait for it to end, or choose another folder"
        with pytest.raises(ValueError, match=busy):
            run_montecarlo(MCConfig(controller="dfs", n_scenarios=4, chunk=4, scenarios=SPEC), out, progress=False, figures=False)
        with pytest.raises(ValueError, match=busy):
            run_tune(TuneConfig(controller="dfs", n_scenarios=4, n_heldout=1, steps=1, scenarios=SPEC), out, progress=False)
        assert os.listdir(out) == [fileio.RUN_LOCK]  # nothing written
    finally:
        os.close(fd)
    summary = run_montecarlo(MCConfig(controller="dfs", n_scenarios=4, chunk=4, scenarios=SPEC), out, progress=False, figures=False)
    assert summary["n_scenarios"] == 4  # the lock released, the folder takes a run


def test_a_run_refused_from_a_new_folder_leaves_the_other_runs_folder(tmp_path, monkeypatch, capsys):
    """Two runs started at once into a new folder both found it new; the one refused then
    removed the folder and the other's lock as its own empty folder, and a third run went in
    beside the first. Here the first run takes the folder between the second's check that it
    is new and its own lock, as a process started a moment earlier does."""
    fcntl = pytest.importorskip("fcntl")
    from jaxflex import cli, fileio

    out = tmp_path / "race"
    held = []
    real_run = cli._run

    def first_run_takes_the_folder(args):
        out.mkdir()
        fd = os.open(out / fileio.RUN_LOCK, os.O_RDWR | os.O_CREAT)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.append(fd)
        return real_run(args)

    monkeypatch.setattr(cli, "_run", first_run_takes_the_folder)
    try:
        assert cli.main(["montecarlo", "--controller", "dfs", "--scenarios", "4", "--chunk", "4", "--out", str(out), "--no-progress"]) == 2
        assert "is in use by another run still going" in capsys.readouterr().err
        assert os.listdir(out) == [fileio.RUN_LOCK]  # the first run's folder and lock stay
    finally:
        os.close(held[0])
    fileio.remove_if_empty(str(out))  # the lock released: an empty folder of a run that wrote nothing goes
    assert not out.exists()


def test_a_resume_by_another_program_is_refused(tmp_path, monkeypatch):
    """A resume by other code, or another jax, was accepted, and its summary mixed the chunks
    of two programs (one change to the modal frequencies moved reduction_db_mode2 by 1.7 dB).
    The folder records the program (a hash of the source, jax's and jaxlib's versions) and a
    resume by another is refused, naming both; tune's checkpoint records it the same way."""
    from jaxflex import fileio
    from tuning.tuner import TuneConfig

    config = MCConfig(controller="dfs", n_scenarios=8, chunk=4, scenarios=SPEC)

    def interrupt(index):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path / "r", progress=False, figures=False, on_chunk=interrupt)
    assert config.fingerprint_fields()["program"] == TuneConfig().fingerprint_fields()["program"] == fileio.program()
    assert fileio.program().startswith("jaxflex source ") and f"jax {jax.__version__}" in fileio.program()
    monkeypatch.setattr(fileio, "program", lambda: "jaxflex source 000000000000, jax 0.0.0, jaxlib 0.0.0")
    with pytest.raises(ValueError, match=r"changed: program: 'jaxflex source [0-9a-f]{12}, jax .*' -> 'jaxflex source 000000000000, jax 0.0.0, jaxlib 0.0.0'"):
        run_montecarlo(config, tmp_path / "r", resume=True, progress=False, figures=False)


def test_summary_matches_direct_rollouts(tmp_path, monkeypatch):
    config = MCConfig(controller="dfs", n_scenarios=50, chunk=32, scenarios=SPEC, percentiles=(10.0, 50.0, 90.0))
    titles, real_histograms = [], plotting.histograms
    monkeypatch.setattr(plotting, "histograms", lambda data, labels, title: titles.append(title) or real_histograms(data, labels, title))
    summary = run_montecarlo(config, tmp_path, progress=False)
    f1, f2 = np.asarray(beam.natural_frequencies_hz(jf.BeamParams(), 2))
    assert titles == [f"dfs: 50 of 50 runs (diverged left out)\nnominal 0.9 m arm, 2 modes at {f1:.3g}, {f2:.3g} Hz"]  # names its arm
    assert summary["n_scenarios"] == 50
    # recompute chunk 1 independently: same key derivation, plain loop over scenarios
    controller, params = controller_and_params("dfs", {}, 1e-3, config.capacity)

    @jax.jit
    def direct(sc):
        arm = jf.scenarios.perturbed_params(jf.BeamParams(), sc.plant)
        plant = jf.discretize(jf.make_plant(arm, 2), 1e-3, "rk4")
        freqs = beam.natural_frequencies_hz(arm, 2)
        closed = jf.rollout(plant, controller, params, sc, output="metrics", mode_freqs_hz=freqs)
        opened = jf.rollout(plant, open_loop(), OpenLoopParams(), sc, output="metrics", mode_freqs_hz=freqs)
        return jf.rollout(plant, controller, params, sc).z[:, 1], closed.tip_ise, closed.modal_energy, opened.modal_energy

    peaks, ise, closed_energy, open_energy = [], [], [], []
    for index, count in ((0, 32), (1, 18)):
        spec = SPEC if index == 0 else ScenarioSpec(**{**SPEC.__dict__, "include_paper": False})
        batch = sample_scenarios(spec, jax.random.fold_in(jax.random.key(0), index), 32)
        for i in range(count):
            tip, tip_ise, closed, opened = direct(jax.tree.map(lambda a: a[i], batch))
            peaks.append(np.abs(np.asarray(tip)).max())
            ise.append(float(tip_ise))
            closed_energy.append(np.asarray(closed))
            open_energy.append(np.asarray(opened))
    peaks = np.array(peaks)
    stats = summary["metrics"]["peak_tip_deflection_m"]
    np.testing.assert_allclose(stats["mean"], peaks.mean(), rtol=1e-10)
    np.testing.assert_allclose(stats["std"], peaks.std(), rtol=1e-8)
    np.testing.assert_allclose([stats["p10"], stats["p50"], stats["p90"]], np.percentile(peaks, [10, 50, 90]), rtol=1e-10)
    assert stats["min"] == pytest.approx(peaks.min()) and stats["max"] == pytest.approx(peaks.max())
    # each column is its own metric: tip ISE, and the dB reduction 10 log10(open / closed) of
    # the windowed modal energy at each mode
    np.testing.assert_allclose(summary["metrics"]["tip_ise"]["mean"], np.mean(ise), rtol=1e-10)
    reduction = 10 * np.log10(np.array(open_energy) / np.array(closed_energy))
    for mode in (1, 2):
        got = summary["metrics"][f"reduction_db_mode{mode}"]
        np.testing.assert_allclose([got["mean"], got["p50"]], [reduction[:, mode - 1].mean(), np.median(reduction[:, mode - 1])], rtol=1e-9)
    assert summary["diverged_fraction"] == 0.0
    assert summary["params"] == {"k": 55.0, "tau_s": 0.005}  # the values simulated, the paper's here
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["dtype"] == "float64"  # the tests run under jax_enable_x64 (conftest.py)
    assert set(saved["metrics"]) >= {"settling_time_s", "peak_tip_deflection_m", "tip_ise", "control_effort", "final_hub_angle_rad", "reduction_db_mode1", "reduction_db_mode2"}
    assert saved["metrics"]["reduction_db_mode1"]["p10"] > 0  # DFS damps the first mode in nearly every scenario
    for name in saved["figures"]:
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
    # other percentiles and band scenarios are read from the stored rows on resume, with no
    # chunk run again; the band figure always draws the median, asked for or not
    def no_rerun(*args):
        raise AssertionError("a chunk was run again")

    drawn, real_bands = {}, plotting.percentile_bands

    def bands(t, values, percentiles, ylabel, title):
        drawn.update(percentiles=list(percentiles), title=title)
        return real_bands(t, values, percentiles, ylabel, title)

    monkeypatch.setattr(montecarlo._Runner, "run_chunk", no_rerun)
    monkeypatch.setattr(plotting, "percentile_bands", bands)
    again = run_montecarlo(dataclasses.replace(config, percentiles=(5.0, 99.0), band_scenarios=8), tmp_path, resume=True, progress=False)
    stats = again["metrics"]["peak_tip_deflection_m"]
    np.testing.assert_allclose([stats["p5"], stats["p99"]], np.percentile(peaks, [5, 99]), rtol=1e-10)
    assert "p50" not in stats and again["percentiles"] == [5.0, 99.0]
    assert drawn["percentiles"] == [5.0, 50.0, 99.0] and "over 8 of 8 scenarios" in drawn["title"]
    # a resume stopped while drawing leaves neither figure nor summary: the histograms were
    # drawn into the folder first, beside the previous run's bands, and a resume left both old
    def stopped(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(plotting, "percentile_bands", stopped)
    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path, resume=True, progress=False)
    assert not any((tmp_path / name).exists() for name in (*montecarlo.FIGURES, "summary.json"))
    # a folder written when they still bound it (in its config and its hash) resumes too
    meta = json.loads((tmp_path / "montecarlo.json").read_text())
    meta["config"].update(percentiles=[10.0, 50.0, 90.0], band_scenarios=256)
    meta["fingerprint"] = hashlib.sha256(json.dumps(meta["config"], sort_keys=True).encode()).hexdigest()[:16]
    (tmp_path / "montecarlo.json").write_text(json.dumps(meta))
    assert run_montecarlo(config, tmp_path, resume=True, progress=False, figures=False)["metrics"]["tip_ise"] == summary["metrics"]["tip_ise"]


def test_a_tip_beyond_the_arms_length_counts_as_diverged(tmp_path):
    """A growing loop that has not blown up (every state below 1e6) but whose tip deflected by
    more than the arm's length is diverged: such runs (27 km on a 1.2 m arm) were averaged
    into the statistics, and the diverged fraction called the controller 98 % robust."""
    # positive feedback, k = -5: over 1 s some of the 8 runs pass the 0.9 m arm's length
    config = MCConfig(controller="dfs", params={"k": -5.0}, n_scenarios=8, chunk=8, scenarios=ScenarioSpec(horizon_s=1.0))
    runner = montecarlo._Runner(config)
    batch = runner.sample(0)
    plant = batch_plant(runner.beam, config.n_modes, config.scenarios.dt, config.method, batch, runner.nominal)
    m = jax.device_get(jf.rollout(plant, runner.controller, runner.params, batch, output="metrics"))
    assert not m.diverged.any() and m.peak_abs_state.max() < 1e6  # no run blew up
    beyond = m.peak_tip_m > config.beam.length_m
    assert 0 < beyond.sum() < 8
    summary = run_montecarlo(config, tmp_path, progress=False, figures=False)
    assert summary["diverged_fraction"] == beyond.mean()
    assert summary["metrics"]["peak_tip_deflection_m"]["max"] == pytest.approx(float(m.peak_tip_m[~beyond].max()), rel=1e-6)
    assert "more than the arm's length" in summary["diverged_definition"]
    # the tip bands leave the same runs out
    assert montecarlo.tip_bands(runner, [50.0])[2:] == (8 - beyond.sum(), 8)


def test_diverged_runs_are_counted_not_averaged(tmp_path):
    config = MCConfig(controller="dfs", params={"k": -400.0}, n_scenarios=8, chunk=8, scenarios=ScenarioSpec(horizon_s=2.0))
    summary = run_montecarlo(config, tmp_path, progress=False, figures=False)
    assert summary["diverged_fraction"] == 1.0
    assert summary["metrics"]["tip_ise"]["count"] == 0 and summary["metrics"]["tip_ise"]["mean"] is None
    # the tip bands leave them out too (they drew 1e22 m bands over a 2 ms axis)
    t, bands, kept, count = montecarlo.tip_bands(montecarlo._Runner(config), [50.0])
    assert (kept, count) == (0, 8) and bands.shape == (1, t.size) and np.all(np.isnan(bands))


# The paper's loop over five chunks, the last one partial: the uninterrupted run of the resume
# test and, in this process, the single-device run of the device-count test. The chunk is not
# a multiple of 4 devices, so that the 4-device run pads it.
FULL_CONFIG = MCConfig(controller="dfs+fuzzy", n_scenarios=70, chunk=15, scenarios=SPEC)


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    return run_montecarlo(FULL_CONFIG, tmp_path_factory.mktemp("full"), progress=False, figures=False)


def test_resume_after_interrupt_gives_the_same_summary(tmp_path, full_run):
    config, full = FULL_CONFIG, full_run
    interrupt = stop_at_chunk(2)

    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path / "cut", progress=False, figures=False, on_chunk=interrupt)
    assert sorted(os.listdir(tmp_path / "cut" / "chunks")) == [f"chunk_{i:06d}.npz" for i in range(3)]
    with pytest.raises(ValueError, match=r"pass --resume \(resume=True\) to continue it, choose another --out \(out_dir\), or delete the folder to start over in it"):
        run_montecarlo(config, tmp_path / "cut", progress=False)
    resumed = run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False)
    assert resumed["metrics"] == full["metrics"] and resumed["n_scenarios"] == 70
    with pytest.raises(ValueError, match=r"another configuration \(changed: seed: 0 -> 3\): resume with the command that started it, its --config and options, and --resume$"):
        run_montecarlo(MCConfig(controller="dfs+fuzzy", n_scenarios=70, chunk=15, seed=3, scenarios=SPEC), tmp_path / "cut", resume=True, progress=False)
    with pytest.raises(ValueError, match="has chunks of 15 scenarios, this one 16 .*; pass --chunk 15"):
        run_montecarlo(MCConfig(controller="dfs+fuzzy", n_scenarios=70, chunk=16, scenarios=SPEC), tmp_path / "cut", resume=True, progress=False)
    # fewer scenarios than the run's chunk cap the chunk whatever --chunk says: the fix names both
    with pytest.raises(ValueError, match="has chunks of 15 scenarios, this one 14 .*; pass --scenarios 15 or more and --chunk 15"):
        run_montecarlo(MCConfig(controller="dfs+fuzzy", n_scenarios=14, chunk=15, scenarios=SPEC), tmp_path / "cut", resume=True, progress=False)
    # as many scenarios as the run's chunk: --chunk alone gives it back
    with pytest.raises(ValueError, match="has chunks of 15 scenarios, this one 8 .*; pass --chunk 15$"):
        run_montecarlo(MCConfig(controller="dfs+fuzzy", n_scenarios=15, chunk=8, scenarios=SPEC), tmp_path / "cut", resume=True, progress=False)
    # a refused resume leaves the finished run's summary; an interrupted one removes it, since
    # it would describe the run before the resume
    assert (tmp_path / "cut" / "summary.json").exists()
    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False, on_chunk=interrupt)
    assert not (tmp_path / "cut" / "summary.json").exists()
    # resuming a folder without a Monte Carlo run is refused before anything is written (but
    # the empty run lock, taken before the folder is checked)
    (tmp_path / "tune").mkdir()
    with pytest.raises(ValueError, match="holds no Monte Carlo run"):
        run_montecarlo(config, tmp_path / "tune", resume=True, progress=False)
    assert [p.name for p in (tmp_path / "tune").iterdir()] == [".jaxflex-run.lock"]
    # a damaged or foreign chunk is named, with what to do, not met with a zip or index error
    chunk = tmp_path / "cut" / "chunks" / "chunk_000003.npz"
    good = chunk.read_bytes()
    chunk.write_bytes(good[: len(good) // 2])
    with pytest.raises(ValueError, match=r"--resume: .*chunk_000003.npz is damaged \(not a chunk's .npz archive\); delete it and pass --resume again"):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False)
    chunk.write_bytes(b"\x80junk")  # NumPy's own message for this one was about pickled data
    with pytest.raises(ValueError, match=r"--resume: .*chunk_000003.npz is damaged \(not a chunk's .npz archive\); delete it and pass --resume again"):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False)
    np.savez(chunk, tip_ise=np.zeros(15))
    with pytest.raises(ValueError, match=r"chunk_000003.npz does not hold this run's 15-scenario columns \(tip_ise \(15,\)\)"):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False)
    names = [*montecarlo.metric_names(config.n_modes), "diverged"]
    np.savez(chunk, **{name: np.zeros(14) for name in names})  # every column, one row short
    with pytest.raises(ValueError, match=r"chunk_000003.npz does not hold this run's 15-scenario columns \(.*tip_ise \(14,\)"):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False)
    # every column and one more, a 3-mode run's mode 3: another run's chunk, not this one's
    np.savez(chunk, **{name: np.zeros(15) for name in names}, reduction_db_mode3=np.zeros(15))
    with pytest.raises(ValueError, match=r"chunk_000003.npz does not hold this run's 15-scenario columns \(.*reduction_db_mode3 \(15,\)"):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False, figures=False)
    # chunks without montecarlo.json cannot be matched to a configuration: a new run would
    # have taken them as its own
    (tmp_path / "cut" / "montecarlo.json").unlink()
    fix = r"has no montecarlo.json to say which run wrote them, so they cannot be used: delete .*chunks and start again{}, or choose another --out"
    with pytest.raises(ValueError, match="holds chunk files but .*" + fix.format("")):
        run_montecarlo(MCConfig(controller="fuzzy", n_scenarios=70, chunk=15, scenarios=SPEC), tmp_path / "cut", progress=False)
    # resumed, it was told to leave out --resume, which then sent it to another --out
    with pytest.raises(ValueError, match="--resume: .*holds chunk files but .*" + fix.format(" without --resume")):
        run_montecarlo(config, tmp_path / "cut", resume=True, progress=False)


# FULL_CONFIG through the command line, in float64 so that the statistics can be compared to
# 1e-12 (the order of the additions differs with the number of shards).
_CLI_CONFIG = """
controller = "dfs+fuzzy"
n_scenarios = 70
chunk = 15
[scenarios]
horizon_s = 0.3
impulse_max_n = 0.5
youngs_modulus_rel = 0.1
noise_angle_rad = 1e-6
"""


def test_statistics_do_not_depend_on_the_device_count(tmp_path, full_run):
    """`jaxflex montecarlo --cpu-devices 4` in a fresh process runs on 4 devices and gives the
    statistics of the 1-device run (float64, 1e-12: only the order of additions differs)."""
    (tmp_path / "mc.toml").write_text(_CLI_CONFIG)
    results = {}
    # This process, when it is a plain single-CPU-device one, has made the 1-device run already
    # (full_run); otherwise (an accelerator, or XLA flags of its own) the command line makes it.
    in_process = jax.default_backend() == "cpu" and jax.device_count() == 1 and not os.environ.get("XLA_FLAGS")
    if in_process:
        results[1] = full_run
    for devices in (4,) if in_process else (1, 4):
        out_dir = tmp_path / f"d{devices}"
        command = [sys.executable, "-m", "jaxflex.cli", "montecarlo", "--config", str(tmp_path / "mc.toml"), "--x64", "--cpu-devices", str(devices), "--no-progress", "--out", str(out_dir)]
        out = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=600)
        assert out.returncode == 0, out.stderr
        assert f"on {devices} device(s)" in out.stdout
        results[devices] = json.loads((out_dir / "summary.json").read_text())
    assert results[1]["devices"] == 1 and results[4]["devices"] == 4
    # 15 scenarios per chunk on 4 devices run padded to 16: the chunk files hold the 15 alone
    with np.load(tmp_path / "d4" / "chunks" / "chunk_000000.npz") as chunk:
        assert {chunk[name].shape for name in chunk.files} == {(15,)}
    assert results[1]["diverged_fraction"] == results[4]["diverged_fraction"]
    for name, stats in results[1]["metrics"].items():
        for key, value in stats.items():
            other = results[4]["metrics"][name][key]
            if value is None:
                assert other is None
            else:
                np.testing.assert_allclose(other, value, rtol=1e-12, err_msg=f"{name}.{key}")


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ScenarioSpec(noise_velocity_rad_s=-0.1), "noise_velocity_rad_s must be a finite number >= 0"),
        (lambda: MCConfig(percentiles=(5.0, 101.0)), r"percentiles must be numbers in \[0, 100\]"),
        (lambda: MCConfig(n_scenarios=0), "n_scenarios must be an integer >= 1"),
        (lambda: MCConfig(controller="lqr"), "controller must be one of"),
        (lambda: MCConfig(seed=1.5), "seed must be an integer"),
        (lambda: MCConfig(seed=2**63), r"seed must be an integer in \[-2\*\*63, 2\*\*63\)"),
        (lambda: MCConfig(percentiles=[True]), r"percentiles must be numbers in \[0, 100\]"),
        (lambda: MCConfig(percentiles=50), r"percentiles must be numbers in \[0, 100\]"),
        (lambda: MCConfig(scenarios={"horizon_s": 1.0}), "scenarios must be a ScenarioSpec"),
        (lambda: MCConfig(params=None), "params must be a dict"),
        (lambda: MCConfig(delay="sinc"), "delay must be one of"),
        (lambda: MCConfig(fuzzy_temperature=-0.1), r"fuzzy_temperature must be 0 \(the faithful controller\) or a Python float in \[1e-05, 1\]"),
        (lambda: MCConfig(fuzzy_temperature=1e155), r"fuzzy_temperature must be 0 .* in \[1e-05, 1\] \(the smooth mode\); got 1e\+155"),
        (lambda: ScenarioSpec(horizon_s=float("nan")), "horizon_s must be a finite number"),
        (lambda: MCConfig(percentiles=(5.0, 99.99999, 100.0)), r"percentiles must differ in their first 6 significant digits .*\['p5', 'p100', 'p100'\]"),
        (lambda: ScenarioSpec(youngs_modulus_rel=1.0), r"youngs_modulus_rel must be in \[0, 1\); got 1.0"),
        (lambda: ScenarioSpec(impulse_max_n=1.0, impulse_duration_s=5e-4), "impulse_duration_s must be >= dt = 0.001 s when impulses are on; got 0.0005"),
        # parameter values, when the config is made (they were refused only when the run started)
        (lambda: MCConfig(params={"tau_s": -1.0}), r"tau_s must be finite and > 0; got -1.0"),
        (lambda: MCConfig(params={"tau_s": 1.0}), r"tau_s must be in \(0, 0.064\] s .*the capacity key of a tune or montecarlo config"),
        (lambda: MCConfig(controller="fuzzy", params={"k1": -1}), r"k1 must be finite and > 0; got -1"),
        (lambda: MCConfig(params={"tau_s": 0.0055}, delay="nearest"), r"whole number of samples .*delay = 'linear' or 'cubic' in by_name and the tune and montecarlo configs"),
        (lambda: MCConfig(beam={"length_m": 1.0}), r"beam must be a BeamParams; got \{'length_m': 1.0\}"),
    ],
)
def test_impossible_descriptions_are_refused(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_cli_refuses_unknown_config_key(tmp_path, capsys):
    from jaxflex import cli
    from tuning.tuner import TuneConfig

    bad = tmp_path / "mc.toml"
    bad.write_text("scenarioz = 3\n")
    assert cli.main(["montecarlo", "--config", str(bad), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert f"unknown config key(s) ['scenarioz'] in {bad}; accepted: [" in capsys.readouterr().err
    bad.write_text("[scenarios]\nhorizon = 3\n")  # a table's key, refused by the table's own check, names the file too
    for command in ("montecarlo", "tune", "stability"):
        assert cli.main([command, "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
        assert f"unknown scenario key(s) ['horizon'] in {bad}; accepted: [" in capsys.readouterr().err
    bad.write_text("[initial]\nkk = 3\n")  # tune's own check of [initial]
    assert cli.main(["tune", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert f"unknown initial parameter(s) ['kk'] for dfs in {bad}; accepted: ['k', 'tau_s']" in capsys.readouterr().err
    with pytest.raises(fileio.UnknownKeys) as refused:  # the library, which does not know the file, names none
        TuneConfig.from_mapping({"initial": {"kk": 3.0}})
    assert str(refused.value) == "unknown initial parameter(s) ['kk'] for dfs; accepted: ['k', 'tau_s']"
    # a misspelt key that is the start of the refusal's first word, or that word itself, is
    # not the value refused: "unknown config key(s) ['unknown']" read "unknown of FILE config key(s)"
    for text, what in (("u = 1\n", "config key(s) ['u']"), ("unknown = 1\n", "config key(s) ['unknown']"), ("[scenarios]\nunknown = 1\n", "scenario key(s) ['unknown']")):
        bad.write_text(text)
        assert cli.main(["tune", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
        assert capsys.readouterr().err.splitlines()[-1].startswith(f"jaxflex tune: error: unknown {what} in {bad}; accepted: ["), text
    bad.write_text('controller = "dfs"\nsteps = 300\n[objective]\ntip_ise = 1.0\n')  # the config a tune run was given
    assert cli.main(["montecarlo", "--config", str(bad), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert f"--config: {bad} is a tune config: montecarlo does not read ['objective', 'steps']. Pass the tuned.json the run wrote as --params" in capsys.readouterr().err


def test_cli_says_how_many_runs_did_not_settle(tmp_path, capsys):
    """A loop that grows too slowly to diverge within the horizon (or, here, the open loop over
    50 ms) settles in no run, and a diverged fraction of 0 alone would read as all well."""
    from jaxflex import cli

    config = tmp_path / "mc.toml"
    config.write_text("band_scenarios = 2\n[params]\nk = 30.0\nk1 = 1.5\n[scenarios]\nhorizon_s = 0.05\n")
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--scenarios", "3", "--out", str(tmp_path / "o"), "--no-progress", "--unroll", "2"]) == 0
    printed, err = capsys.readouterr()
    assert f"note: open_loop does not use [params] k, k1 of {config} (it reads none)" in err  # --controller overrode the config's controller
    assert "diverged fraction 0" in printed
    assert json.loads((tmp_path / "o" / montecarlo.META).read_text())["config"]["unroll"] == 2  # --unroll reached the run
    assert "note: 3 of the 3 runs that did not diverge had not settled by the end of the 0.05 s horizon" in err
    assert f"reads there as a large dB reduction: each run's row is in {tmp_path / 'o' / 'chunks'})" in err
    # a resume that sets neither --chunk nor --unroll takes the folder's (it compared the
    # defaults, 4096 and 1, with them and was refused: 'changed: unroll: 2 -> 1')
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--scenarios", "5", "--out", str(tmp_path / "o"), "--no-progress", "--resume"]) == 0
    assert f"montecarlo: --resume: --chunk 3 and --unroll 2, as the run in {tmp_path / 'o'} recorded\n" in capsys.readouterr().err
    meta = json.loads((tmp_path / "o" / montecarlo.META).read_text())
    assert (meta["chunk"], meta["config"]["unroll"], meta["n_scenarios"]) == (3, 2, 5)  # the resume's count recorded
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["n_scenarios"] == 5
    # nor --scenarios: the folder's count (it ran the default 10,000 instead, silently)
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--out", str(tmp_path / "o"), "--no-progress", "--resume"]) == 0
    assert f"montecarlo: --resume: --scenarios 5, --chunk 3 and --unroll 2, as the run in {tmp_path / 'o'} recorded\n" in capsys.readouterr().err
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["n_scenarios"] == 5
    # fewer than recorded, from the config or --scenarios: said (it shrank the run silently)
    config.write_text("band_scenarios = 2\nn_scenarios = 4\n[params]\nk = 30.0\nk1 = 1.5\n[scenarios]\nhorizon_s = 0.05\n")
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--out", str(tmp_path / "o"), "--no-progress", "--resume"]) == 0
    assert f"note: --resume: n_scenarios of {config} asked for 4 scenarios, where the run in {tmp_path / 'o'} had recorded 5" in capsys.readouterr().err
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--scenarios", "3", "--out", str(tmp_path / "o"), "--no-progress", "--resume"]) == 0
    assert "note: --resume: --scenarios asked for 3 scenarios, where the run in" in capsys.readouterr().err
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["n_scenarios"] == 3
    # below the folder's chunk of 3: refused, without the note that the folder took the count
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--scenarios", "2", "--out", str(tmp_path / "o"), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "has chunks of 3 scenarios, this one 2" in err and "note: --resume" not in err
    assert json.loads((tmp_path / "o" / montecarlo.META).read_text())["n_scenarios"] == 3
    assert cli.main(["montecarlo", "--controller", "open_loop", "--config", str(config), "--scenarios", "5", "--out", str(tmp_path / "o"), "--no-progress", "--resume", "--unroll", "1"]) == 2
    assert "changed: unroll: 2 -> 1" in capsys.readouterr().err  # one given is compared, not replaced
    # nor --controller or --seed: the folder's (it took the counts, then refused the default
    # controller as "changed"); a value equal to the default is taken without a word
    assert cli.main(["montecarlo", "--config", str(config), "--scenarios", "3", "--out", str(tmp_path / "o"), "--no-progress", "--resume"]) == 0
    assert f"montecarlo: --resume: --chunk 3, --unroll 2 and --controller open_loop, as the run in {tmp_path / 'o'} recorded\n" in capsys.readouterr().err


def test_cli_params_run_the_controller_as_tuned(tmp_path, capsys):
    """`--params tuned.json` takes the tuned run's delay approximation, Pade order, capacity,
    fuzzy temperature and arm, not the Monte Carlo defaults."""
    from jaxflex import cli

    tuned = tmp_path / "tuned.json"
    arm_table = {**BeamParams(length_m=0.6, payload_mass_kg=0.05)._asdict()}  # as tuned.json holds it, None included
    named = {"k": 45.0, "tau_s": 0.006, "k1": 1.1, "k2": 0.25, "k3": 0.9}
    tuned.write_text(json.dumps({"controller": "dfs+fuzzy", "params": named, "config": {
        "capacity": 16, "delay": "pade", "pade_order": 5, "fuzzy_temperature": 0.03, "beam": arm_table, "n_modes": 3, "method": "zoh"}}))
    config = tmp_path / "mc.toml"
    # the config's own pade_order beats the tuned run's; the --scenarios flag beats the config's
    config.write_text("band_scenarios = 2\nn_scenarios = 5\npade_order = 4\n[scenarios]\nhorizon_s = 0.05\n")
    out = tmp_path / "o"
    # the default chunk (4096) is capped at the 3 scenarios asked for
    assert cli.main(["montecarlo", "--params", str(tuned), "--config", str(config), "--scenarios", "3", "--out", str(out), "--no-progress"]) == 0
    printed, err = capsys.readouterr()
    assert "peak tip deflection (m): mean " in printed and ", p50 " in printed and "None" not in printed
    assert "was tuned for" not in err  # the model it was tuned on is the one that runs
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controller"] == "dfs+fuzzy" and summary["params"] == named
    assert summary["controller_options"] == {"capacity": 16, "delay": "pade", "pade_order": 4, "fuzzy_temperature": 0.03}
    assert summary["beam"] == arm_table and summary["chunk"] == 3
    assert (summary["n_modes"], summary["method"]) == (3, "zoh")  # the model it was tuned on
    with np.load(out / "chunks" / "chunk_000000.npz") as data:
        assert data["diverged"].shape == (3,)
    # the statistics are those of the tuned controller, run directly with its options
    direct = MCConfig(
        controller="dfs+fuzzy", params=named, n_scenarios=3, chunk=3, band_scenarios=2, scenarios=ScenarioSpec(horizon_s=0.05),
        capacity=16, delay="pade", pade_order=4, fuzzy_temperature=0.03, beam=BeamParams(length_m=0.6, payload_mass_kg=0.05), n_modes=3, method="zoh",
    )
    assert run_montecarlo(direct, tmp_path / "direct", progress=False, figures=False)["metrics"] == summary["metrics"]
    # and the runner simulates that arm, not the paper's
    arm_plant = discretize(make_plant(BeamParams(length_m=0.6, payload_mass_kg=0.05), 3), 1e-3, "zoh")
    np.testing.assert_allclose(montecarlo._Runner(direct).nominal.Ad, arm_plant.Ad, rtol=1e-12)
    assert not np.allclose(arm_plant.Ad, discretize(make_plant(BeamParams(), 3), 1e-3, "zoh").Ad)
    # a config's [params] beside --params: one of the two would be dropped without a word
    config.write_text("band_scenarios = 2\n[params]\nk = 30.0\n[scenarios]\nhorizon_s = 0.05\n")
    assert cli.main(["montecarlo", "--params", str(tuned), "--config", str(config), "--scenarios", "3", "--out", str(tmp_path / "both"), "--no-progress"]) == 2
    assert f"--params {tuned} and [params] in {config} both set the controller's parameters: give one of them" in capsys.readouterr().err
    assert not (tmp_path / "both").exists()


def test_params_tuned_at_another_dt_run_at_that_dt(tmp_path, capsys):
    """A tuned.json from a 2 ms run: montecarlo --params runs it at 2 ms (its 50 ms delay fits
    the 32-sample buffer there), and reproduce --params, at the paper's 1 ms, refuses it by name."""
    from jaxflex import cli

    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"controller": "dfs", "params": {"k": 20.0, "tau_s": 0.05}, "config": {"capacity": 32, "delay": "linear", "scenarios": {"dt": 0.002}}}))
    config = tmp_path / "mc.toml"
    config.write_text("band_scenarios = 2\n[scenarios]\nhorizon_s = 0.1\n")
    out = tmp_path / "o"
    assert cli.main(["montecarlo", "--params", str(tuned), "--config", str(config), "--scenarios", "2", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenarios"]["dt"] == 0.002 and summary["scenarios"]["horizon_s"] == 0.1
    # a config's own dt takes precedence, and is checked against the tuned delay
    config.write_text("[scenarios]\nhorizon_s = 0.1\ndt = 0.001\n")
    assert cli.main(["montecarlo", "--params", str(tuned), "--config", str(config), "--scenarios", "2", "--out", str(tmp_path / "p"), "--no-progress"]) == 2
    assert "tau_s must be in (0, 0.032] s" in capsys.readouterr().err
    # one that fits runs, and says that the gains were tuned at another dt
    config.write_text("band_scenarios = 2\n[scenarios]\nhorizon_s = 0.1\ndt = 0.004\n")
    assert cli.main(["montecarlo", "--params", str(tuned), "--config", str(config), "--scenarios", "2", "--out", str(tmp_path / "q"), "--no-progress"]) == 0
    assert f"note: {tuned} was tuned for dt = 0.002 s (here 0.004 s); --config sets what runs here" in capsys.readouterr().err
    assert cli.main(["reproduce", "--params", str(tuned), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "cannot run on the paper's scenario (dt = 0.001 s): tuned at dt = 0.002 s, run at dt = 0.001 s: tau_s must be in (0, 0.032] s" in err
    # reproduce has no capacity option: the message names where these gains' buffer is set
    assert "tau_s must be in (0, 0.032] s (the delay buffer holds 32 samples of 0.001 s); got 0.05 s. The buffer is the capacity in the tuned.json's config (32 samples), which its tune run set." in err
    assert "dfs()" not in err


def test_the_band_figure_says_how_many_of_chunk_0s_scenarios_it_draws(tmp_path, monkeypatch):
    """The bands' title reads "over KEPT of COUNT scenarios": those left after the diverged
    ones, of the band scenarios drawn from chunk 0 (2 of 5 here, from a stand-in tip_bands);
    the median is drawn beside the percentiles asked for."""
    from types import SimpleNamespace

    config = MCConfig(controller="dfs", n_scenarios=3, scenarios=ScenarioSpec(horizon_s=0.05), percentiles=(10.0, 90.0))
    columns = {name: np.asarray([1.0, 2.0, 3.0]) for name in montecarlo.metric_names(config.n_modes)}
    columns["diverged"] = np.zeros(3, bool)
    drawn = {}
    monkeypatch.setattr(plotting, "histograms", lambda *args: None)
    monkeypatch.setattr(plotting, "percentile_bands", lambda t, bands, percentiles, ylabel, title: drawn.update(percentiles=list(percentiles), title=title))
    monkeypatch.setattr(plotting, "save", lambda fig, path: None)
    monkeypatch.setattr(montecarlo, "tip_bands", lambda runner, percentiles: (np.arange(2) * 1e-3, np.zeros((len(percentiles), 2)), 2, 5))
    montecarlo._figures(SimpleNamespace(config=config, beam=config.beam), columns, str(tmp_path))
    assert "over 2 of 5 scenarios" in drawn["title"] and drawn["percentiles"] == [10.0, 50.0, 90.0]


def test_percentile_bands_pair_each_percentile_with_its_mirror():
    """A band joins p and 100 - p; a percentile without its mirror is a line of its own (the
    p99 of (10, 50, 90, 99) was once paired with p10)."""
    import matplotlib.pyplot as plt

    from jaxflex import plotting

    t = np.linspace(0, 1, 5)
    for percentiles, labels in (((10.0, 50.0, 90.0, 99.0), ["p10-p90", "median", "p99"]), ((5.0, 25.0, 50.0, 75.0, 95.0), ["p5-p95", "p25-p75", "median"])):
        bands = np.outer(np.asarray(percentiles), np.ones_like(t))
        fig = plotting.percentile_bands(t, bands, percentiles, "y", "title")
        assert sorted(fig.axes[0].get_legend_handles_labels()[1]) == sorted(labels)
        plt.close(fig)
    with pytest.raises(ValueError, match=r"bands must have shape \(2, 5\) \(len\(percentiles\), len\(t\)\)"):
        plotting.percentile_bands(t, np.zeros((3, 5)), (10.0, 90.0), "y", "title")


def test_numpy_scalars_are_accepted_and_stored_as_plain_numbers():
    numpy_cfg = MCConfig(n_scenarios=np.int64(40), chunk=np.int32(8), capacity=np.int64(64), pade_order=np.int64(8), seed=np.uint64(7), fuzzy_temperature=np.float32(0.5))
    plain_cfg = MCConfig(n_scenarios=40, chunk=8, capacity=64, pade_order=8, seed=7, fuzzy_temperature=0.5)
    assert all(type(getattr(numpy_cfg, name)) is int for name in ("n_scenarios", "chunk", "capacity", "pade_order", "seed"))
    assert type(numpy_cfg.fuzzy_temperature) is float
    assert type(MCConfig(beam=BeamParams(density_kg_m3=np.float32(2700.0))).beam.density_kg_m3) is float  # the arm too
    assert numpy_cfg.fingerprint() == plain_cfg.fingerprint()


def test_a_run_out_of_memory_is_named_and_leaves_no_run_behind(tmp_path, capsys, monkeypatch):
    """An out-of-memory chunk (XLA's RESOURCE_EXHAUSTED, e.g. horizon_s = 1e9) was a traceback,
    and the montecarlo.json written before it blocked the next run in that folder."""
    from jaxflex import cli

    def exhausted(self, index):
        raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 4000000000000 bytes.")

    monkeypatch.setattr(montecarlo._Runner, "run_chunk", exhausted)
    config = MCConfig(n_scenarios=2, scenarios=ScenarioSpec(horizon_s=0.05))
    assert cli.main(["montecarlo", "--scenarios", "2", "--out", str(tmp_path / "new"), "--no-progress"]) == 2
    assert "error: out of memory (RESOURCE_EXHAUSTED: Out of memory allocating 4000000000000 bytes.); lower the batch" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    with pytest.raises(RuntimeError):
        run_montecarlo(config, tmp_path / "kept", progress=False, figures=False)
    assert not (tmp_path / "kept" / "montecarlo.json").exists()
    monkeypatch.undo()
    assert run_montecarlo(config, tmp_path / "kept", progress=False, figures=False)["n_scenarios"] == 2  # no --resume needed


def test_statistics_leave_out_diverged_and_nonfinite_runs():
    """summary.json's statistics are over the runs that did not diverge; a settling time of
    +inf (not settled by the end) is counted apart, not averaged."""
    config = MCConfig(n_scenarios=3, percentiles=(50.0,))
    columns = {name: np.asarray([1.0, 5.0, 3.0]) for name in montecarlo.metric_names(config.n_modes)}
    columns["diverged"] = np.asarray([False, True, False])
    columns["settling_time_s"] = np.asarray([0.5, 0.2, np.inf])
    summary = montecarlo.summarize(config, columns)
    assert summary["diverged_fraction"] == pytest.approx(1 / 3)
    tip = summary["metrics"]["tip_ise"]
    assert (tip["count"], tip["nonfinite"], tip["mean"], tip["max"], tip["p50"]) == (2, 0, 2.0, 3.0, 2.0)
    settling = summary["metrics"]["settling_time_s"]
    assert (settling["count"], settling["nonfinite"], settling["mean"]) == (1, 1, 0.5)
    # a float32 run's statistics, computed in float64, are given with float32's digits: its
    # settling time of 0.312 s was 0.31200000643730164
    columns = {name: np.asarray(column, np.float32 if name != "diverged" else bool) for name, column in columns.items()}
    columns["settling_time_s"] = np.asarray([0.312, 0.2, 0.318], np.float32)
    settling = montecarlo.summarize(config, columns)["metrics"]["settling_time_s"]
    assert (settling["min"], settling["max"], settling["mean"], settling["p50"]) == (0.312, 0.318, 0.315, 0.315)


def test_statistics_at_the_ends_and_with_every_run_diverged():
    """p0 and p100 are the min and the max; with no run left the keys are the same, all None."""
    config = MCConfig(n_scenarios=4, percentiles=(0, 37.5, 100))
    values = np.asarray([4.0, 1.0, 3.0, 2.0])
    columns = {name: values for name in montecarlo.metric_names(config.n_modes)}
    columns["diverged"] = np.zeros(4, bool)
    tip = montecarlo.summarize(config, columns)["metrics"]["tip_ise"]
    # sorted 1, 2, 3, 4: the 37.5th percentile is at position 0.375 * 3 = 1.125, between 2 and 3
    assert (tip["p0"], tip["p37.5"], tip["p100"]) == (1.0, 2.125, 4.0)
    columns["diverged"] = np.ones(4, bool)
    gone = montecarlo.summarize(config, columns)["metrics"]["tip_ise"]
    assert set(gone) == set(tip) and {k: v for k, v in gone.items() if k not in ("count", "nonfinite")} == dict.fromkeys(set(tip) - {"count", "nonfinite"})


def test_cli_names_out_of_memory_and_lets_other_runtime_errors_through(tmp_path, monkeypatch, capsys):
    from jaxflex import cli

    def exhausted(args):
        raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 4.00GiB\ndetails")

    monkeypatch.setattr(cli, "_run", exhausted)
    assert cli.main(["montecarlo", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "jaxflex montecarlo: error: out of memory (RESOURCE_EXHAUSTED: Out of memory allocating 4.00GiB); lower the batch (--chunk, --scenarios) or the horizon (horizon_s)"

    def other(args):
        raise RuntimeError("boom")

    monkeypatch.setattr(cli, "_run", other)
    with pytest.raises(RuntimeError, match="boom"):
        cli.main(["montecarlo", "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()  # the folder it created, empty, is removed


def test_cli_distributed_options_are_checked_before_anything_runs(tmp_path, capsys):
    from jaxflex import cli

    assert cli.main(["montecarlo", "--distributed", "--process-id", "-1", "--out", str(tmp_path / "o")]) == 2
    assert "--process-id must be an integer >= 0; got -1" in capsys.readouterr().err
    assert cli.main(["montecarlo", "--process-id", "0", "--out", str(tmp_path / "o")]) == 2
    assert "--process-id only applies with --distributed" in capsys.readouterr().err
    out = str(tmp_path / "o")
    assert cli.main(["montecarlo", "--distributed", "--num-processes", "2", "--process-id", "2", "--out", out]) == 2
    assert "--process-id must be below --num-processes (2): 0 to 1; got 2" in capsys.readouterr().err
    # JAX took "localhost" to an IndexError and "localhost:abc" to a gRPC abort of the process
    for bad in ("localhost", "localhost:abc", "localhost:0", "localhost:65536", ":1234", "::1:1234", "[::1]", "[]:80", "[x]:80", "a b:80", "localhost:\u00b2"):
        with pytest.raises(SystemExit) as exit_info:
            cli.main(["montecarlo", "--distributed", "--coordinator", bad, "--num-processes", "1", "--process-id", "0", "--out", out])
        assert exit_info.value.code == 2
        assert f"argument --coordinator: expected HOST:PORT with a port from 1 to 65535 (an IPv6 host in brackets: [::1]:1234); got {bad!r}" in capsys.readouterr().err
    for good in ("localhost:1234", "10.0.0.1:65535", "[::1]:1", "[fe80::1]:8476", "node-7.cluster:29500"):
        assert cli._parser().parse_args(["montecarlo", "--coordinator", good]).coordinator == good
    assert not (tmp_path / "o").exists()


def test_cli_distributed_failure_names_the_options(tmp_path, monkeypatch, capsys):
    """JAX's own refusal names its arguments (coordinator_address); the message says which
    options to pass."""
    import jax

    from jaxflex import cli

    def initialize(**kwargs):
        raise ValueError("coordinator_address should be defined.")

    monkeypatch.setattr(jax.distributed, "initialize", initialize)
    assert cli.main(["montecarlo", "--distributed", "--out", str(tmp_path / "o")]) == 2
    assert ("jaxflex montecarlo: error: --distributed: coordinator_address should be defined. Pass --coordinator HOST:PORT, "
            "--num-processes and --process-id, or run under a cluster JAX detects (SLURM, Open MPI)") in capsys.readouterr().err


def test_model_line_counts_the_modes_above_nyquist():
    from jaxflex import cli
    from jaxflex.beam import BeamParams, natural_frequencies_hz

    freqs = np.asarray(natural_frequencies_hz(BeamParams(), 2), float)  # 13.3 and 36.5 Hz
    assert freqs[0] < 25 < freqs[1]  # at dt = 0.02 s the Nyquist frequency, 25 Hz, lies between them
    line = cli._model_line(BeamParams(), 2, 0.02)
    assert line.endswith("(Nyquist 25 Hz); 1 mode(s) above Nyquist alias in what the controller measures")
    assert "above Nyquist" not in cli._model_line(BeamParams(), 2, 1e-3)
    # a first mode exactly at Nyquist is refused, as one above it: the first of a few moduli
    # whose mode 1 some float dt puts exactly at 0.5 / dt
    for modulus in (71e9, 70e9, 72e9, 69e9, 73e9):
        arm = BeamParams(youngs_modulus_pa=modulus)
        f1 = float(np.asarray(natural_frequencies_hz(arm, 2), float)[0])
        near = 0.5 / f1 + np.arange(-300, 301) * np.spacing(0.5 / f1)
        exact = [float(dt) for dt in near if 0.5 / dt == f1]
        if exact:
            break
    assert exact
    with pytest.raises(ValueError, match=r"^dt must be below .* to lie below the Nyquist frequency"):
        cli._model_line(arm, 2, exact[0])
    # the damping is named too, as the ratio each flexible mode of the model run gets (read
    # here off the continuous plant's eigenvalues, -Re(s) / |s|): a damping_ratio of 1 meant
    # as 1 % shows as 1, and a given Rayleigh pair as itself
    def ratios(arm, n_modes):
        with jax.enable_x64(True):
            s = np.linalg.eigvals(np.asarray(make_plant(arm, n_modes).A))
        s = s[s.imag > 0]
        return ", ".join(f"{z:.4g}" for z in (-s.real / abs(s))[np.argsort(abs(s))])

    assert ratios(BeamParams(damping_ratio=0.5), 2) == "0.5, 0.5"
    assert " Hz with damping ratios 1, 1 in flexible modes 1-2 (damping_ratio = 1 of the 2-mode model), sampled every " in cli._model_line(BeamParams(damping_ratio=1.0), 2, 1e-3)
    given = BeamParams(rayleigh_alpha=0.5, rayleigh_beta=2e-5)
    assert f" Hz with damping ratios {ratios(given, 2)} in flexible modes 1-2 (Rayleigh alpha = 0.5 1/s, beta = 2e-05 s), sampled every " in cli._model_line(given, 2, 1e-3)
    # damping_ratio is that of the 2-mode model: the 1-mode model's one mode (15.7 Hz, not
    # 13.3) runs with another ratio, and a 4-mode model's higher modes with more
    for n_modes, modes in ((1, "mode 1"), (4, "modes 1-4")):
        shown = ratios(BeamParams(), n_modes)
        assert abs(float(shown.split(", ")[0]) - 0.01) > 5e-4 if n_modes == 1 else float(shown.split(", ")[3]) > 0.02
        expected = f"damping ratio{'s' if n_modes > 1 else ''} {shown} in flexible {modes} (damping_ratio = 0.01 of the 2-mode model), "
        assert expected in cli._model_line(BeamParams(), n_modes, 1e-3)


def test_the_dtype_is_part_of_a_runs_fingerprint():
    """A float32 run's chunks are not resumed under --x64 (nor the other way round)."""
    config = MCConfig(n_scenarios=3)
    with jax.enable_x64(False):
        f32 = config.fingerprint_fields(), config.fingerprint()
    with jax.enable_x64(True):
        f64 = config.fingerprint_fields(), config.fingerprint()
    assert (f32[0]["dtype"], f64[0]["dtype"]) == ("float32", "float64") and f32[1] != f64[1]
    # and a gain given as a float32 is not the float64 number it prints as (55.000008 in files)
    assert MCConfig(params={"k": np.float32(55.000008)}).fingerprint() != MCConfig(params={"k": 55.000008}).fingerprint()


def test_a_config_of_the_wrong_kind_is_refused(tmp_path):
    """A dict failed with an AttributeError ('dict' object has no attribute 'fingerprint')."""
    with pytest.raises(ValueError, match=r"config must be a MCConfig \(build one with MCConfig\(...\)\); got dict"):
        run_montecarlo({"n_scenarios": 8}, tmp_path)
    assert not os.listdir(tmp_path)


def test_percentiles_may_be_an_array():
    """A NumPy or JAX array of percentiles was refused as "must be numbers in [0, 100]" though
    it was; NumPy float32 elements too. They are stored as a tuple of Python floats."""
    for percentiles in (np.array([5.0, 50.0, 95.0]), jax.numpy.asarray([5.0, 50.0, 95.0]), [np.float32(5.0), 50, 95.0]):
        assert MCConfig(percentiles=percentiles).percentiles == (5.0, 50.0, 95.0)
    for percentiles in (np.array(50.0), np.array([5.0, 101.0]), np.array([[5.0]]), np.array([True])):
        with pytest.raises(ValueError, match=r"percentiles must be numbers in \[0, 100\] \(a non-empty list, tuple or 1-D array\)"):
            MCConfig(percentiles=percentiles)


def test_an_arm_that_overflows_the_run_dtype_is_refused_with_the_config():
    """With method = "zoh" the config built no plant: a float32 run printed the model at
    "nan, nan Hz" before the arm was refused (and before the fix, ran an inf/NaN plant)."""
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match=r"BeamParams.youngs_modulus_pa must be in \[1.175e-38, 3.403e\+38\] to be simulated in float32"):
            MCConfig(beam=BeamParams(youngs_modulus_pa=1e39), method="zoh")
    MCConfig(beam=BeamParams(youngs_modulus_pa=1e39), method="zoh")  # float64 holds it


class StandInRunner:
    """Stands in for montecarlo's simulation, so that only its bookkeeping runs: chunk i's
    metrics are all i + 1, and nothing diverges."""

    def __init__(self, config):
        self.config, self.chunk, self.n_devices = config, config.run_chunk, 1

    def run_chunk(self, index):
        return {name: np.full(self.chunk, 0.0 if name == "diverged" else index + 1.0) for name in [*montecarlo.metric_names(self.config.n_modes), "diverged"]}


def stop_at_chunk(stop: int):
    """An on_chunk that interrupts the run (as Ctrl-C) when chunk ``stop`` is done."""

    def interrupt(index):
        if index == stop:
            raise KeyboardInterrupt

    return interrupt


def test_resume_says_so_and_its_bar_starts_at_the_stored_chunks(tmp_path, monkeypatch, capsys):
    """A resumed run says how many chunks it found, and its progress bar starts at them: it
    said nothing, and the bar ran up from 0 through the stored chunks at a rate (and time
    left) that no simulated chunk had."""

    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    config = MCConfig(n_scenarios=45, chunk=10, scenarios=SPEC)
    interrupt = stop_at_chunk(2)

    clock = iter(range(0, 1000, 20))  # each reading 20 s after the last: a line every other chunk
    with monkeypatch.context() as patch, pytest.raises(KeyboardInterrupt):
        patch.setattr(montecarlo, "Heartbeat", functools.partial(Heartbeat, clock=lambda: next(clock)))
        run_montecarlo(config, tmp_path, progress=False, figures=False, on_chunk=interrupt)
    # without the bar it says that it compiles, and a line every 30 s (the bar sat at 0 through
    # the compile, and without it the run said nothing until its end)
    assert capsys.readouterr().err == ("montecarlo: 45 scenarios in 5 chunk(s) of 10 on 1 device(s), compiling\n"
                                       "montecarlo: 20 of 45 scenarios (44 %) after 40 s, about 50 s left\n")
    summary = run_montecarlo(config, tmp_path, resume=True, progress=True, figures=False)
    err = capsys.readouterr().err
    assert f"montecarlo: resuming: 3 of 5 chunks already in {tmp_path / 'chunks'}" in err
    assert "30/45" in err and "10/45" not in err, err
    # and only the chunks run add to it: it ends at 45/45, the stored ones not counted twice (75/45)
    counts = [int(n) for n in re.findall(r"\b(\d+)/45\b", err)]
    assert max(counts) == counts[-1] == 45, err
    assert summary["n_scenarios"] == 45 and summary["metrics"]["tip_ise"]["max"] == 5.0
    # without the bar (--no-progress) it still says so: it said nothing there
    summary = run_montecarlo(config, tmp_path, resume=True, progress=False, figures=False)
    assert capsys.readouterr().err == f"montecarlo: resuming: 5 of 5 chunks already in {tmp_path / 'chunks'}\n"  # nothing to compile


def test_heartbeat_says_the_end_and_leaves_the_compile_out_of_the_time_left(capsys):
    clock = iter([0, 100, 110, 140, 150, 160])  # made; a first update that compiled for 100 s; then 10 s each
    beat = Heartbeat("x", "steps", 5, clock=lambda: next(clock))
    for _ in range(5):
        beat.update(1, "; note")
    # at 140 s the rate since the first update gives 40 s left (93 s with the compile in it)
    assert capsys.readouterr().err == ("x: 1 of 5 steps (20 %) after 100 s; note\n"
                                       "x: 3 of 5 steps (60 %) after 140 s, about 40 s left; note\n"
                                       "x: 5 of 5 steps (100 %) after 160 s; note\n")
    for kwargs, said in ((dict(total=0), r"total must be an integer >= 1; got 0"), (dict(total=5, done=6), r"done must be an integer in \[0, 5\]; got 6"),
                         (dict(total=5, every_s=-1.0), r"every_s must be a finite number of seconds > 0; got -1.0")):
        with pytest.raises(ValueError, match=said):
            Heartbeat("x", "steps", **kwargs)


def test_tip_bands_are_over_the_first_scenarios_of_chunk_0():
    """The bands are the percentiles, at each time, of the tip deflection's magnitude of chunk
    0's first band_scenarios scenarios (the paper's one first), recomputed here one rollout at
    a time: the signed deflection's median sat at 0 (starts and strikes of either sign)."""
    spec = ScenarioSpec(horizon_s=0.05, impulse_max_n=0.5, impulse_duration_s=0.005, noise_angle_rad=1e-6)
    config = MCConfig(controller="dfs", n_scenarios=16, chunk=8, band_scenarios=5, scenarios=spec)
    t, bands, kept, count = montecarlo.tip_bands(montecarlo._Runner(config), [10.0, 50.0, 90.0])
    assert (kept, count) == (5, 5) and bands.shape == (3, 50)
    np.testing.assert_allclose(t, np.arange(50) * 1e-3)
    batch = sample_scenarios(spec, jax.random.fold_in(jax.random.key(0), 0), 8)
    plant = discretize(make_plant(BeamParams(), 2), 1e-3, "rk4")
    controller, params = controller_and_params("dfs", {}, 1e-3, config.capacity)
    tip = jax.jit(lambda sc: jf.rollout(plant, controller, params, sc).z[:, 1])
    tips = [np.asarray(tip(jax.tree.map(lambda a, i=i: a[i], batch))) for i in range(5)]
    np.testing.assert_allclose(bands, np.percentile(np.abs(np.array(tips)), [10, 50, 90], axis=0), rtol=1e-9, atol=1e-15)
    assert np.all(bands >= 0) and np.median(bands[1]) > 0


def test_histograms_leave_out_the_diverged_runs(tmp_path, monkeypatch):
    """As the statistics: a diverged run's metrics (1e22 m) are no part of the histograms."""
    from types import SimpleNamespace

    config = MCConfig(controller="dfs", n_scenarios=3, scenarios=ScenarioSpec(horizon_s=0.05))
    names = montecarlo.metric_names(config.n_modes)
    columns = {name: np.asarray([1.0, 1e22, 3.0]) for name in names}
    columns["diverged"] = np.asarray([False, True, False])
    drawn = {}
    monkeypatch.setattr(plotting, "histograms", lambda data, labels, title: drawn.update(data=data, labels=labels, title=title))
    monkeypatch.setattr(plotting, "percentile_bands", lambda *args: None)
    monkeypatch.setattr(plotting, "save", lambda fig, path: None)  # nothing drawn: what is handed to the figure is tested
    monkeypatch.setattr(montecarlo, "tip_bands", lambda runner, percentiles: (np.arange(2) * 1e-3, np.zeros((len(percentiles), 2)), 2, 3))
    montecarlo._figures(SimpleNamespace(config=config, beam=config.beam), columns, str(tmp_path))
    assert set(drawn["data"]) == set(names) and all(list(v) == [1.0, 3.0] for v in drawn["data"].values())
    assert drawn["title"].startswith("dfs: 2 of 3 runs (diverged left out)")
    # the axis labels: each metric's definition, the dB reductions' in their short form (the
    # whole definition, summary.json's, took four lines under the panel)
    assert drawn["labels"]["reduction_db_mode2"] == "vibration reduction at mode 2: open over closed-loop energy of the tip deflection (dB)"
    assert {k: v for k, v in drawn["labels"].items() if not k.startswith("reduction")} == montecarlo.METRICS


def test_an_unrolled_loop_reaches_both_rollouts_and_leaves_the_metrics():
    """MCConfig.unroll (3-3.8x faster chunks on an H100, slower on the CPU) changes the
    compiled loop, not the metrics: equal up to float32 rounding of another fusion. Over
    0.3 s no energy reaches float32's resolution, where the dB figures differ more (up to
    1.8 dB at 116 dB over 3 s, benchmarks/README.md)."""
    config = MCConfig(controller="dfs+fuzzy", n_scenarios=6, chunk=6, scenarios=SPEC, unroll=8)
    runner = montecarlo._Runner(config)
    assert str(jax.make_jaxpr(runner.evaluate)(runner.sample(0))).count("unroll=8") == 2  # the closed and the open loop
    plain = montecarlo._Runner(dataclasses.replace(config, unroll=1)).run_chunk(0)
    unrolled = runner.run_chunk(0)
    for name, values in plain.items():
        np.testing.assert_allclose(unrolled[name], values, rtol=1e-4, atol=1e-9, err_msg=name)
    assert config.fingerprint() != dataclasses.replace(config, unroll=1).fingerprint()  # a resume keeps the folder's loop
    for bad in (0, 65, 2.0, True):
        with pytest.raises(ValueError, match=rf"unroll must be an integer in \[1, 64\]; got {bad!r}"):
            MCConfig(unroll=bad)


def test_readme_montecarlo_config_is_the_defaults_it_says(tmp_path, monkeypatch, capsys):
    """The README's montecarlo config block is read by the command as written, and each value
    it shows is the default it says it is (the README had no key list at all)."""
    import pathlib

    from jaxflex import cli

    readme = (pathlib.Path(__file__).resolve().parent.parent / "README.md").read_text()
    section = readme.split("## Monte Carlo: `jaxflex montecarlo`", 1)[1]
    config = tmp_path / "mc.toml"
    config.write_text(section.split("```toml\n", 1)[1].split("```", 1)[0])

    class Given(Exception):
        pass

    def given(config, *args, **kwargs):
        raise Given(config)

    monkeypatch.setattr(montecarlo, "run_montecarlo", given)
    with pytest.raises(Given) as ran:  # the configuration the run would have been given
        cli.main(["montecarlo", "--config", str(config), "--out", str(tmp_path / "o"), "--no-progress"])
    assert "does not use [params]" not in capsys.readouterr().err
    config = ran.value.args[0]
    assert dataclasses.replace(config, params={}) == MCConfig()  # [beam] shows the paper's arm, [scenarios] the default horizon
    assert config.params.items() <= PAPER_PARAMS.items()  # [params] the paper's values


def test_a_mode_above_nyquist_has_no_reduction(tmp_path):
    """At dt = 0.02 s (Nyquist 25 Hz) mode 2, near 36 Hz, is sampled only as its alias: its dB
    reduction is NaN, counted apart, where mode 1's stays (the open loop's own: 0 dB)."""
    spec = ScenarioSpec(horizon_s=0.4, dt=0.02)
    config = MCConfig(controller="open_loop", n_scenarios=3, band_scenarios=2, scenarios=spec, method="zoh")
    runner = montecarlo._Runner(config)
    batch = runner.sample(0)
    with pytest.raises(ValueError, match=r"mode_freqs_hz must be below the Nyquist frequency, 25 Hz \(dt = 0.02 s\)"):  # rollout's own check
        jf.rollout(runner.nominal, open_loop(), OpenLoopParams(), batch, output="metrics", mode_freqs_hz=np.asarray([13.3, 36.5]))
    metrics = run_montecarlo(config, tmp_path, progress=False, figures=False)["metrics"]
    assert (metrics["reduction_db_mode2"]["count"], metrics["reduction_db_mode2"]["nonfinite"]) == (0, 3)
    assert metrics["reduction_db_mode1"]["count"] == 3 and abs(metrics["reduction_db_mode1"]["max"]) < 1e-6


def test_parameters_the_controller_does_not_read_leave_the_fingerprint():
    """A [params] k edited under the fuzzy controller, or a paper value given rather than left
    out, is the same run: a resume was refused as another configuration."""
    spec = ScenarioSpec(horizon_s=0.05)
    fuzzy = MCConfig(controller="fuzzy", n_scenarios=2, scenarios=spec)
    assert MCConfig(controller="fuzzy", params={"k": 30.0}, n_scenarios=2, scenarios=spec).fingerprint() == fuzzy.fingerprint()
    assert MCConfig(controller="fuzzy", params={"k1": 1.02}, n_scenarios=2, scenarios=spec).fingerprint() == fuzzy.fingerprint()
    assert MCConfig(controller="fuzzy", params={"k1": 1.5}, n_scenarios=2, scenarios=spec).fingerprint() != fuzzy.fingerprint()
    assert MCConfig(controller="dfs", params={"k": 30.0}, n_scenarios=2, scenarios=spec).fingerprint() != MCConfig(controller="dfs", n_scenarios=2, scenarios=spec).fingerprint()


def test_metric_definitions_name_each_mode_and_keep_their_words():
    """"mode i" becomes "mode 2" and nothing else: "the mode is at or above" read "the mode 2s"."""
    doc = montecarlo.metric_names(3)["reduction_db_mode2"]
    assert doc == montecarlo.REDUCTION_DOC.replace("at mode i of", "at mode 2 of") and "NaN when the mode is at or above" in doc


class _Ran(Exception):
    """Raised in place of a tune or Monte Carlo run: what a command says before it runs is under test."""


@pytest.fixture
def no_run(monkeypatch):
    import tuning.run

    def ran(*args, **kwargs):
        raise _Ran

    monkeypatch.setattr(tuning.run, "run_tune", ran)
    monkeypatch.setattr(montecarlo, "run_montecarlo", ran)


@pytest.mark.parametrize("command", ["tune", "montecarlo"])
def test_unit_slips_in_the_scenarios_are_noted_before_the_run(tmp_path, no_run, capsys, command):
    """A horizon shorter than mode 1's period (a modulus of 200 meant in GPa: 0.0007 Hz) and initial
    deflections that are not small against the arm (q0_std_m = 1 meant as 1 mm; a modal
    velocity over mode 1's angular frequency) are noted, naming where each value came from."""
    from jaxflex import cli

    config = tmp_path / "arm.toml"

    def notes(text):
        config.write_text(text)
        with pytest.raises(_Ran):
            cli.main([command, "--config", str(config), "--out", str(tmp_path / "o"), "--no-progress"])
        return [line for line in capsys.readouterr().err.splitlines() if line.startswith("note:")]

    assert notes("") == []  # the defaults: 1 mm and 1e-5 m/s, 13.3 Hz over 1 or 3 s
    slow = BeamParams(youngs_modulus_pa=200.0)
    f1 = float(beam.natural_frequencies_hz(slow, 2)[0])
    horizon = 3 if command == "montecarlo" else 1  # each command's default horizon_s
    assert 1 / f1 > 100
    assert notes("[beam]\nyoungs_modulus_pa = 200\n") == [
        f"note: mode 1's period, {1 / f1:.3g} s, is longer than the horizon, horizon_s = {horizon} s (the default), so a run sees less than one cycle of it "
        "(or the arm's values are off: a modulus in GPa or a length in mm lowers its frequencies)"]
    tail = ": the model is linear, for deflections small against the length, and montecarlo counts a tip beyond the length as diverged (SI units: 1 mm is 0.001)"
    assert notes("[scenarios]\nq0_std_m = 1\n") == [f"note: [scenarios] q0_std_m = 1 m of {config} gives initial modal deflections of 111% of the arm's length, 0.9 m" + tail]
    assert notes("[scenarios]\nq0_std_m = 0.08\n") == []  # under a tenth of the length: no note
    f1 = float(beam.natural_frequencies_hz(BeamParams(), 2)[0])
    v = 0.2 * 0.9 * 2 * np.pi * f1  # a velocity that swings mode 1 to a fifth of the length
    assert notes(f"[scenarios]\nqdot0_std_m_s = {v!r}\n") == [
        f"note: [scenarios] qdot0_std_m_s = {v:g} m/s of {config} gives initial modal deflections, over mode 1's angular frequency (2 pi x {f1:.4g} Hz), of 20% of the arm's length, 0.9 m" + tail]


def test_a_negative_dfs_gain_is_noted(tmp_path, no_run, capsys):
    """[params] k = -55 ran with every scenario diverged and no word; it is noted (not refused:
    the stability analysis takes either sign), and not for a controller that does not read k."""
    from jaxflex import cli

    config = tmp_path / "mc.toml"
    config.write_text("[params]\nk = -55\n")
    for controller, noted in (("dfs", True), ("dfs+fuzzy", True), ("fuzzy", False)):
        with pytest.raises(_Ran):
            cli.main(["montecarlo", "--config", str(config), "--controller", controller, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert (f"note: [params] k = -55 of {config} is negative, the opposite sign to the paper's 55" in err) is noted


def test_a_resumed_run_without_the_bar_counts_from_the_stored_chunks(tmp_path, monkeypatch, capsys):
    """--no-progress's lines after a resume count the 30 scenarios already stored, as the bar
    does."""
    from jaxflex.heartbeat import Heartbeat

    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    config = MCConfig(n_scenarios=45, chunk=10, scenarios=SPEC)
    interrupt = stop_at_chunk(2)

    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path, progress=False, figures=False, on_chunk=interrupt)
    capsys.readouterr()
    clock = iter(range(0, 1000, 20))  # every line is due
    monkeypatch.setattr(montecarlo, "Heartbeat", functools.partial(Heartbeat, clock=lambda: next(clock)))
    run_montecarlo(config, tmp_path, resume=True, progress=False, figures=False)
    counts = [int(n) for n in re.findall(r"montecarlo: (\d+) of 45 scenarios", capsys.readouterr().err)]
    assert counts and counts[-1] == 45 and min(counts) > 30


def test_each_column_is_its_run_metric_and_a_mode_at_the_nyquist_frequency_has_no_reduction():
    """Each column of a run's row is the RunMetrics field it is named for (every field a value
    of its own here: no other test recomputed the effort and final hub angle columns).
    Modes strictly below the Nyquist frequency (500 Hz at 1 ms) get a reduction,
    10 log10(open / closed); one at it gets NaN, as one above it does."""
    import jax.numpy as jnp

    from jaxflex.rollout import RunMetrics

    metrics = RunMetrics(*(jnp.asarray(v) for v in (0.1, 2.0, 0.3, 5.0, 7.0, 0.25, 0.2, 1.0, False)), jnp.asarray([1.0, 1.0]))
    row = montecarlo._metrics_row(metrics, jnp.asarray([10.0, 10.0]), jnp.asarray([499.0, 500.0]), 1.0, 500.0)
    assert set(row) == {*montecarlo.metric_names(2), "diverged"}
    expected = {"peak_tip_deflection_m": 0.1, "tip_ise": 2.0, "control_effort": 7.0, "final_hub_angle_rad": 0.25, "settling_time_s": 0.2, "diverged": 0.0}
    assert {name: float(row[name]) for name in expected} == expected
    assert float(row["reduction_db_mode1"]) == pytest.approx(10.0)
    assert np.isnan(float(row["reduction_db_mode2"]))


def test_each_unit_slip_note_at_its_threshold():
    """The notes a run prints before it starts, just past their documented thresholds: initial
    deflections of over a tenth of the arm's length (13 % here), a horizon shorter than mode 1's
    period (half of it), a damping_ratio of 0.5 or more."""
    from jaxflex import cli

    arm = BeamParams()
    spec = ScenarioSpec(q0_std_m=0.12)  # 0.12 m on the 0.9 m arm
    notes = cli._scenario_notes(arm, 2, spec, {"q0_std_m": spec.q0_std_m}, "c.toml")
    assert len(notes) == 1 and notes[0].startswith("[scenarios] q0_std_m = 0.12 m of c.toml gives initial modal deflections of 13%")
    f1 = float(np.asarray(beam.natural_frequencies_hz(arm, 2))[0])
    spec = ScenarioSpec(horizon_s=0.5 / f1)
    notes = cli._scenario_notes(arm, 2, spec, {"horizon_s": spec.horizon_s}, "c.toml")
    assert len(notes) == 1 and notes[0].startswith("mode 1's period")
    assert cli._model_line(BeamParams(damping_ratio=0.5), 2, 1e-3).endswith("; a damping_ratio of 0.5 damps the modes heavily (1 % is 0.01)")


def test_a_heartbeat_line_is_due_once_every_s_has_passed(capsys):
    """Readings at 0, 10 and 30 s with every_s = 30: the second update, at exactly 30 s, prints.
    Time left by the documented rate since the first update: (30 - 10) s per step x 3 steps."""
    clock = iter([0.0, 10.0, 30.0])
    beat = Heartbeat("x", "steps", 5, clock=lambda: next(clock))
    beat.update(1)
    beat.update(1)
    assert capsys.readouterr().err == "x: 2 of 5 steps (40 %) after 30 s, about 60 s left\n"


def test_recorded_settings_take_integer_counts_and_known_controllers_only(tmp_path):
    """What --resume runs at comes from the folder's record only where the record holds a
    usable value: JSON's true and false are no count or seed, and a controller name jaxflex
    does not know is not taken (the command line's, or its default, stands instead)."""
    def recorded(record):
        (tmp_path / montecarlo.META).write_text(json.dumps(record))
        return montecarlo.recorded_settings(tmp_path)

    assert recorded({"n_scenarios": True, "chunk": 4, "config": {"unroll": 2, "seed": False, "controller": "dfs"}}) == {"chunk": 4, "unroll": 2, "controller": "dfs"}
    assert recorded({"n_scenarios": 6, "chunk": 3, "config": {"unroll": 1, "seed": 5, "controller": "pid"}}) == {"n_scenarios": 6, "chunk": 3, "unroll": 1, "seed": 5}


def test_a_resume_at_the_recorded_count_says_nothing_about_fewer_scenarios(tmp_path, monkeypatch, capsys):
    """Asking a resume for as many scenarios as the folder recorded is no shrinking; asking for
    fewer is said (the run itself is stood in for: only the CLI's note is tested)."""
    from jaxflex import cli

    def summary(config, out, **kwargs):
        tip = {"mean": 0.01, "p5": 0.01, "p50": 0.01, "p95": 0.01}
        return {"n_scenarios": config.n_scenarios, "devices": 1, "diverged_fraction": 0.0, "percentiles": [5, 50, 95],
                "metrics": {"peak_tip_deflection_m": tip, "settling_time_s": {"nonfinite": 0, "count": config.n_scenarios}}}

    monkeypatch.setattr(montecarlo, "recorded_settings", lambda out: {"n_scenarios": 5})
    monkeypatch.setattr(montecarlo, "run_montecarlo", summary)
    args = ["montecarlo", "--controller", "dfs", "--scenarios", "5", "--out", str(tmp_path / "o"), "--no-progress", "--resume"]
    assert cli.main(args) == 0
    assert "note: --resume" not in capsys.readouterr().err
    assert cli.main([*args[:4], "4", *args[5:]]) == 0
    assert "note: --resume: --scenarios asked for 4 scenarios, where the run in" in capsys.readouterr().err


# -- audit 16 (the run loop): counts and percentiles refused, the resume bar and lines, atomic chunk files, summary.json last, the chunk as run, sharding, the seed --

TINY_SPEC = ScenarioSpec(horizon_s=0.02, impulse_max_n=0.5, noise_angle_rad=1e-6)


@pytest.mark.parametrize("name", ["chunk", "band_scenarios"])
def test_counts_below_one_are_refused(name):
    """MCConfig's doc: chunk >= 1; band_scenarios is a count of scenarios (>= 1, as the others)."""
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match=rf"{name} must be an integer >= 1; got {bad!r}"):
            MCConfig(**{name: bad})


def test_resume_with_a_missing_middle_chunk_counts_only_what_is_stored(tmp_path, monkeypatch, capsys):
    """45 scenarios in chunks of 10 (the last holds 5); chunk 1 deleted (as the damaged-chunk
    message tells): the stored chunks hold 10 + 10 + 10 + 5 = 35 scenarios, so the bar starts
    at 35/45 and the --no-progress lines count from 35 and end at 45."""
    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    config = MCConfig(n_scenarios=45, chunk=10, scenarios=TINY_SPEC)
    run_montecarlo(config, tmp_path, progress=False, figures=False)
    (tmp_path / "chunks" / "chunk_000001.npz").unlink()
    capsys.readouterr()
    summary = run_montecarlo(config, tmp_path, resume=True, progress=True, figures=False)
    err = capsys.readouterr().err
    assert "resuming: 4 of 5 chunks" in err
    counts = [int(n) for n in re.findall(r"\b(\d+)/45\b", err)]
    assert counts and counts[0] == 35 and counts[-1] == 45 and max(counts) == 45, err
    assert summary["n_scenarios"] == 45
    (tmp_path / "chunks" / "chunk_000001.npz").unlink()
    clock = iter(range(0, 1000, 40))  # every line due
    monkeypatch.setattr(montecarlo, "Heartbeat", functools.partial(Heartbeat, clock=lambda: next(clock)))
    run_montecarlo(config, tmp_path, resume=True, progress=False, figures=False)
    counts = [int(n) for n in re.findall(r"montecarlo: (\d+) of 45 scenarios", capsys.readouterr().err)]
    assert counts == [45], counts  # 35 stored + the 10 run now


def test_a_partial_resume_says_it_compiles(tmp_path, monkeypatch, capsys):
    """A resume with chunks left to run says it compiles (nothing to compile only when all are stored)."""
    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    config = MCConfig(n_scenarios=30, chunk=10, scenarios=TINY_SPEC)

    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path, progress=False, figures=False, on_chunk=stop_at_chunk(0))
    capsys.readouterr()
    run_montecarlo(config, tmp_path, resume=True, progress=False, figures=False)
    err = capsys.readouterr().err
    assert "montecarlo: resuming: 1 of 3 chunks" in err
    assert "montecarlo: 30 scenarios in 3 chunk(s) of 10 on 1 device(s), compiling\n" in err


def test_a_chunk_file_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """A write stopped part way (Ctrl-C in np.savez) leaves no chunk file: a resume would
    otherwise meet a truncated chunk_000000.npz."""
    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    config = MCConfig(n_scenarios=10, chunk=10, scenarios=TINY_SPEC)
    real = np.savez

    def stopped(f, **rows):
        real(f, **rows)
        f.seek(0)
        f.truncate(10)  # a part of the file written
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", stopped)
    with pytest.raises(KeyboardInterrupt):
        run_montecarlo(config, tmp_path, progress=False, figures=False)
    assert os.listdir(tmp_path / "chunks") == []


def test_summary_json_is_moved_in_last(tmp_path, monkeypatch):
    """The figures are moved into the folder before summary.json (its presence means the run finished)."""
    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    monkeypatch.setattr(montecarlo, "_figures", lambda runner, columns, stage: [open(os.path.join(stage, n), "wb").close() for n in montecarlo.FIGURES] and list(montecarlo.FIGURES))
    moved, real = [], os.replace

    def replace(src, dst):
        if os.path.dirname(os.path.abspath(os.fspath(dst))) == str(tmp_path):
            moved.append(os.path.basename(os.fspath(dst)))
        return real(src, dst)

    monkeypatch.setattr(fileio.os, "replace", replace)
    run_montecarlo(MCConfig(n_scenarios=4, chunk=4, scenarios=TINY_SPEC), tmp_path, progress=False, figures=True)
    finals = [name for name in moved if name in (*montecarlo.FIGURES, "summary.json")]
    assert sorted(finals) == sorted([*montecarlo.FIGURES, "summary.json"]) and finals[-1] == "summary.json", moved


def test_summary_says_the_chunk_as_run(tmp_path, monkeypatch, capsys):
    """chunk 10 over 4 scenarios runs one chunk of 4: the start line, the summary and the record say 4."""
    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    summary = run_montecarlo(MCConfig(n_scenarios=4, chunk=10, scenarios=TINY_SPEC), tmp_path, progress=False, figures=False)
    assert summary["chunk"] == 4 and summary["n_scenarios"] == 4
    assert "montecarlo: 4 scenarios in 1 chunk(s) of 4 on 1 device(s), compiling\n" in capsys.readouterr().err


_SHARD_SCRIPT = """
import jax
jax.config.update("jax_enable_x64", True)
from jaxflex import montecarlo
from jaxflex.scenarios import ScenarioSpec
assert jax.device_count() == 4
config = montecarlo.MCConfig(controller="dfs", n_scenarios=8, chunk=8, band_scenarios=1, scenarios=ScenarioSpec(horizon_s=0.01))
runner = montecarlo._Runner(config)
seen = []
real = runner.evaluate
def evaluate(batch):
    seen.extend(leaf.sharding for leaf in jax.tree.leaves(batch))
    return real(batch)
runner.evaluate = evaluate
rows = runner.run_chunk(0)
assert seen and all(len(s.device_set) == 4 and not s.is_fully_replicated for s in seen), seen
shapes = {len({idx[0].indices(8) for idx in s.devices_indices_map((8,) + (1,) * 0).values()}) for s in seen[:1]}
assert shapes == {4}, shapes  # the 8 scenarios split into 4 different blocks of rows
print("ok")
"""


def test_the_scenario_axis_is_split_over_the_devices():
    """Module doc: each chunk's scenario axis is sharded over all local devices. On 4 CPU
    devices every leaf handed to the compiled chunk is split (4 different row blocks), not
    replicated on each device (same results, 4x the work)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    out = subprocess.run([sys.executable, "-c", _SHARD_SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


def test_the_seed_picks_the_scenarios():
    """Module doc: chunk i holds the scenarios drawn from fold_in(key(seed), i). With seed 7,
    chunk 1's batch is that draw (not seed 0's), and its metrics differ from seed 0's."""
    from jaxflex.scenarios import sample_scenarios

    config = MCConfig(controller="dfs", n_scenarios=8, chunk=4, band_scenarios=1, seed=7, scenarios=TINY_SPEC)
    runner = montecarlo._Runner(config)
    spec = dataclasses.replace(TINY_SPEC, include_paper=False)
    expected = sample_scenarios(spec, jax.random.fold_in(jax.random.key(7), 1), 4)
    for got, want in zip(jax.tree.leaves(runner.sample(1)), jax.tree.leaves(expected)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    seed0 = montecarlo._Runner(MCConfig(controller="dfs", n_scenarios=8, chunk=4, band_scenarios=1, seed=0, scenarios=TINY_SPEC)).run_chunk(1)
    assert not np.array_equal(runner.run_chunk(1)["peak_tip_deflection_m"], seed0["peak_tip_deflection_m"])


def test_a_run_without_figures_lists_none(tmp_path, monkeypatch):
    """figures=False draws nothing, and summary.json's "figures" says so (an empty list)."""
    monkeypatch.setattr(montecarlo, "_Runner", StandInRunner)
    summary = run_montecarlo(MCConfig(n_scenarios=4, chunk=4, scenarios=TINY_SPEC), tmp_path, progress=False, figures=False)
    assert summary["figures"] == [] and not any((tmp_path / name).exists() for name in montecarlo.FIGURES)
    assert json.loads((tmp_path / "summary.json").read_text())["figures"] == []


def test_params_named_by_anything_but_strings_are_refused():
    """``params`` is a dict of values by name: a key that is no name is refused as such."""
    for bad in ({1: 55.0}, {("k",): 55.0}):
        with pytest.raises(ValueError, match=r"params must be a dict of parameter values by name; got \{"):
            MCConfig(params=bad)


@pytest.mark.parametrize("empty", [(), [], np.array([])])
def test_no_percentiles_is_refused(empty):
    """The message names a non-empty list: an empty one is refused, not run with no percentiles."""
    with pytest.raises(ValueError, match=r"percentiles must be numbers in \[0, 100\] \(a non-empty list, tuple or 1-D array\)"):
        MCConfig(percentiles=empty)
