"""What sample_scenarios draws, against the closed form of each distribution of ScenarioSpec
(large batches; the tolerances are a few standard errors)."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.beam import BeamParams
from jaxflex.montecarlo import MCConfig
from jaxflex.plant import check_rk4_step, discretize, make_plant
from jaxflex.scenarios import PlantPerturbation, ScenarioSpec, _paper_x0, batch_plant, check_plants, initial_condition, pad_batch, perturbed_params, sample_scenarios
from tuning.tuner import TuneConfig

N = 4000
REL = 4 / np.sqrt(N)  # a few relative standard errors of a mean or a standard deviation
SPEC = ScenarioSpec(
    horizon_s=0.2, q0_std_m=2e-3, qdot0_std_m_s=3e-5, theta0_std_rad=0.01, impulse_max_n=0.4, impulse_duration_s=0.007,
    step_max_n=0.2, noise_angle_rad=1e-4, noise_velocity_rad_s=5e-3, youngs_modulus_rel=0.1, density_rel=0.05,
    hub_inertia_rel=0.2, payload_max_kg=0.03, include_paper=False,
)


def draw(spec):
    return jax.tree.map(np.asarray, sample_scenarios(spec, jax.random.key(1), N, n_modes=2, dtype=np.float64))


def test_initial_state_noise_and_plant_follow_their_distributions():
    sc = draw(SPEC)
    # initial state [theta, q1, q2, theta_dot, q1_dot, q2_dot]
    np.testing.assert_allclose(sc.x0.std(axis=0), [0.01, 2e-3, 2e-3, 0.0, 3e-5, 3e-5], rtol=REL)
    # measurement noise: the angle column and the velocity column each with its own std
    np.testing.assert_allclose(sc.noise.reshape(-1, 2).std(axis=0), [1e-4, 5e-3], rtol=0.01)
    # white: a new draw at every sample (one draw held for a whole scenario has the same
    # standard deviation over the batch, and a lag-1 correlation of 1); 4000 x 199 pairs
    for column in range(2):
        assert abs(np.corrcoef(sc.noise[:, :-1, column].ravel(), sc.noise[:, 1:, column].ravel())[0, 1]) < 0.01
    # the plant: independent uniform scales, and a payload in [0, max] with mean max / 2
    p = sc.plant
    for scale, half_width in ((p.youngs_modulus_scale, 0.1), (p.density_scale, 0.05), (p.hub_inertia_scale, 0.2)):
        assert np.all(np.abs(scale - 1) <= half_width) and np.std(scale) == pytest.approx(half_width / np.sqrt(3), rel=REL)
    assert abs(np.corrcoef(p.youngs_modulus_scale, p.density_scale)[0, 1]) < 0.1
    assert p.payload_mass_kg.min() >= 0 and p.payload_mass_kg.max() <= 0.03
    assert p.payload_mass_kg.mean() == pytest.approx(0.015, rel=REL)


def test_pulse_and_step_follow_their_distributions():
    """The same key draws the same start times with the pulse or the step alone."""
    pulse = draw(dataclasses.replace(SPEC, step_max_n=0.0)).force[:, :, 0]
    step = draw(dataclasses.replace(SPEC, impulse_max_n=0.0)).force[:, :, 0]
    on = np.abs(pulse) > 0
    lengths = on.sum(axis=1)
    assert np.all(np.abs(lengths - 7) <= 1) and np.mean(lengths == 7) > 0.5  # 7 ms at 1 ms, up to the rounding of the start
    amplitude = np.abs(pulse).max(axis=1)
    assert amplitude.max() <= 0.4 and amplitude.mean() == pytest.approx(0.2, rel=2 * REL)
    level = step[:, -1]
    assert np.all(np.abs(step - level[:, None]) * (np.abs(step) > 0) == 0)  # on once, at one level
    assert np.abs(level).max() <= 0.2 and np.abs(level).mean() == pytest.approx(0.1, rel=2 * REL)
    pulse_start, step_start = np.argmax(on, axis=1), np.argmax(np.abs(step) > 0, axis=1)
    # a start uniform in [0, 0.1 s) switches the force on at the first sample at or after it,
    # k = ceil(start / dt) (sample k is at t = k dt): uniform on 1 .. 100, mean 50.5
    for start in (pulse_start, step_start):
        assert start.min() == 1 and start.max() == 100
        assert abs(start.mean() - 50.5) < 4 * np.sqrt((100**2 - 1) / 12 / N)
    assert abs(np.corrcoef(pulse_start, step_start)[0, 1]) < 0.1  # drawn apart


def test_the_papers_scenario_is_member_zero():
    spec = dataclasses.replace(SPEC, include_paper=True)
    sc = jax.tree.map(np.asarray, sample_scenarios(spec, jax.random.key(0), 8, dtype=np.float64))
    np.testing.assert_array_equal(sc.x0[0], _paper_x0(2))
    assert not sc.force[0].any() and not sc.noise[0].any()
    plant0 = [float(leaf[0]) for leaf in sc.plant]
    assert plant0 == [1.0, 1.0, 1.0, 0.0]
    assert sc.force[1:].any()
    assert sc.noise[1:].any()


def test_a_payload_alone_perturbs_the_plant_and_adds_to_the_nominal_one():
    from jaxflex.beam import BeamParams
    from jaxflex.scenarios import PlantPerturbation, perturbed_params

    spec = ScenarioSpec(horizon_s=0.01, payload_max_kg=0.03, include_paper=False)
    p = sample_scenarios(spec, jax.random.key(2), 64, n_modes=2, dtype=np.float64).plant
    assert p is not None and 0 < float(p.payload_mass_kg.min()) and float(p.payload_mass_kg.max()) <= 0.03
    np.testing.assert_array_equal(np.asarray(p.youngs_modulus_scale), 1.0)
    loaded = perturbed_params(BeamParams(payload_mass_kg=0.1), PlantPerturbation(1.0, 1.0, 1.0, 0.02))
    assert loaded.payload_mass_kg == pytest.approx(0.12, rel=1e-15) and loaded.hub_inertia_kg_m2 == BeamParams().hub_inertia_kg_m2


@pytest.mark.parametrize(
    "name, value", [(name, value) for name in ("horizon_s", "dt") for value in ("3", True, float("nan"), 0.0)] + [("horizon_s", None)]
)
def test_paper_scenario_refuses_a_horizon_or_dt_that_is_not_a_number(name, value):
    """horizon_s = "3" ran 3 s (float("3")) and True ran 1 s: both were taken as numbers."""
    from jaxflex import make_plant
    from jaxflex.scenarios import paper_scenario

    with pytest.raises(ValueError, match=rf"{name} must be a finite number of seconds > 0; got {value!r}"):
        paper_scenario(make_plant(), **{name: value})


@pytest.mark.parametrize("horizon_s, steps", [(1.004, 100), (1.006, 101), (0.006, 1), (3.0, 300)])
def test_the_horizon_is_rounded_to_the_nearest_whole_sample(horizon_s, steps):
    """The documented rounding at dt = 0.01 s: the scenario and the spec both run ``steps`` samples."""
    from jaxflex import make_plant
    from jaxflex.scenarios import paper_scenario

    assert ScenarioSpec(horizon_s=horizon_s, dt=0.01).steps == steps
    assert paper_scenario(make_plant(), horizon_s=horizon_s, dt=0.01).force.shape[0] == steps


def test_a_horizon_of_exactly_max_steps_samples_is_accepted():
    """'at most MAX_STEPS samples': MAX_STEPS itself runs, one more is refused, and the
    refusal gives the count in full (as 1e+07 it read the same as the limit)."""
    from jaxflex.scenarios import MAX_STEPS, horizon_steps

    assert MAX_STEPS == 10**7 and horizon_steps(1e4, 1e-3) == MAX_STEPS
    with pytest.raises(ValueError, match=r"horizon_s / dt must be at most 10,000,000 samples .*; got 10000 s at dt = 0.001 s, 10,000,001 samples$"):
        horizon_steps(10000.001, 1e-3)


def test_a_horizon_under_half_a_sample_is_refused():
    """0.004 s at 10 ms rounds to no sample at all (0.006 s rounds to one, above); each entry
    point that takes a horizon says so."""
    from jaxflex import make_plant
    from jaxflex.scenarios import horizon_steps, paper_scenario

    with pytest.raises(ValueError, match=r"horizon_s must cover at least one sample of dt = 0.01; got 0.004"):
        ScenarioSpec(horizon_s=0.004, dt=0.01)
    with pytest.raises(ValueError, match=r"horizon_s must cover at least one sample of dt = 0.01; got 0.004"):
        horizon_steps(0.004, 0.01)
    with pytest.raises(ValueError, match=r"horizon_s must cover at least one sample of dt = 0.01; got 0.004"):
        paper_scenario(make_plant(), horizon_s=0.004, dt=0.01)


def test_paper_scenario_of_a_traced_plant_needs_its_dt():
    """Under jit a sampled plant's dt is traced: the scenario took 1 ms for it, so a 2 ms
    plant ran twice the horizon asked for. It is refused unless dt is given, and then used."""
    from jaxflex import discretize, make_plant, rollout
    from jaxflex.controllers import OpenLoopParams, open_loop
    from jaxflex.scenarios import paper_scenario

    plant = discretize(make_plant(), 2e-3)
    assert paper_scenario(plant, 1.0).force.shape == (500, 1)
    with pytest.raises(ValueError, match=r"the sampled plant's dt is traced .* pass dt="):
        jax.jit(lambda P: paper_scenario(P, 1.0).force)(plant)
    end = jax.jit(lambda P: rollout(P, open_loop(), OpenLoopParams(), paper_scenario(P, 1.0, dt=2e-3)).t[-1])(plant)
    assert float(end) == pytest.approx(0.998)


def test_an_impulse_that_outlasts_the_horizon_is_refused():
    """A pulse starts in the first half of the horizon: one longer than horizon_s / 2 was cut off
    at the end of the horizon (a 0.2 s pulse over 0.05 s lasted 26-44 samples, not 200)."""
    with pytest.raises(ValueError, match=r"impulse_duration_s must be <= horizon_s / 2 = 0.025 s when impulses are on .*; got 0.2"):
        ScenarioSpec(horizon_s=0.05, impulse_max_n=1.0, impulse_duration_s=0.2)
    with pytest.raises(ValueError, match=r"impulse_duration_s must be <= horizon_s / 2 = 0.025 s .*; got 0.03"):
        ScenarioSpec(horizon_s=0.05, impulse_max_n=1.0, impulse_duration_s=0.03)  # within the horizon, past its half
    ScenarioSpec(horizon_s=0.05, impulse_duration_s=0.2)  # impulses off: the duration is unused
    spec = ScenarioSpec(horizon_s=0.05, impulse_max_n=1.0, impulse_duration_s=0.025, include_paper=False)
    force = np.asarray(sample_scenarios(spec, jax.random.key(0), 64).force[:, :, 0])
    assert np.all(np.sum(force != 0, axis=1) == 25)  # every pulse whole


RK4_SPEC = ScenarioSpec(horizon_s=1.0, dt=0.012, youngs_modulus_rel=0.5)  # nominal fastest mode: omega dt = 2.75, E x1.5: 3.37


def test_configs_refuse_scenarios_whose_stiffest_arm_rk4_grows():
    """The nominal arm passes RK4's check at dt = 12 ms, the arm with E x1.5 does not. Before
    the corners were checked, a Monte Carlo with k = 0 (the open loop) counted 31 % of its
    scenarios as diverged under RK4 and none under ZOH."""
    check_rk4_step(make_plant(), RK4_SPEC.dt)
    with pytest.raises(ValueError, match="method = 'rk4' with dt = 0.012 s is unstable"):
        check_rk4_step(make_plant(BeamParams(youngs_modulus_pa=1.5 * BeamParams().youngs_modulus_pa)), RK4_SPEC.dt)
    match = r"the scenarios' plant uncertainty reaches an arm \(E x1.5, rho x1, I_H x1, payload \+0 kg\) that cannot be run: method = 'rk4' with dt = 0.012 s .* omega dt = 3.37"
    with pytest.raises(ValueError, match=match):
        check_plants(RK4_SPEC, BeamParams(), 2, "rk4")
    with pytest.raises(ValueError, match=match):
        MCConfig(controller="dfs", scenarios=RK4_SPEC, method="rk4")
    with pytest.raises(ValueError, match=match):
        TuneConfig(controller="dfs", scenarios=RK4_SPEC, method="rk4")
    check_plants(RK4_SPEC, BeamParams(), 2, "zoh")
    check_plants(dataclasses.replace(RK4_SPEC, youngs_modulus_rel=0.03), BeamParams(), 2, "rk4")  # omega dt = 2.79
    with pytest.raises(ValueError, match=r"\(E x1, rho x0.7, I_H x1, payload \+0 kg\)"):
        check_plants(dataclasses.replace(RK4_SPEC, youngs_modulus_rel=0.0, density_rel=0.3), BeamParams(), 2, "rk4")


def test_check_plants_refuses_what_is_not_a_spec_or_a_method():
    with pytest.raises(ValueError, match=r"spec must be a ScenarioSpec \(build one with ScenarioSpec\(...\)\); got dict"):
        check_plants({"dt": 1e-3}, BeamParams(), 2, "rk4")
    with pytest.raises(ValueError, match=r"method must be one of \('rk4', 'zoh'\); got 'euler'"):
        check_plants(RK4_SPEC, BeamParams(), 2, "euler")


def test_an_overflow_at_a_corner_is_refused():
    """Under vmap the drawn arms are traced, so make_plant cannot check them; their corners are
    checked in the run's dtype (float64 here, as float32 in a default run)."""
    big = BeamParams(youngs_modulus_pa=1.5e308)  # x1.5 is above float64's 1.8e308
    MCConfig(controller="dfs", method="zoh", beam=big)
    with pytest.raises(ValueError, match=r"\(E x1.5, .*youngs_modulus_pa must be finite; got inf"):
        MCConfig(controller="dfs", method="zoh", beam=big, scenarios=ScenarioSpec(youngs_modulus_rel=0.5))
    # the heaviest payload is a corner too: 1e30 kg makes a plant that is not finite
    with pytest.raises(ValueError, match=r"payload \+1e\+30 kg"):
        check_plants(ScenarioSpec(payload_max_kg=1e30), BeamParams(), 2, "zoh")


def test_the_fastest_mode_of_any_drawn_arm_is_at_a_corner():
    """What check_plants relies on: no arm inside the uncertainty box has a faster mode than
    the box's corners (E x[0.6, 1.4], rho x[0.7, 1.3], I_H x[0.5, 1.5], payload [0, 0.2] kg)."""
    box = np.array([(0.6, 1.4), (0.7, 1.3), (0.5, 1.5), (0.0, 0.2)])

    def fastest(scales):
        arm = perturbed_params(BeamParams(), PlantPerturbation(*map(np.float64, scales)))
        return np.max(np.abs(np.linalg.eigvals(np.asarray(make_plant(arm).A))))

    corners = max(fastest(c) for c in itertools.product(*box))
    inside = [fastest(s) for s in np.random.default_rng(0).uniform(box[:, 0], box[:, 1], (64, 4))]
    assert max(inside) < corners
    assert max(inside) > 0.8 * corners  # the draws reach near it, so the bound is not vacuous


def test_sample_scenarios_and_initial_condition_name_bad_inputs():
    """A dict for the spec failed with an AttributeError, an int for the key with JAX's
    'invalid PRNG key data' TypeError, an integer dtype with a message about jax.random.normal;
    initial_condition took a string into JAX's TypeError and integers into an int32 scenario
    that rollout then refused for its dtype."""
    spec = ScenarioSpec(horizon_s=0.01)
    with pytest.raises(ValueError, match=r"spec must be a ScenarioSpec \(build one with ScenarioSpec\(...\).*; got dict"):
        sample_scenarios({"horizon_s": 0.01}, jax.random.key(0), 2)
    for key in (0, np.uint32(3), jnp.zeros(3, jnp.uint32)):
        with pytest.raises(ValueError, match=r"key must be a JAX PRNG key \(jax.random.key\(seed\)\)"):
            sample_scenarios(spec, key, 2)
    # a batch of keys of either kind: the legacy one was refused as no key at all
    for keys in (jax.random.split(jax.random.key(0), 3), jax.random.split(jax.random.PRNGKey(0), 3)):
        with pytest.raises(ValueError, match=r"key must be one PRNG key \(shape \(\)\); got a batch of shape \(3,\): n draws the 2 scenarios from one key"):
            sample_scenarios(spec, keys, 2)
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype \(jnp.float32, jnp.float64\); got int32"):
        sample_scenarios(spec, jax.random.key(0), 2, dtype=jnp.int32)
    # both kinds of key draw the same scenarios
    new, legacy = sample_scenarios(spec, jax.random.key(1), 3), sample_scenarios(spec, jax.random.PRNGKey(1), 3)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(legacy)))
    with pytest.raises(ValueError, match=r"x0 must be a real number or an array of real numbers; got 'abc'"):
        initial_condition("abc", 10)
    with pytest.raises(ValueError, match=r"x0 must be finite; got \[nan, 0.0"):
        initial_condition([float("nan")] + [0.0] * 5, 10)  # refused only later, by rollout
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype \(jnp.float32, jnp.float64\); got int32"):
        initial_condition([0.0] * 6, 10, dtype=jnp.int32)
    for x0 in (np.zeros((2, 6)), 0.0):  # one state: a batch of them or a number is refused
        with pytest.raises(ValueError, match=r"x0 must have shape \(n_x,\)"):
            initial_condition(x0, 10)
    sc = initial_condition([0, 1, 0, 0, 0, 0], 10)
    assert sc.x0.dtype == jnp.zeros(()).dtype and sc.x0.tolist() == [0, 1, 0, 0, 0, 0]
    assert initial_condition(np.zeros(6, np.float32), 10).x0.dtype == jnp.float32  # a float x0 keeps its dtype


def test_scenario_plant_and_modes_are_those_of_the_drawn_arm_and_refuse_a_non_scenario():
    """``scenario_plant`` and ``scenario_modes_hz`` build the arm a scenario's perturbation
    draws (the nominal one without), and name a non-Scenario instead of an AttributeError."""
    from jaxflex.beam import natural_frequencies_hz
    from jaxflex.plant import discretize
    from jaxflex.scenarios import scenario_modes_hz, scenario_plant

    arm = BeamParams()
    batch = sample_scenarios(ScenarioSpec(youngs_modulus_rel=0.3, payload_max_kg=0.1, include_paper=False), jax.random.key(3), 2)
    one = jax.tree.map(lambda a: a[1], batch)
    drawn = arm._replace(youngs_modulus_pa=arm.youngs_modulus_pa * float(one.plant.youngs_modulus_scale), density_kg_m3=arm.density_kg_m3 * float(one.plant.density_scale),
                         hub_inertia_kg_m2=arm.hub_inertia_kg_m2 * float(one.plant.hub_inertia_scale), payload_mass_kg=arm.payload_mass_kg + float(one.plant.payload_mass_kg))
    np.testing.assert_allclose(scenario_modes_hz(arm, 2, one), natural_frequencies_hz(drawn, 2), rtol=1e-6)
    np.testing.assert_allclose(scenario_plant(arm, 2, 1e-3, "zoh", one).Ad, discretize(make_plant(drawn, 2), 1e-3, "zoh").Ad, rtol=1e-6, atol=1e-9)
    assert not np.allclose(scenario_modes_hz(arm, 2, one), natural_frequencies_hz(arm, 2), rtol=1e-3)
    # a batch in one rollout: the nominal plant itself without uncertainty, else each member's own
    from jaxflex.scenarios import batch_modes_hz, batch_plant

    nominal = discretize(make_plant(arm, 2), 1e-3, "zoh")
    assert batch_plant(arm, 2, 1e-3, "zoh", batch._replace(plant=None), nominal) is nominal
    plants = batch_plant(arm, 2, 1e-3, "zoh", batch, nominal)
    for i in range(2):
        member = jax.tree.map(lambda a, i=i: a[i], batch)
        np.testing.assert_allclose(plants.Ad[i], discretize(make_plant(perturbed_params(arm, member.plant), 2), 1e-3, "zoh").Ad, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(batch_modes_hz(arm, 2, batch)[i], natural_frequencies_hz(perturbed_params(arm, member.plant), 2), rtol=1e-6)
    np.testing.assert_allclose(batch_modes_hz(arm, 2, batch._replace(plant=None)), natural_frequencies_hz(arm, 2), rtol=1e-12)
    for bad in (None, {"plant": None}, batch.plant):
        with pytest.raises(ValueError, match=r"scenario must be a Scenario \(build one with paper_scenario"):
            scenario_modes_hz(arm, 2, bad)
        with pytest.raises(ValueError, match=r"scenario must be a Scenario \(build one with paper_scenario"):
            scenario_plant(arm, 2, 1e-3, "zoh", bad)
        with pytest.raises(ValueError, match=r"scenario must be a Scenario \(build one with paper_scenario"):
            batch_plant(arm, 2, 1e-3, "zoh", bad, nominal)
        with pytest.raises(ValueError, match=r"scenario must be a Scenario \(build one with paper_scenario"):
            batch_modes_hz(arm, 2, bad)


def test_pad_batch_repeats_the_last_scenario_and_refuses_what_is_not_a_batch():
    batch = sample_scenarios(ScenarioSpec(horizon_s=0.01, youngs_modulus_rel=0.1), jax.random.key(3), 5)
    padded = pad_batch(batch, 4)  # 5 -> 8: three copies of scenario 4, the first 5 untouched
    for leaf, orig in zip(jax.tree.leaves(padded), jax.tree.leaves(batch)):
        assert leaf.shape[0] == 8
        np.testing.assert_array_equal(leaf[:5], orig)
        np.testing.assert_array_equal(leaf[5:], np.repeat(np.asarray(orig[-1:]), 3, axis=0))
    assert pad_batch(batch, 5) is batch and pad_batch(batch, 1) is batch
    with pytest.raises(ValueError, match=r"multiple must be an integer >= 1; got 0"):
        pad_batch(batch, 0)
    with pytest.raises(ValueError, match=r"batch must hold scenarios on axis 0 of every leaf, the same count in each; got leading sizes \[3, 4\]"):
        pad_batch({"a": jnp.ones(3), "b": jnp.ones(4)}, 2)
    with pytest.raises(ValueError, match=r"got leading sizes \[None\]"):
        pad_batch(jnp.ones(()), 2)
    with pytest.raises(ValueError, match="batch must hold scenarios"):  # as its docstring says: no scenarios, nothing to repeat
        pad_batch({"a": jnp.ones((0, 3)), "b": jnp.ones((0,))}, 2)


def test_each_factor_of_a_perturbation_scales_its_own_field():
    """Distinct factors, so that one applied to another's field shows (the tests above draw
    rho and I_H at 1, where any mix-up of the two was invisible)."""
    arm = BeamParams(payload_mass_kg=0.1)
    got = perturbed_params(arm, PlantPerturbation(*map(np.float64, (1.1, 1.2, 0.7, 0.02))))
    assert got.youngs_modulus_pa == pytest.approx(1.1 * arm.youngs_modulus_pa, rel=1e-15)
    assert got.density_kg_m3 == pytest.approx(1.2 * arm.density_kg_m3, rel=1e-15)
    assert got.hub_inertia_kg_m2 == pytest.approx(0.7 * arm.hub_inertia_kg_m2, rel=1e-15)
    assert got.payload_mass_kg == pytest.approx(0.12, rel=1e-15)
    assert all(getattr(got, name) == getattr(arm, name) for name in ("length_m", "width_m", "thickness_m", "damping_ratio"))
    assert perturbed_params(arm, None) is arm


@pytest.mark.parametrize(
    "changes, factors",
    [
        # I_H x0.5 lifts mode 2 to omega dt = 3.35 at 12 ms (the nominal arm: 2.75)
        (dict(hub_inertia_rel=0.5), (1.0, 1.0, 0.5, 0.0)),
        # a payload only lowers the modes: the arm that grows is E x1.5 with none
        (dict(youngs_modulus_rel=0.5, payload_max_kg=0.1), (1.5, 1.0, 1.0, 0.0)),
    ],
)
def test_check_plants_reaches_the_lower_end_of_each_range(changes, factors):
    """Each factor's range has two ends, and the fastest mode may be at the lower one: a
    lighter hub, or no payload, raises the frequencies."""
    spec = ScenarioSpec(horizon_s=1.0, dt=0.012, **changes)
    check_rk4_step(make_plant(), spec.dt)  # the nominal arm runs at this dt
    with pytest.raises(ValueError, match="is unstable"):  # the arm at that end does not
        check_rk4_step(make_plant(perturbed_params(BeamParams(), PlantPerturbation(*map(np.float64, factors)))), spec.dt)
    e, rho, hub, payload = (f"{v:g}" for v in factors)
    with pytest.raises(ValueError, match=rf"reaches an arm \(E x{e}, rho x{rho}, I_H x{hub}, payload \+{payload} kg\) that cannot be run"):
        check_plants(spec, BeamParams(), 2, "rk4")


def test_block_reading_needs_two_modes():
    """With one mode the state is [theta, q1, theta_dot, q1_dot]: "block" would set
    theta_dot = 1e-3 rad/s, not a q_2 that the model lacks."""
    from jaxflex.scenarios import paper_scenario

    with pytest.raises(ValueError, match=r"reading='block' sets q_2 and needs n_modes >= 2; got n_modes = 1"):
        paper_scenario(make_plant(BeamParams(), 1), reading="block")
    np.testing.assert_array_equal(np.asarray(paper_scenario(make_plant(BeamParams(), 1)).x0), [0, 1e-3, 0, 1e-5])


def test_initial_state_components_are_drawn_independently():
    """One key per component: a key used twice made q_i(0) and q_i_dot(0) the same draw
    scaled (correlation 1), which the standard deviations alone do not show."""
    x0 = draw(SPEC).x0[:, [0, 1, 2, 4, 5]]  # theta, q1, q2, q1_dot, q2_dot (theta_dot is 0)
    corr = np.corrcoef(x0.T)
    assert np.max(np.abs(corr - np.eye(5))) < 0.1
    # nor any value of one draw among another's: a key reused for another shape gives the hub
    # angle the first values of the q's draw (scenario 0's theta(0) / std is its q1(0) / std),
    # which shifted by one scenario correlates with nothing. Standardised, 64 scenarios' 320
    # normal values lie more than 1e-6 apart (pairs closer by chance: 320^2 / 2 x 0.28 x 2e-6 = 0.03)
    few = jax.tree.map(np.asarray, sample_scenarios(SPEC, jax.random.key(1), 64, dtype=np.float64)).x0
    z = np.concatenate([few[:, 0] / 0.01, few[:, 1:3].ravel() / 2e-3, few[:, 4:6].ravel() / 3e-5])
    assert np.min(np.diff(np.sort(z))) > 1e-6


def _pulse_and_step():
    """Each scenario's signed pulse amplitude and step level, and their start samples (the
    same key draws the same starts with the pulse or the step alone)."""
    pulse = draw(dataclasses.replace(SPEC, step_max_n=0.0)).force[:, :, 0]
    step = draw(dataclasses.replace(SPEC, impulse_max_n=0.0)).force[:, :, 0]
    pulse_start, step_start = np.argmax(pulse != 0, axis=1), np.argmax(step != 0, axis=1)
    return pulse[np.arange(N), pulse_start], pulse_start, step[:, -1], step_start


def test_pulse_amplitude_and_step_level_are_uniform_in_both_signs():
    """Uniform on [-impulse_max_n, impulse_max_n] and [-step_max_n, step_max_n]: drawn on
    [0, max] instead, every pulse pushed the same way, with the same mean |amplitude| and
    maximum that the test above checks."""
    from scipy import stats

    amplitude, _, level, _ = _pulse_and_step()
    for values, top in ((amplitude, 0.4), (level, 0.2)):
        assert stats.kstest(values / top, "uniform", args=(-1, 2)).pvalue > 1e-3
        assert np.mean(values < 0) == pytest.approx(0.5, abs=4 * 0.5 / np.sqrt(N))


def test_every_per_scenario_draw_is_independent_of_the_others():
    """One key per quantity: the initial state, the pulse's start and amplitude, the step's
    start and level, and the four plant factors. A key used twice (the density drawn with the
    hub inertia's number, the payload with the pulse's amplitude key) correlates two of them
    fully, which each one's own distribution does not show."""
    sc = draw(SPEC)
    amplitude, pulse_start, level, step_start = _pulse_and_step()
    columns = [*sc.x0[:, [0, 1, 2, 4, 5]].T, amplitude, pulse_start, level, step_start, *sc.plant]
    corr = np.corrcoef(np.stack(columns))
    assert corr.shape == (13, 13) and np.max(np.abs(corr - np.eye(13))) < 0.1


def test_an_impulse_of_one_sample_is_accepted():
    """impulse_duration_s may equal dt (the docs' range [dt, horizon_s / 2]): a one-sample pulse."""
    spec = ScenarioSpec(horizon_s=0.05, impulse_max_n=1.0, impulse_duration_s=1e-3, include_paper=False)
    lengths = np.sum(np.asarray(sample_scenarios(spec, jax.random.key(0), 256).force[:, :, 0]) != 0, axis=1)
    assert np.all(lengths <= 2) and np.mean(lengths == 1) > 0.9


def test_a_spec_without_uncertainty_draws_no_plant():
    """Factors of 1 and no payload are the nominal plant: no per-scenario plant is drawn
    (batch_plant then shares the nominal one over the batch)."""
    spec = ScenarioSpec(horizon_s=0.01)
    assert not spec.perturbs_plant and sample_scenarios(spec, jax.random.key(0), 2).plant is None
    assert all(ScenarioSpec(horizon_s=0.01, **{name: 0.1}).perturbs_plant for name in ("youngs_modulus_rel", "density_rel", "hub_inertia_rel", "payload_max_kg"))


@pytest.mark.parametrize("dt", [1.05e-3, 1.001e-3, 0.999e-3])
def test_paper_scenario_refuses_a_dt_near_the_sampled_plants(dt):
    """Only the sampled plant's own dt (to float32's rounding) is taken: a dt 0.1 % off would
    run the horizon at a time step the plant was not sampled at."""
    from jaxflex import discretize
    from jaxflex.scenarios import paper_scenario

    plant = discretize(make_plant(), 1e-3)
    with pytest.raises(ValueError, match=r"differs from the sampled plant's dt = 0.001 s"):
        paper_scenario(plant, 0.1, dt=dt)
    assert paper_scenario(plant, 0.1, dt=1e-3).force.shape == (100, 1)
    plant32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), plant)  # holds dt rounded
    assert paper_scenario(plant32, 0.1, dt=1e-3).force.shape == (100, 1)


def test_a_key_draws_the_same_scenarios_in_float32_and_float64():
    """JAX's float64 draws from a key are other numbers than its float32 ones: `--x64` ran
    another batch from the same seed (a Monte Carlo's peak tip deflection moved 8 %, which
    read as float32's error). Now the float64 batch, cast to float32, is the float32 one: a
    pulse's start compared in each dtype also moved by a sample in 2 of 10,000 scenarios."""
    spec = dataclasses.replace(SPEC, include_paper=True)
    wide = draw(spec)
    with jax.enable_x64(False):
        narrow = jax.tree.map(np.asarray, sample_scenarios(spec, jax.random.key(1), N, n_modes=2, dtype=jnp.float32))
    for a, b in zip(jax.tree.leaves(narrow), jax.tree.leaves(wide)):
        assert a.dtype == np.float32 and b.dtype == np.float64
        np.testing.assert_array_equal(a, b.astype(np.float32))


def test_batch_plant_refuses_a_sample_time_other_than_the_nominal_plants():
    """A 2 ms batch beside a 1 ms nominal plant ran at 2 ms when it held perturbations and at
    1 ms when it did not, without a word."""
    arm = BeamParams()
    nominal = discretize(make_plant(arm, 2), 1e-3, "zoh")
    batch = sample_scenarios(ScenarioSpec(horizon_s=0.01, youngs_modulus_rel=0.1), jax.random.key(0), 2)
    with pytest.raises(ValueError, match=r"dt = 0.002 s must be the nominal plant's sample time, 0.001 s: build both at one dt"):
        batch_plant(arm, 2, 2e-3, "zoh", batch, nominal)
    assert batch_plant(arm, 2, 1e-3, "zoh", batch, nominal).Ad.shape == (2, 6, 6)
    # likewise the number of modes: 3 for a perturbed batch, the nominal plant's 2 otherwise
    with pytest.raises(ValueError, match=r"n_modes = 3 must be the nominal plant's number of modes, 2: build both with one n_modes"):
        batch_plant(arm, 3, 1e-3, "zoh", batch, nominal)
    with pytest.raises(ValueError, match=r"nominal must be a DiscretePlant"):
        batch_plant(arm, 2, 1e-3, "zoh", batch, None)
