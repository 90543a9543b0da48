"""``jaxflex.controllers.by_name``: each name and option builds the controller one would build
by hand (same parameters, same torques), bad names are refused with the accepted values, and
the call sites built on it (bench, Monte Carlo, tuned.json) keep their configurations."""

import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex import beam, bench, montecarlo, report
from jaxflex.controllers import DFSParams, OpenLoopParams, by_name, combine, dfs, fuzzy, fuzzy_params, open_loop
from jaxflex.controllers.registry import NAMES
from tests.helpers import tree_allclose

DT = 1e-3


def torques(controller, params, ys):
    """The torques of ``controller`` fed the measurements ``ys`` [T, 2], one step at a time."""
    state = controller.init(params, ys[0])
    out = []
    for y in ys:
        state, u = controller.step(params, state, y)
        out.append(np.asarray(u))
    return np.stack(out)


def measurements(dtype=jnp.float64):
    rng = np.random.default_rng(0)
    return jnp.asarray(rng.uniform(-1.0, 1.0, (12, 2)) * np.array([0.5, 3.0]), dtype)


BY_HAND = {
    "open_loop": ({}, lambda: (open_loop(), OpenLoopParams())),
    "dfs, paper": ({}, lambda: (dfs(DT), DFSParams(55.0, 0.005))),
    "dfs, linear": (
        {"params": {"k": 40.0, "tau_s": 0.0032}, "capacity": 16, "delay": "linear"},
        lambda: (dfs(DT, 16, interpolation="linear"), DFSParams(40.0, 0.0032)),
    ),
    "dfs, cubic": ({"params": {"tau_s": 0.0047}, "delay": "cubic"}, lambda: (dfs(DT, interpolation="cubic"), DFSParams(55.0, 0.0047))),
    "dfs, pade": ({"delay": "pade", "pade_order": 6}, lambda: (dfs(DT, approximation="pade", pade_order=6), DFSParams(55.0, 0.005))),
    "fuzzy, paper": ({}, lambda: (fuzzy(), fuzzy_params(1.02, 0.30, 1.0))),
    "fuzzy, singleton": ({"params": {"k1": 2.0}, "defuzz": "singleton"}, lambda: (fuzzy(defuzz="singleton"), fuzzy_params(2.0, 0.30, 1.0))),
    "fuzzy, smooth": ({"temperature": 0.02}, lambda: (fuzzy(temperature=0.02), fuzzy_params())),
    "dfs+fuzzy": (
        {"params": {"k": 50.0, "k3": 0.5}, "delay": "linear"},
        lambda: (combine(dfs(DT, interpolation="linear"), fuzzy()), (DFSParams(50.0, 0.005), fuzzy_params(1.02, 0.30, 0.5))),
    ),
}


@pytest.mark.parametrize("case", list(BY_HAND))
def test_each_name_is_the_controller_built_by_hand(case):
    options, build = BY_HAND[case]
    name = case.split(",")[0]
    controller, params = by_name(name, dt=DT, **options)
    hand_controller, hand_params = build()
    tree_allclose(params, hand_params, rtol=0)
    controller.check(params)
    ys = measurements()
    expected = torques(hand_controller, hand_params, ys)
    np.testing.assert_array_equal(torques(controller, params, ys), expected)
    if name != "open_loop":
        assert np.any(expected != 0)  # the measurements do excite the controller


def test_dtype_sets_every_parameter_leaf():
    controller, params = by_name("dfs+fuzzy", dt=DT, dtype=jnp.float32)
    assert {leaf.dtype for leaf in jax.tree.leaves(params)} == {jnp.dtype(jnp.float32)}
    hand = (DFSParams(jnp.float32(55.0), jnp.float32(0.005)), fuzzy_params(dtype=jnp.float32))
    ys = measurements(jnp.float32)
    np.testing.assert_array_equal(torques(controller, params, ys), torques(combine(dfs(DT), fuzzy()), hand, ys))
    # An integer dtype truncated the 5 ms delay and k2 to 0, and the check then named them.
    for build in (lambda: by_name("dfs+fuzzy", dt=DT, dtype=jnp.int32), lambda: fuzzy_params(dtype=jnp.int32)):
        with pytest.raises(ValueError, match=re.escape("dtype must be a floating dtype (jnp.float32, jnp.float64); got int32")):
            build()
    with pytest.raises(ValueError, match=re.escape("dtype must be a floating dtype (jnp.float32, jnp.float64); got 'foo'")):
        fuzzy_params(dtype="foo")


@pytest.mark.parametrize("name", ["pid", "DFS", "dfs + fuzzy", "", None])
def test_unknown_names_are_refused_with_the_accepted_ones(name):
    accepted = "('open_loop', 'dfs', 'fuzzy', 'dfs+fuzzy')"
    assert str(NAMES) == accepted
    with pytest.raises(ValueError, match=re.escape(f"name must be one of {accepted}; got {name!r}")):
        by_name(name, dt=DT)


def test_bad_options_are_refused_by_name():
    with pytest.raises(ValueError, match=re.escape("delay must be one of ('nearest', 'linear', 'cubic', 'pade'); got 'sinc'")):
        by_name("dfs", dt=DT, delay="sinc")
    with pytest.raises(ValueError, match=re.escape("params: unknown parameter name(s) ['tau']; accepted: ['k', 'tau_s', 'k1', 'k2', 'k3']")):
        by_name("dfs", dt=DT, params={"tau": 0.004})
    with pytest.raises(ValueError, match=re.escape("params must be a mapping of parameter values by name ({'k': 55.0, 'tau_s': 0.005}); got 'k=5'")):
        by_name("dfs", dt=DT, params="k=5")  # dict("k=5") failed with "dictionary update sequence element"
    with pytest.raises(ValueError, match=re.escape("params['k'] must be a finite number; got 'fast'")):
        by_name("dfs", dt=DT, params={"k": "fast"})
    # a bool or a numeric string is not a gain either (float() would take both), nor a NaN
    for bad in (True, "70", float("nan")):
        with pytest.raises(ValueError, match=re.escape(f"params['k'] must be a finite number; got {bad!r}")):
            by_name("dfs", dt=DT, params={"k": bad})
    assert by_name("dfs", dt=DT, params={"k": np.float32(30.0)})[1] == DFSParams(30.0, 0.005)
    # every option is checked, whether the controller reads it or not (a Pade order of -5
    # passed with the default delay, and a capacity of 0 with the fuzzy controller)
    for name, option, message in (
        ("dfs", {"pade_order": -5}, "pade_order must be an integer in [1, 100]; got -5"),
        ("fuzzy", {"capacity": 0}, "capacity must be an integer in [1, 1000000] (samples); got 0"),
        ("dfs", {"defuzz": "mean"}, "defuzz must be one of ('centroid', 'singleton'); got 'mean'"),
        ("open_loop", {"temperature": -1.0}, "temperature must be 0 (the faithful controller) or a Python float in [1e-05, 1]"),
    ):
        with pytest.raises(ValueError, match=re.escape(message)):
            by_name(name, dt=DT, **option)
    # the configurations refuse them when they are made, by the table's name
    with pytest.raises(ValueError, match=re.escape("params['k'] must be a finite number; got True")):
        montecarlo.MCConfig(params={"k": True})
    from tuning.tuner import TuneConfig

    with pytest.raises(ValueError, match=re.escape("initial['k'] must be a finite number; got '70'")):
        TuneConfig(initial={"k": "70"})


def test_unused_names_are_ignored():
    _, params = by_name("dfs", dt=DT, params={"k": 30.0, "k1": 9.0})
    assert params == DFSParams(30.0, 0.005)


def test_call_sites_keep_their_configurations(tmp_path):
    ys = measurements()
    # jaxflex bench: nearest-sample DFS, "smooth" is the centroid at SMOOTH_TEMPERATURE, params in dtype
    controller, params = bench.controller_and_params("dfs+fuzzy", "smooth", jnp.float64)
    hand = combine(dfs(DT), fuzzy(temperature=bench.SMOOTH_TEMPERATURE)), (DFSParams(jnp.float64(55.0), jnp.float64(0.005)), fuzzy_params())
    np.testing.assert_array_equal(torques(controller, params, ys), torques(*hand, ys))
    # Monte Carlo: linear-interpolated DFS with the run's capacity
    controller, params = montecarlo.controller_and_params("dfs", {"tau_s": 0.0042}, DT, 8)
    np.testing.assert_array_equal(torques(controller, params, ys), torques(dfs(DT, 8, interpolation="linear"), DFSParams(55.0, 0.0042), ys))
    # tuned.json: its config picks the delay and the fuzzy temperature
    path = tmp_path / "tuned.json"
    named = {"k": 45.0, "tau_s": 0.006, "k1": 1.1, "k2": 0.25, "k3": 0.9}
    path.write_text(json.dumps({"controller": "dfs+fuzzy", "params": named, "config": {"delay": "pade", "pade_order": 5, "fuzzy_temperature": 0.03}}))
    tuned = report.load_tuned(path)
    assert (tuned.name, tuned.named) == ("dfs+fuzzy", named)
    assert tuned.options == {"capacity": 64, "delay": "pade", "pade_order": 5, "fuzzy_temperature": 0.03}
    assert tuned.beam == beam.BeamParams() and tuned.dt == DT  # no [beam] or [scenarios]: the paper's arm and dt
    controller, params = tuned.build(DT)
    hand = combine(dfs(DT, approximation="pade", pade_order=5), fuzzy(temperature=0.03)), (DFSParams(45.0, 0.006), fuzzy_params(1.1, 0.25, 0.9))
    np.testing.assert_array_equal(torques(controller, params, ys), torques(*hand, ys))
    # Monte Carlo with a tuned run's options: its runner builds that same controller
    runner = montecarlo._Runner(montecarlo.MCConfig(controller="dfs+fuzzy", params=named, delay="pade", pade_order=5, fuzzy_temperature=0.03))
    np.testing.assert_array_equal(torques(runner.controller, runner.params, ys), torques(*hand, ys))


def test_a_combined_controller_checks_both_parts():
    controller, params = by_name("dfs+fuzzy", dt=1e-3)
    controller.check(params)
    with pytest.raises(ValueError, match="k1"):
        controller.check((params[0], fuzzy_params(k1=-1.0)))
    with pytest.raises(ValueError, match="tau_s"):
        controller.check((DFSParams(55.0, -0.005), params[1]))


def test_capacity_reaches_the_buffer():
    """by_name's capacity is the delay buffer's: 16 samples hold 16 ms at 1 ms, not 17."""
    controller, params = by_name("dfs", dt=1e-3, params={"tau_s": 0.016}, capacity=16)
    controller.check(params)
    with pytest.raises(ValueError, match=r"the delay buffer holds 16 samples"):
        controller.check(DFSParams(55.0, 0.017))


def test_pd_reads_the_angle_and_the_velocity():
    """u = -(kp theta + kd theta_dot), each gain on its own measurement (and the documented
    defaults kp = 1, kd = 0.1)."""
    from jaxflex.controllers import PDParams, pd

    u = pd().step(PDParams(2.0, 0.5), (), jnp.asarray([0.1, 3.0]))[1]
    np.testing.assert_allclose(np.asarray(u), [-(2.0 * 0.1 + 0.5 * 3.0)], rtol=1e-12)
    assert PDParams() == (1.0, 0.1)


def test_default_buffer_holds_64_samples():
    """dfs()'s documented default capacity: 64 ms of delay at 1 ms, and not one sample more."""
    controller, params = by_name("dfs", dt=1e-3, params={"tau_s": 0.064})
    controller.check(params)
    controller, params = by_name("dfs", dt=1e-3, params={"tau_s": 0.065})
    with pytest.raises(ValueError, match="tau_s"):
        controller.check(params)


@pytest.mark.parametrize("k", [True, "55", None])
def test_a_tuned_json_gain_that_is_not_a_number_is_refused(tmp_path, k):
    path = tmp_path / "tuned.json"
    path.write_text(json.dumps({"controller": "dfs", "params": {"k": k, "tau_s": 0.005}}))
    with pytest.raises(ValueError, match=r"lacks numeric parameter\(s\) \['k'\] for dfs"):
        report.load_tuned(path)
