"""Bad input to public entry points, found by a walkthrough that tried about 480 cases: each
of these leaked a TypeError or IndexError from deep inside, took a bad value silently, or
named a narrower range than the one checked. Each is now a ValueError naming the parameter."""

import numpy as np
import pytest

from jaxflex.analysis import vibration_reduction_db
from jaxflex.controllers import DFSParams, by_name, dfs, fuzzy
from jaxflex.montecarlo import MCConfig, run_montecarlo
from jaxflex.plant import discretize, make_plant
from jaxflex.rollout import rollout
from jaxflex.scenarios import paper_scenario
from tuning.identify import identify_modes
from tuning.tuner import TuneConfig, tune


@pytest.mark.parametrize(
    "call, match",
    [
        # dt was checked only when a DFS was built: open_loop and fuzzy took any dt
        (lambda: by_name("open_loop", dt=-1.0), r"dt must be finite and > 0; got -1.0"),
        (lambda: by_name("fuzzy", dt="x"), r"dt must be a real number; got 'x'"),
        # an IndexError on t[0], and an empty channel list read as 'no mode above the noise'
        (lambda: identify_modes([], []), r"the record must hold at least 2 samples of at least 1 channel; got t of shape \(0,\)"),
        (lambda: identify_modes(np.arange(100) * 1e-3, np.zeros((100, 0))), r"at least 1 channel; got t of shape \(100,\) and y of shape \(100, 0\)"),
        # TypeErrors from len(None) and iterating None
        (lambda: fuzzy(rules=None), r"rules must be a sequence of \(angle, velocity, torque\) triples; got None"),
        (lambda: fuzzy(set_names=None), r"set_names must be a sequence of at least 2 strings; got None"),
        # os.fspath's TypeError; a callback that is no function failed after sampling and compiling
        (lambda: tune(TuneConfig(), None), r"out_dir \(--out\) must be a folder's path \(a non-empty str or os.PathLike\); got None"),
        (lambda: run_montecarlo(MCConfig(), 3), r"out_dir \(--out\) must be a folder's path .*; got 3"),
        (lambda: tune(TuneConfig(), "unused", on_step=5), r"on_step must be None or a function called with the step number; got int 5"),
        (lambda: run_montecarlo(MCConfig(), "unused", on_chunk="x"), r"on_chunk must be None or a function called with the chunk's index; got str 'x'"),
        # dict(None)'s TypeError
        (lambda: TuneConfig.from_mapping(None), r"values must be a mapping of the config's keys .*; got NoneType None"),
        # said 'integer >= 1' while 101 was refused later
        (lambda: TuneConfig(n_modes=0), r"n_modes must be an integer in \[1, 100\]; got 0"),
        (lambda: MCConfig(n_modes=101), r"n_modes must be an integer in \[1, 100\]; got 101"),
        # a negative PSD gave NaN dB; a string leaked JAX's own type error
        (lambda: vibration_reduction_db(np.arange(10.0), -np.ones(10), np.ones(10), [4.0]), r"psd_open must be a power spectral density, >= 0 \(units\^2/Hz\); got a minimum of -1"),
        (lambda: vibration_reduction_db(np.arange(10.0), np.ones(10), "abc", [4.0]), r"psd_closed must be a real number or an array of real numbers; got 'abc'"),
    ],
)
def test_bad_input_is_refused_by_name(call, match, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=match):
        call()
    assert not (tmp_path / "unused").exists()  # refused before any folder is made


def test_a_diverged_runs_nan_psd_still_gives_nan_decibels():
    """The PSD check refuses negative values only: a diverged run's NaN PSD passes, as NaN dB."""
    reduction = vibration_reduction_db(np.arange(10.0), np.full(10, np.nan), np.ones(10), [4.0])
    assert np.isnan(np.asarray(reduction)).all()


def test_an_empty_batch_of_scenarios_is_refused():
    """x0 of shape (0, 6) reached a reduction with no identity inside the loop."""
    plant = discretize(make_plant(), 1e-3)
    scenario = paper_scenario(plant, 0.01)
    with pytest.raises(ValueError, match=r"scenario.x0 must hold at least one scenario \(B >= 1\); got shape \(0, 6\)"):
        rollout(plant, dfs(), DFSParams(), scenario._replace(x0=np.zeros((0, 6))))
