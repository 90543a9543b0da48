"""Bad input to public entry points, found by a walkthrough that tried about 480 cases: each
of these leaked a TypeError or IndexError from deep inside, took a bad value silently, or
named a narrower range than the one checked. Each is now a ValueError naming the parameter."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.analysis import vibration_reduction_db
from jaxflex.analysis.metrics import run_diverged
from jaxflex.analysis.psd import band_mask, band_peak
from jaxflex.analysis.stability import delta, pade_loop_matrix, rightmost_real_grid, spectral_radius, unstable_root_count
from jaxflex.beam import BeamParams, exact_natural_frequencies_hz, modal_matrices
from jaxflex.controllers import DFSParams, by_name, combine, dfs, fuzzy
from jaxflex.controllers.base import Controller
from jaxflex.controllers.fuzzy import FuzzyParams, fuzzy_params, fuzzy_surface
from jaxflex.montecarlo import MCConfig, run_montecarlo
from jaxflex.plant import discretize, make_plant
from jaxflex.rollout import rollout
from jaxflex.scenarios import ScenarioSpec, batch_plant, paper_scenario, sample_scenarios
from jaxflex.montecarlo import metric_names, recorded_settings, summarize
from tuning.calibrate import calibrate, to_toml
from tuning.identify import identify_modes, read_record
from tuning.run import run_tune
from tuning.transforms import tuned_controller
from tuning.tuner import TuneConfig, tune


def _sampled_plant():
    return discretize(make_plant(), 1e-3)


def _float32(call):
    with jax.enable_x64(False):
        return call()


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
        # a second walkthrough: TypeErrors, KeyErrors and AttributeErrors from deep inside, and
        # resume="no" read as true
        (lambda: recorded_settings(None), r"out_dir must be a folder's path \(a non-empty str or os.PathLike\); got None"),
        (lambda: read_record(None), r"path must be a file's path \(a non-empty str or os.PathLike\); got None"),
        (lambda: metric_names("2"), r"n_modes must be an integer in \[1, 100\]; got '2'"),
        (lambda: summarize("x", {}), r"config must be a MCConfig \(build one with MCConfig\(\.\.\.\)\); got str"),
        (lambda: summarize(MCConfig(n_modes=1), {"diverged": [False]}), r"columns must map each of \[.*'reduction_db_mode1'.*\] to its values, one per run; missing \['control_effort', "),
        (lambda: to_toml("junk"), r"calibration must be a Calibration \(the result of calibrate\(\.\.\.\)\); got str"),
        (lambda: to_toml(calibrate([13.0], BeamParams()), dt="x"), r"dt must be a real number; got 'x'"),
        (lambda: tune(TuneConfig(), "unused", resume="no"), r"resume must be True or False; got 'no'"),
        (lambda: run_tune(TuneConfig(), "unused", progress=None), r"progress must be True or False; got None"),
        (lambda: run_montecarlo(MCConfig(), "unused", figures=1), r"figures must be True or False; got 1"),
        # 10^6 samples of history aborted the process; 1 sample of buffer divided by zero
        (lambda: spectral_radius(_sampled_plant(), 55.0, 10**6), r"delay_steps must be an integer in \[1, 2048\] \(samples\); got 1000000$"),
        (lambda: spectral_radius(_sampled_plant(), 55.0, 3, n_hist=10**6), r"n_hist must be an integer in \[1, 2048\] \(samples\); got 1000000"),
        (lambda: tuned_controller("dfs", capacity=1), r"capacity must be an integer in \[2, 2048\] \(samples\); got 1"),
        (lambda: TuneConfig(capacity=4096), r"capacity must be an integer in \[2, 2048\] \(samples\); got 4096"),
        # a batch of plants failed deep in NumPy; a bool s was read as 1 + 0j
        (lambda: spectral_radius(jax.tree.map(lambda a: jnp.stack([a, a]), _sampled_plant()), 55.0, 5), r"plant must be one plant \(a state matrix of shape \(n, n\)\); got a batch, of shape \(2, 6, 6\)"),
        (lambda: delta(make_plant(), 55.0, 0.005, True), r"s must be a complex number or an array of them \(concrete: delta is NumPy\); got True"),
        (lambda: pade_loop_matrix(_sampled_plant(), 55.0, "x", 4), r"tau_s must be a real number; got 'x'"),
        (lambda: unstable_root_count("junk", 0.01), r"result must be a CriticalDelays \(the result of critical_delays\(\.\.\.\)\); got str"),
        # inf entries returned for an arm 1e-30 m thick in float32, 0 stiffness at 1e-120 m in
        # float64; a ZeroDivisionError at 1e-200 m long
        (lambda: _float32(lambda: modal_matrices(BeamParams(thickness_m=1e-30))), r"the 2-mode model's matrices must be finite, with each flexible mode's stiffness > 0, in float32; got inf, NaN or 0"),
        (lambda: modal_matrices(BeamParams(thickness_m=1e-120)), r"the 2-mode model's matrices must be finite, with each flexible mode's stiffness > 0, in float64; got inf, NaN or 0 for BeamParams\("),
        # the same 0 stiffness with the damping given, so that no 0 / 0 frequency makes a NaN first
        (lambda: modal_matrices(BeamParams(thickness_m=1e-110, rayleigh_alpha=0.0, rayleigh_beta=0.0)), r"the 2-mode model's matrices must be finite, with each flexible mode's stiffness > 0, in float64; got inf, NaN or 0"),
        (lambda: exact_natural_frequencies_hz(BeamParams(length_m=1e-200)), r"params: the arm's frequency equation must be finite in float64"),
        # JAX's TypeError on a string; argmax of an empty sequence
        (lambda: band_mask("abc", 10.0), r"freqs must be a real number or an array of real numbers; got 'abc'"),
        (lambda: band_peak([], [], 10.0), r"freqs must be a non-empty 1-D array, one value per frequency bin; got shape \(0,\)"),
        (lambda: run_diverged("x", 1.0, 0.9), r"blew_up must be a bool or an array of bools \(RunMetrics.diverged\); got 'x'"),
        (lambda: run_diverged(False, "x", 0.9), r"peak_tip_m must be a real number or an array of real numbers; got 'x'"),
        # a batch of keys; a horizon of 10^12 samples ran out of memory with nothing named
        (lambda: sample_scenarios(ScenarioSpec(horizon_s=0.01), jax.random.split(jax.random.key(0), 3), 3), r"key must be one PRNG key \(shape \(\)\); got a batch of shape \(3,\)"),
        (lambda: ScenarioSpec(dt=1e-9), r"horizon_s / dt must be at most 10,000,000 samples .*; got 1 s at dt = 1e-09 s, 1,000,000,000 samples$"),
        (lambda: paper_scenario(_sampled_plant(), 1e9), r"horizon_s / dt must be at most 10,000,000 samples"),
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


def _plant_and_scenario():
    plant = discretize(make_plant(), 1e-3)
    return plant, paper_scenario(plant, 0.01)


@pytest.mark.parametrize(
    "call, match",
    [
        # a DFSParams, a NamedTuple of two fields, passed for the pair: 'params must be a DFSParams; got float 55.0'
        (lambda: rollout(*_plant_and_scenario()[:1], combine(dfs(), fuzzy()), DFSParams(), _plant_and_scenario()[1]),
         r"params of a combined controller must be a pair \(first's params, second's params\), as \(DFSParams\(\.\.\.\), fuzzy_params\(\)\) for combine\(dfs\(\), fuzzy\(\)\); got DFSParams"),
        # tuple centres passed check() and failed in jnp.result_type with a TypeError
        (lambda: rollout(*_plant_and_scenario()[:1], fuzzy(), FuzzyParams(1.0, 0.3, 1.0, (-1.0, -0.5, 0.0, 0.5, 1.0), *(jnp.linspace(-1.0, 1.0, 5),) * 2), _plant_and_scenario()[1]),
         r"angle_centres must be an array \(jnp.asarray\(\.\.\.\), or build the parameters with fuzzy_params\(centres=\.\.\.\)\); got tuple"),
        # JAX's own TypeError on a string
        (lambda: fuzzy_surface(fuzzy_params(), "a", 0.1), r"^e must be a real number; got 'a'$"),
        # scalars: TypeError 'float' object is not iterable
        (lambda: rightmost_real_grid(make_plant(), 55.0, 0.005), r"k_values and tau_s must be non-empty 1-D arrays \(the grid's axes\); got shapes \(\), \(\)"),
        # a traced option: 'must be a finite number > 0; got JitTracer'
        (lambda: jax.jit(lambda h: ScenarioSpec(horizon_s=h))(1.0), r"horizon_s must be a concrete number, not traced under jit, vmap or grad"),
    ],
)
def test_bad_input_found_by_a_python_walkthrough_is_refused_by_name(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_options_accept_concrete_zero_d_arrays_as_the_numbers_they_hold():
    """A BeamParams of jnp scalars (as built for grad) was refused by TuneConfig as 'must be a
    finite number > 0; got Array(0.6)'; a float32 reads as the decimal it prints as."""
    config = TuneConfig(beam=BeamParams(length_m=jnp.asarray(0.6), hub_inertia_kg_m2=np.float32(2e-3)), n_modes=jnp.asarray(3))
    assert (config.beam.length_m, config.beam.hub_inertia_kg_m2, config.n_modes) == (0.6, 0.002, 3)
    assert type(config.n_modes) is int
    assert ScenarioSpec(horizon_s=np.array(0.5)).horizon_s == 0.5
    with pytest.raises(ValueError, match=r"n_modes must be an integer in \[1, 100\]; got True"):
        TuneConfig(n_modes=np.bool_(True))  # a bool array stays a bool
    with pytest.raises(ValueError, match=r"horizon_s must be a finite number > 0; got array\(\[0.5\]\)"):
        ScenarioSpec(horizon_s=np.array([0.5]))  # one number, not an array of them


def _float32_plant_and_scenario():
    with jax.enable_x64(False):  # the suite runs with x64 on
        return _plant_and_scenario()


def test_a_numpy_float64_gain_runs_in_float32_without_x64():
    """Without x64 JAX reads a NumPy float64 as float32; a gain from np.linspace was refused as
    'wider than the plant's float32'. Under x64 it would widen the loop, and stays refused."""
    plant, scenario = _float32_plant_and_scenario()
    k = np.linspace(10.0, 100.0, 5)[2]
    with jax.enable_x64(False):
        np.testing.assert_array_equal(rollout(plant, dfs(), DFSParams(k, 0.005), scenario).u, rollout(plant, dfs(), DFSParams(float(k), 0.005), scenario).u)
    with pytest.raises(ValueError, match=r"params.k is float64, wider than the plant's float32"):
        rollout(plant, dfs(), DFSParams(k, 0.005), scenario)


def test_a_controllers_torque_in_another_dtype_is_refused_by_name():
    """lax.scan refused the carry with a message that named no controller."""
    plant, scenario = _float32_plant_and_scenario()
    wide = Controller(lambda p, y: (), lambda p, s, y: (s, (-p * y[:1]).astype(jnp.float64)), lambda p: None)
    with pytest.raises(ValueError, match=r"the controller's step returns the torque u in float64, wider than the plant's float32: build its constants"):
        rollout(plant, wide, 1.0, scenario)
    # a narrower torque, or a weakly typed one, ran before the check and still does
    narrow = Controller(lambda p, y: (), lambda p, s, y: (s, (-p * y[:1]).astype(jnp.bfloat16)), lambda p: None)
    weak = Controller(lambda p, y: (), lambda p, s, y: (s, jax.lax.full((1,), 0.0)), lambda p: None)
    assert rollout(plant, narrow, 1.0, scenario).x.dtype == jnp.float32
    assert rollout(plant, weak, 1.0, scenario).x.dtype == jnp.float32
    assert rollout(discretize(make_plant(), 1e-3), narrow, 1.0, paper_scenario(discretize(make_plant(), 1e-3), 0.01)).x.dtype == jnp.float64


def test_paper_scenario_of_a_batch_of_plants():
    """A batch of plants (batch_plant) failed in float(plant.dt); its scenario is the paper's
    x0 for each, with the force and noise shared, and runs as the plants one by one."""
    nominal = discretize(make_plant(), 1e-3)
    spec = ScenarioSpec(horizon_s=0.05, youngs_modulus_rel=0.1)
    batch = sample_scenarios(spec, jax.random.key(1), 3)
    plants = batch_plant(BeamParams(), 2, 1e-3, "zoh", batch, nominal)
    scenario = paper_scenario(plants, 0.05)
    assert scenario.x0.shape == (3, 6) and scenario.force.shape == (50, 1)
    together = rollout(plants, dfs(), DFSParams(), scenario)
    for i in range(3):
        one = jax.tree.map(lambda a: a[i], plants)
        np.testing.assert_allclose(together.x[i], rollout(one, dfs(), DFSParams(), paper_scenario(one, 0.05)).x, rtol=1e-5, atol=1e-12)
    with pytest.raises(ValueError, match=r"the batch of plants has sample times from 0.001 to 0.002 s; they must share one dt"):
        paper_scenario(plants._replace(dt=jnp.asarray([1e-3, 2e-3, 1e-3])))
    for dt in (jnp.asarray(np.nan), jnp.asarray([1e-3, np.nan, 1e-3])):  # a NaN dt is named as such, not as a batch's spread
        with pytest.raises(ValueError, match=r"^dt must be a finite number of seconds > 0; got nan$"):
            paper_scenario(nominal._replace(dt=dt))
    with pytest.raises(ValueError, match=r"plant must hold at least one plant; got an empty batch"):
        paper_scenario(jax.tree.map(lambda a: a[:0], plants))


def test_a_batch_with_plant_uncertainty_on_one_shared_plant_is_refused():
    """A hand-written Monte Carlo, rollout(nominal, ..., sampled batch), ran every scenario on
    the nominal plant and dropped the drawn moduli, densities and payloads silently."""
    nominal = discretize(make_plant(), 1e-3)
    batch = sample_scenarios(ScenarioSpec(horizon_s=0.01, youngs_modulus_rel=0.1), jax.random.key(0), 2)
    with pytest.raises(ValueError, match=r"scenario.plant holds each scenario's plant uncertainty, which rollout does not apply to one plant shared by the batch: pass batch_plant\("):
        rollout(nominal, dfs(), DFSParams(), batch)
    plants = batch_plant(BeamParams(), 2, 1e-3, "rk4", batch, nominal)
    assert rollout(plants, dfs(), DFSParams(), batch).x.shape == (2, 10, 6)
    assert rollout(nominal, dfs(), DFSParams(), batch._replace(plant=None)).x.shape == (2, 10, 6)


def test_bounds_are_inclusive_or_strict_as_their_messages_say():
    """'in [low, high]' takes both ends; '> 0' refuses 0 and '>= 0' takes it; a NumPy bool
    (as read from an array) is a flag; dt = 0 is not '> 0'."""
    from jaxflex import checks
    from jaxflex.heartbeat import Heartbeat

    assert checks.integer("n", 5, 1, high=5) == 5
    with pytest.raises(ValueError, match=r"n must be an integer in \[1, 5\]; got 6"):
        checks.integer("n", 6, 1, high=5)
    Heartbeat("x", "steps", 5, done=5)  # done = total: a resume of a finished run
    with pytest.raises(ValueError, match=r"every_s must be a finite number of seconds > 0; got 0.0"):
        Heartbeat("x", "steps", 5, every_s=0.0)
    assert checks.number("x", 0.0) == 0.0
    assert checks.flag("resume", np.bool_(True)) is True and checks.flag("resume", np.array([False])[0]) is False
    with pytest.raises(ValueError, match=r"dt must be finite and > 0; got 0.0"):
        by_name("fuzzy", dt=0.0)


def test_a_sum_of_controllers_is_batched_only_when_both_parts_are():
    """An unbatched part given a [n_y, B] measurement would run wrongly: the sum maps it."""
    plain = Controller(lambda p, y0: (), lambda p, s, y: (s, jnp.zeros((1,), y.dtype)), lambda p: None)
    assert plain.batched is False and dfs().batched is True
    assert combine(dfs(), plain).batched is False and combine(plain, dfs()).batched is False
    assert combine(dfs(), dfs()).batched is True


def test_a_check_that_fails_on_concrete_parameters_is_reported_not_skipped():
    """check_params skips a controller's check only when a parameter is traced; JAX's type
    error from a check on concrete parameters (here a Python `if` inside its own jit) is a
    broken check, and reaches the caller."""
    from jaxflex.controllers.base import check_params

    def check(params):
        jax.jit(lambda v: 1 if v > 0 else 0)(params)

    ctrl = Controller(lambda p, y0: (), lambda p, s, y: (s, jnp.zeros((1,), y.dtype)), check)
    with pytest.raises(jax.errors.JAXTypeError):
        check_params(ctrl, jnp.float32(1.0))
    jax.jit(lambda p: check_params(ctrl, p))(jnp.float32(1.0))  # traced: skipped
