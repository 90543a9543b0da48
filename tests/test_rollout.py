"""Closed-loop rollout: a NumPy reference loop, jit/eager and vmap/loop agreement, gradients
against central differences, and input validation."""

import re
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflex as jf
from jaxflex.controllers import Controller, DFSParams, OpenLoopParams, PDParams, by_name, combine, dfs, fuzzy, fuzzy_params, open_loop, pd
from jaxflex.scenarios import PlantPerturbation, Scenario, initial_condition, paper_scenario
from tests.helpers import tree_allclose

RTOL_LOOP = 1e-10  # same arithmetic in another order, float64
ATOL_REORDER = 1e-14  # batched matmuls sum in another order: round-off of O(1) states
RTOL_FD = 1e-5  # the bar for gradients against central differences, float64


@pytest.fixture(scope="module")
def plant2():
    return jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")


def _numpy_dfs_loop(plant, k, delay_steps, scenario):
    """Independent reference: a plain Python loop with a list as the delay line."""
    Ad, Bd, Ed, C = (np.asarray(a) for a in (plant.Ad, plant.Bd, plant.Ed, plant.C))
    x = np.asarray(scenario.x0).copy()
    force, noise = np.asarray(scenario.force), np.asarray(scenario.noise)
    thetas, xs, us = [], [], []
    for i in range(force.shape[0]):
        y = C @ x + noise[i]
        thetas.append(y[0])
        past = thetas[max(i - delay_steps, 0)] if i - delay_steps >= 0 else thetas[0]
        u = -k * (y[0] - past)
        xs.append(x)
        us.append(u)
        x = Ad @ x + Bd[:, 0] * u + Ed[:, 0] * force[i, 0]
    return np.array(xs), np.array(us)


def test_dfs_rollout_matches_python_loop_with_force_and_noise(plant2):
    rng = np.random.default_rng(0)
    steps = 300
    sc = Scenario(
        jnp.asarray(paper_scenario(plant2).x0),
        jnp.asarray(rng.normal(scale=0.1, size=(steps, 1))),
        jnp.asarray(rng.normal(scale=1e-5, size=(steps, 2))),
    )
    traj = jf.rollout(plant2, dfs(), DFSParams(55.0, 0.005), sc)
    xs, us = _numpy_dfs_loop(plant2, 55.0, 5, sc)
    np.testing.assert_allclose(np.asarray(traj.x), xs, rtol=RTOL_LOOP, atol=1e-14)
    np.testing.assert_allclose(np.asarray(traj.u[:, 0]), us, rtol=RTOL_LOOP, atol=1e-14)
    np.testing.assert_allclose(np.asarray(traj.t), np.arange(steps) * 1e-3)
    np.testing.assert_allclose(np.asarray(traj.z[:, 2]), 0.9 * xs[:, 0] + np.asarray(traj.z[:, 1]), rtol=1e-12)


def test_paper_scenario_readings(plant2):
    printed = paper_scenario(plant2)
    block = paper_scenario(plant2, reading="block")
    np.testing.assert_array_equal(np.asarray(printed.x0), [0, 1e-3, 0, 0, 1e-5, 0])
    np.testing.assert_array_equal(np.asarray(block.x0), [0, 0, 1e-3, 0, 1e-5, 0])
    assert printed.force.shape == (3000, 1) and printed.noise.shape == (3000, 2)
    with pytest.raises(ValueError, match="reading must be one of"):
        paper_scenario(plant2, reading="other")


def test_jit_equals_eager(plant2):
    sc = paper_scenario(plant2, horizon_s=0.3)
    ctrl = combine(dfs(), pd())
    params = (DFSParams(55.0, 0.005), PDParams(0.5, 0.05))
    eager = jf.rollout(plant2, ctrl, params, sc)
    jitted = jax.jit(jf.rollout, static_argnums=1)(plant2, ctrl, params, sc)
    tree_allclose(eager, jitted, rtol=1e-12, atol=1e-16)


def test_vmap_over_scenarios_equals_loop(plant2):
    key = jax.random.key(0)
    x0s = 1e-3 * jax.random.normal(key, (8, 6))
    scs = jax.vmap(lambda x0: initial_condition(x0, 200))(x0s)
    batched = jax.jit(jax.vmap(lambda sc: jf.rollout(plant2, dfs(), DFSParams(55.0, 0.005), sc)))(scs)
    batched = jax.tree.map(np.asarray, batched)
    # The unbatched rollout, compiled once and called per scenario (an eager rollout would
    # trace and compile its scan again at every call).
    single = jax.jit(lambda x0: jf.rollout(plant2, dfs(), DFSParams(55.0, 0.005), initial_condition(x0, 200)))
    for i in range(8):
        one = single(x0s[i])
        tree_allclose(jax.tree.map(lambda a: a[i], batched), one, rtol=1e-12, atol=ATOL_REORDER)


def test_closed_over_and_traced_plants_give_the_same_loop(plant2):
    """A plant closed over by jit (its matrices' exact zeros are skipped in the loop) and the
    same plant passed as an argument (traced: every term kept) give the same loop, and a
    non-finite state is still reported."""
    assert (np.asarray(plant2.Ad) == 0).any() and (np.asarray(plant2.Cz) == 0).any()  # zeros to skip
    sc = paper_scenario(plant2, horizon_s=0.3)
    params = DFSParams(55.0, 0.005)
    for output in ("trajectory", "metrics"):
        closed = jax.jit(lambda sc, output=output: jf.rollout(plant2, dfs(), params, sc, output=output))
        traced = jax.jit(lambda plant, sc, output=output: jf.rollout(plant, dfs(), params, sc, output=output))
        tree_allclose(closed(sc), traced(plant2, sc), rtol=1e-12, atol=1e-16)
        # the closed-over loop does skip terms: fewer multiplications in its program
        assert str(jax.make_jaxpr(closed)(sc)).count(" mul ") < str(jax.make_jaxpr(traced)(plant2, sc)).count(" mul ")
    hub_inf = sc._replace(x0=sc.x0.at[0].set(jnp.inf))  # the component no other one depends on
    assert bool(closed(hub_inf).diverged) and bool(traced(plant2, hub_inf).diverged)


BATCH_CONTROLLERS = [
    ("open loop", open_loop(), OpenLoopParams()),
    ("DFS nearest", dfs(), DFSParams(55.0, 0.005)),
    ("DFS linear", dfs(interpolation="linear"), DFSParams(55.0, 0.0047)),
    ("DFS cubic", dfs(interpolation="cubic"), DFSParams(55.0, 0.0047)),
    ("DFS Pade", dfs(approximation="pade", pade_order=3), DFSParams(55.0, 0.005)),
    ("PD", pd(), PDParams(20.0, 0.5)),
    ("fuzzy", fuzzy(), fuzzy_params()),  # its defuzzifiers share the batching (vmap of the surface)
    ("DFS+fuzzy", combine(dfs(), fuzzy()), (DFSParams(55.0, 0.005), fuzzy_params())),
]


def _batch_of_scenarios(plant, batch, steps, seed=0):
    """B scenarios around the paper's, each with its own initial state, tip force and noise."""
    rng = np.random.default_rng(seed)
    base = np.asarray(paper_scenario(plant).x0)
    x0 = base + 1e-3 * rng.standard_normal((batch, base.shape[0])) * (np.arange(base.shape[0]) > 0)
    force = 0.2 * rng.standard_normal((batch, steps, 1))
    noise = rng.standard_normal((batch, steps, 2)) * np.array([1e-5, 1e-3])
    return Scenario(*(jnp.asarray(a) for a in (x0, force, noise)))


@pytest.mark.parametrize("name, controller, params", BATCH_CONTROLLERS, ids=[c[0] for c in BATCH_CONTROLLERS])
def test_a_batch_in_one_rollout_equals_vmap_over_single_scenarios(plant2, name, controller, params):
    """The batch as one rollout (the batch last in the loop; what Monte Carlo, the tuner and
    the benchmark run) against ``vmap`` over single rollouts, for every built-in controller:
    metrics with per-scenario inputs and a batch of plants; for DFS+fuzzy also trajectories
    with the inputs and the plant shared by the batch (one compilation fewer per controller)."""
    del name
    scs = _batch_of_scenarios(plant2, 5, 150)
    scale = jnp.array([1.0, 0.9, 1.1, 0.95, 1.05])
    plants = jax.vmap(lambda s: plant2._replace(Bd=plant2.Bd * s))(scale)  # five arms
    freqs = jnp.array([[3.0, 20.0]]) * scale[:, None]

    def both(plant, sc, plant_axis, freqs, freq_axis, shared_inputs):
        one = lambda p, s, f: jf.rollout(p, controller, params, s, output=output, **({"mode_freqs_hz": f} if output == "metrics" else {}))  # noqa: E731
        in_axes = (plant_axis, Scenario(0, None, None) if shared_inputs else 0, freq_axis)
        return jax.jit(jax.vmap(one, in_axes=in_axes))(plant, sc, freqs), jax.jit(one)(plant, sc, freqs)

    output = "metrics"  # Monte Carlo's and the tuner's case
    mapped, batched = both(plants, scs, 0, freqs, 0, False)
    tree_allclose(batched, mapped, rtol=1e-12, atol=1e-15)
    if isinstance(params, tuple):  # DFS+fuzzy, the paper's controller: also trajectories with shared inputs
        output = "trajectory"
        mapped, batched = both(plant2, scs._replace(force=scs.force[0], noise=scs.noise[0]), None, freqs[0], None, True)
        tree_allclose(batched, mapped, rtol=1e-12, atol=1e-15)


def test_a_controller_written_for_one_scenario_runs_a_batch_through_vmap(plant2):
    """A user's controller (``batched`` False) is mapped over the batch by the rollout, and
    gives what ``vmap`` over single rollouts gives, values and gradients."""

    class Gain(NamedTuple):
        k: Any

    def step(params, state, y):  # written for one scenario: a shape check and a full sum
        assert y.shape == (2,)
        return state + 1.0, -params.k * jnp.sum(y * jnp.array([1.0, 0.05])).reshape(1) + 0.0 * state

    mine = Controller(lambda params, y0: jnp.zeros(()), step, lambda params: None)
    scs = _batch_of_scenarios(plant2, 4, 120)

    def loss(k, batched):
        run = lambda s: jf.rollout(plant2, mine, Gain(k), s, output="metrics").tip_ise  # noqa: E731
        return jnp.mean(run(scs) if batched else jax.vmap(run)(scs))

    for batched in (False, True):
        assert np.isfinite(float(loss(30.0, batched)))
    value, grad = jax.value_and_grad(loss)(30.0, True)
    value_ref, grad_ref = jax.value_and_grad(loss)(30.0, False)
    np.testing.assert_allclose(float(value), float(value_ref), rtol=1e-12)
    np.testing.assert_allclose(float(grad), float(grad_ref), rtol=1e-10)


def test_the_gradient_of_a_batch_equals_the_gradient_through_vmap(plant2):
    """The tuner's loss (a batch mean) differentiated through the batched rollout and through
    ``vmap`` over single rollouts: the same gradient for DFS+fuzzy's 20 parameters."""
    controller, params = by_name("dfs+fuzzy", dt=1e-3, delay="linear", params={"tau_s": 0.0047})
    scs = _batch_of_scenarios(plant2, 4, 150)

    def loss(params, batched):
        run = lambda s: jf.rollout(plant2, controller, params, s, output="metrics").tip_ise  # noqa: E731
        return jnp.mean(run(scs) if batched else jax.vmap(run)(scs))

    grads = [jax.jit(jax.grad(loss), static_argnums=1)(params, batched) for batched in (True, False)]
    tree_allclose(grads[0], grads[1], rtol=1e-10, atol=1e-14)
    assert all(float(jnp.max(jnp.abs(g))) > 0 for g in jax.tree.leaves(grads[0]))


def test_a_batched_delay_line_is_one_row_per_slot(plant2):
    """The reason for running the batch in the loop: the DFS ring buffer is carried as
    [slots, 1, B] (each sample's write and read one contiguous row), not [B, slots, 1] as
    ``vmap`` lays it out."""
    scs = _batch_of_scenarios(plant2, 3, 20)
    params = DFSParams(55.0, 0.005)
    shapes = lambda jaxpr: {tuple(v.aval.shape) for eqn in jaxpr.eqns if eqn.primitive.name == "scan" for v in eqn.invars}  # noqa: E731
    batched = jax.make_jaxpr(lambda s: jf.rollout(plant2, dfs(capacity=8), params, s, output="metrics"))(scs).jaxpr
    mapped = jax.make_jaxpr(jax.vmap(lambda s: jf.rollout(plant2, dfs(capacity=8), params, s, output="metrics")))(scs).jaxpr
    assert (9, 1, 3) in shapes(batched) and (3, 9, 1) not in shapes(batched)
    assert (3, 9, 1) in shapes(mapped)


def test_bad_batches_are_refused_by_name(plant2):
    scs = _batch_of_scenarios(plant2, 3, 20)
    plants = jax.tree.map(lambda a: jnp.stack([a] * 2), plant2)
    params = DFSParams(55.0, 0.005)
    with pytest.raises(ValueError, match=r"a batch of plants .* needs a batch of as many scenarios"):
        jf.rollout(plants, dfs(), params, scs)
    with pytest.raises(ValueError, match=r"a batch of plants .* needs a batch of as many scenarios"):
        jf.rollout(plants, dfs(), params, jax.tree.map(lambda a: a[0], scs))
    # the batch's shape in the message, with T for the horizon (it read -1)
    with pytest.raises(ValueError, match=r"^scenario.force must have shape \(T, 1\) with T >= 1 \(shared by the batch\), or \(3, T, 1\) with the batch first; got \(2, 20, 1\)$"):
        jf.rollout(plant2, dfs(), params, scs._replace(force=scs.force[:2]))
    with pytest.raises(ValueError, match=r"scenario.noise must have shape"):
        jf.rollout(plant2, dfs(), params, scs._replace(noise=scs.noise[:, :10]))
    # a force cut short is named as the horizon the noise is measured against (the noise alone was blamed)
    with pytest.raises(ValueError, match=r"^scenario.noise must have shape \(10, 2\) or \(3, 10, 2\), the horizon T = 10 of scenario.force; got \(3, 20, 2\) \(force and noise hold one row per sample\)$"):
        jf.rollout(plant2, dfs(), params, scs._replace(force=scs.force[:, :10]))
    with pytest.raises(ValueError, match="scenario.x0 must have shape"):
        jf.rollout(plant2, dfs(), params, scs._replace(x0=scs.x0[None]))
    with pytest.raises(ValueError, match=r"plant.dt must have shape \(2,\)"):
        jf.rollout(plants._replace(dt=plant2.dt), dfs(), params, jax.tree.map(lambda a: a[:2], scs))
    with pytest.raises(ValueError, match=r"mode_freqs_hz must be a 1-D array .* or 3 of them"):
        jf.rollout(plant2, dfs(), params, scs, output="metrics", mode_freqs_hz=jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="controller.batched must be True or False"):
        jf.rollout(plant2, dfs()._replace(batched=1), params, scs)


def _tip_ise(plant, params, steps=400):
    sc = paper_scenario(plant, horizon_s=steps * 1e-3)
    traj = jf.rollout(plant, dfs(), params, sc)
    return jnp.sum(traj.z[:, 1] ** 2) * 1e-3


# Each gradient test below compiles one ``value_and_grad`` and reads both the gradient and the
# central-difference values of the loss from it (the value is the forward pass of the same
# program), instead of one compilation for the gradient and eager rollouts for the differences.


def test_dfs_gradient_wrt_k_matches_central_difference(plant2):
    k = 55.0
    vg = jax.jit(jax.value_and_grad(lambda k: _tip_ise(plant2, DFSParams(k, 0.005))))
    g = float(vg(k)[1])
    h = 1e-4 * k
    fd = (float(vg(k + h)[0]) - float(vg(k - h)[0])) / (2 * h)
    assert g != 0 and np.isfinite(g)
    np.testing.assert_allclose(g, fd, rtol=RTOL_FD)


FUZZY_FIELDS = ("k1", "k2", "k3")


@pytest.fixture(scope="module")
def fuzzy_tip_ise(plant2):
    """Jitted value and gradient of the tip ISE w.r.t. (k1, k2, k3), compiled once for the module:
    1 s of the paper scenario under the paper's fuzzy controller, float64."""
    sc = paper_scenario(plant2, horizon_s=1.0)

    def loss(k1, k2, k3):
        params = fuzzy_params(1.02, 0.30, 1.0)._replace(k1=k1, k2=k2, k3=k3)
        traj = jf.rollout(plant2, fuzzy(), params, sc)
        return jnp.sum(traj.z[:, 1] ** 2) * 1e-3

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))


@pytest.mark.parametrize("field", FUZZY_FIELDS)
def test_fuzzy_gradient_wrt_scaling_factors_matches_central_difference(fuzzy_tip_ise, field):
    """At the paper's operating point, 1 s of the paper scenario, float64."""
    paper = fuzzy_params(1.02, 0.30, 1.0)
    base = {name: float(getattr(paper, name)) for name in FUZZY_FIELDS}

    def loss(v):
        return float(fuzzy_tip_ise(*(v if name == field else base[name] for name in FUZZY_FIELDS))[0])

    v = base[field]
    g = float(fuzzy_tip_ise(*(base[name] for name in FUZZY_FIELDS))[1][FUZZY_FIELDS.index(field)])
    h = 1e-5 * v  # small enough that no membership kink is crossed along the 1000 samples
    fd = (loss(v + h) - loss(v - h)) / (2 * h)
    assert g != 0 and np.isfinite(g)
    np.testing.assert_allclose(g, fd, rtol=RTOL_FD)


def test_gradient_wrt_plant_parameter(plant2):
    def loss(E):
        d = jf.discretize(jf.make_plant(jf.BeamParams(youngs_modulus_pa=E), 2), 1e-3, "rk4")
        return _tip_ise(d, DFSParams(55.0, 0.005), steps=200)

    E = 71e9
    vg = jax.jit(jax.value_and_grad(loss))
    g = float(vg(E)[1])
    h = 1e-4 * E
    fd = (float(vg(E + h)[0]) - float(vg(E - h)[0])) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=RTOL_FD)


# Short runs for the gradients of the PD and combined controllers and of the running metrics:
# 80 samples of the paper scenario with a tip-force pulse, so the hub moves at once.
FD_STEPS = 80


def _pulse_scenario(plant):
    sc = paper_scenario(plant, horizon_s=FD_STEPS * 1e-3)
    return sc._replace(force=sc.force.at[3:8, 0].set(0.2))


def _check_against_central_differences(vg, params, fields, rtol=RTOL_FD, h_rel=1e-5):
    """``vg(params) -> (loss, grads)`` jitted once: each field's gradient against a central
    difference of the loss from the same program (float64; truncation ~(h_rel)^2 ~ 1e-10 and
    round-off ~eps / h_rel ~ 1e-11, relative, far below ``rtol``)."""
    grads = vg(params)[1]
    for name in fields:
        v = float(getattr(params, name))
        h = h_rel * abs(v)
        up, down = (float(vg(params._replace(**{name: v + d}))[0]) for d in (h, -h))
        g = float(getattr(grads, name))
        assert g != 0 and np.isfinite(g), name
        np.testing.assert_allclose(g, (up - down) / (2 * h), rtol=rtol, err_msg=name)


def test_pd_gradient_wrt_gains_matches_central_difference(plant2):
    sc = _pulse_scenario(plant2)

    def loss(p):
        traj = jf.rollout(plant2, pd(), p, sc)
        return (jnp.sum(traj.z[:, 1] ** 2) + jnp.sum(traj.z[:, 0] ** 2)) * 1e-3

    _check_against_central_differences(jax.jit(jax.value_and_grad(loss)), PDParams(1.0, 0.1), ("kp", "kd"))


def test_combined_controller_gradient_matches_central_difference(plant2):
    """DFS (linear read, fractional tau) + PD through ``combine``: the gradient reaches each
    gain of both parts of the parameter pair. (PD as the second part: its program compiles in
    a fraction of the fuzzy controller's time; the fuzzy gains' own gradients are checked
    above and in test_fuzzy.py.)"""
    sc = _pulse_scenario(plant2)
    ctrl = combine(dfs(1e-3, 16, "linear"), pd())

    class Gains(NamedTuple):
        k: Any
        tau_s: Any
        kp: Any
        kd: Any

    def loss(g):
        traj = jf.rollout(plant2, ctrl, (DFSParams(g.k, g.tau_s), PDParams(g.kp, g.kd)), sc)
        return (jnp.sum(traj.z[:, 1] ** 2) + jnp.sum(traj.z[:, 0] ** 2)) * 1e-3

    gains = Gains(*(jnp.asarray(v) for v in (55.0, 0.0053, 1.0, 0.1)))
    _check_against_central_differences(jax.jit(jax.value_and_grad(loss)), gains, Gains._fields)


def test_running_metrics_gradients_match_central_differences(plant2):
    """Every differentiable field of ``RunMetrics`` (output="metrics", the tuner's path) in k and
    a fractional tau (linear read): one forward-mode Jacobian, with the metrics themselves as its
    aux (one compilation), against central differences of the metrics. The peak and the
    settling time are left out: piecewise (here the peak is the initial deflection, and the
    settling time is piecewise constant)."""
    sc = _pulse_scenario(plant2)
    ctrl = dfs(1e-3, 16, "linear")
    fields = ("tip_ise", "tip_iae", "hub_ise", "control_effort", "final_hub_angle_rad")

    def metrics(p):
        m = jf.rollout(plant2, ctrl, p, sc, output="metrics", mode_freqs_hz=[13.3, 36.5])
        out = jnp.concatenate([jnp.stack([getattr(m, f) for f in fields]), m.modal_energy])
        return out, out

    jac_and_values = jax.jit(jax.jacfwd(metrics, has_aux=True))
    base = DFSParams(jnp.asarray(55.0), jnp.asarray(0.0053))
    jac = jac_and_values(base)[0]
    for name in DFSParams._fields:
        x = float(getattr(base, name))
        h = 1e-5 * x
        up, down = (np.asarray(jac_and_values(base._replace(**{name: jnp.asarray(x + d)}))[1]) for d in (h, -h))
        g = np.asarray(getattr(jac, name))
        assert np.all(g != 0) and np.all(np.isfinite(g)), name
        np.testing.assert_allclose(g, (up - down) / (2 * h), rtol=RTOL_FD, err_msg=name)


def test_open_loop_conserves_energy_without_damping():
    params = jf.BeamParams(rayleigh_alpha=0.0, rayleigh_beta=0.0)
    p = jf.make_plant(params, 2)
    d = jf.discretize(p, 1e-3, "zoh")
    traj = jf.rollout(d, open_loop(), OpenLoopParams(), paper_scenario(d, horizon_s=1.0))
    from jaxflex import beam

    mats = beam.modal_matrices(params, 2)
    q, qd = traj.x[:, :3], traj.x[:, 3:]
    energy = 0.5 * jnp.einsum("ti,ij,tj->t", qd, mats.M, qd) + 0.5 * jnp.einsum("ti,ij,tj->t", q, mats.K, q)
    np.testing.assert_allclose(np.asarray(energy), float(energy[0]), rtol=1e-9)


@pytest.mark.parametrize(
    "params, match",
    [
        (DFSParams(55.0, 0.0055), "whole number of samples"),
        (DFSParams(55.0, 0.5), r"tau_s must be in \(0, 0.064\]"),
        (DFSParams(55.0, -0.001), "tau_s must be finite and > 0"),
        (DFSParams(float("nan"), 0.005), "k must be finite"),
    ],
)
def test_bad_dfs_parameters_are_rejected(plant2, params, match):
    with pytest.raises(ValueError, match=match):
        jf.rollout(plant2, dfs(), params, paper_scenario(plant2, horizon_s=0.01))


def test_concrete_parameters_are_checked_beside_traced_ones(plant2):
    """Under grad with respect to one gain, the other parameters are concrete and still
    checked by name (they were skipped with any leaf traced: a fractional delay ran NaN, a
    negative k2 gave a finite, wrong gradient). All-traced parameters run as before, and a
    user's check that reads a traced value is skipped under tracing, not raised."""
    sc = paper_scenario(plant2, horizon_s=0.02)

    def ise(controller, params):
        return jnp.sum(jf.rollout(plant2, controller, params, sc).z[:, 1] ** 2)

    with pytest.raises(ValueError, match="tau_s must be a whole number of samples"):
        jax.grad(lambda k: ise(dfs(), DFSParams(k, 0.0055)))(55.0)
    with pytest.raises(ValueError, match=r"tau_s must be in \(0, 0.064\]"):
        jax.grad(lambda k: ise(dfs(), DFSParams(k, 0.5)))(55.0)
    with pytest.raises(ValueError, match="k2 must be finite and > 0"):
        jax.grad(lambda k1: ise(fuzzy(), fuzzy_params(k1, -0.3, 1.0)))(1.02)
    with pytest.raises(ValueError, match="angle_centres must have shape"):
        jax.grad(lambda k3: ise(fuzzy(), fuzzy_params(1.02, 0.3, k3)._replace(angle_centres=jnp.asarray([1.0, 0.5, 0.0, -0.5, -1.0]))))(1.0)
    with pytest.raises(ValueError, match="k must be finite"):
        jax.grad(lambda tau: ise(dfs(interpolation="linear"), DFSParams(float("nan"), tau)))(0.0055)
    assert np.isfinite(float(jax.grad(lambda k: ise(dfs(), DFSParams(k, 0.005)))(55.0)))
    assert np.isnan(float(jax.jit(lambda p: ise(dfs(), p))(DFSParams(55.0, 0.0055))))  # all traced: NaN, as documented

    def strict_check(p):
        if not float(p["kp"]) > 0:
            raise ValueError("kp must be > 0")

    mine = Controller(lambda p, y0: (), lambda p, s, y: (s, -(p["kp"] * y[:1] + p["kd"] * y[1:2])), strict_check)
    with pytest.raises(ValueError, match="kp must be > 0"):
        ise(mine, {"kp": -1.0, "kd": 0.1})
    assert np.isfinite(float(jax.grad(lambda kp: ise(mine, {"kp": kp, "kd": 0.1}))(1.0)))  # its check reads the traced kp: skipped


def test_fractional_delay_accepted_with_linear_interpolation(plant2):
    sc = paper_scenario(plant2, horizon_s=0.05)
    traj = jf.rollout(plant2, dfs(interpolation="linear"), DFSParams(55.0, 0.0055), sc)
    assert np.all(np.isfinite(np.asarray(traj.x)))


def test_a_controller_sample_time_that_is_not_a_time_is_refused(plant2):
    """A Controller's dt of "0.001" failed in NumPy's ufuncs, and 0 was reported as another dt
    than the plant's."""
    sc = paper_scenario(plant2, horizon_s=0.01)
    for dt in ("0.001", 0.0, -1e-3, float("nan"), True):
        with pytest.raises(ValueError, match=re.escape(f"controller.dt must be a finite number of seconds > 0; got {dt!r}")):
            jf.rollout(plant2, pd()._replace(dt=dt), PDParams(1.0, 0.1), sc)


def test_controller_built_for_another_dt_is_rejected(plant2):
    # dfs(dt=2e-3) reads tau = 6 ms as 3 samples: on a 1 ms plant that would simulate a 3 ms delay.
    sc = paper_scenario(plant2, horizon_s=0.01)
    with pytest.raises(ValueError, match=r"controller was built for dt = 0.002 s but the plant is sampled at dt = 0.001 s"):
        jf.rollout(plant2, dfs(dt=2e-3), DFSParams(55.0, 0.006), sc)
    # the paper's 5 ms is 2.5 samples of 2 ms: the dt is named, not the delay's rounding
    with pytest.raises(ValueError, match=r"controller was built for dt = 0.002 s but the plant is sampled at dt = 0.001 s"):
        jf.rollout(plant2, dfs(dt=2e-3), DFSParams(55.0, 0.005), sc)
    with pytest.raises(ValueError, match=r"built for dt = 0.002 s and dt = 0.001 s"):
        combine(dfs(dt=2e-3), dfs(dt=1e-3))
    assert combine(fuzzy(), dfs(dt=2e-3)).dt == 2e-3 and combine(pd(), fuzzy()).dt is None
    # Under jit the plant is traced and cannot refuse: the run is NaN and reports itself diverged.
    simulate = jax.jit(jf.rollout, static_argnums=1, static_argnames="output")
    assert bool(simulate(plant2, dfs(dt=2e-3), DFSParams(55.0, 0.006), sc, output="metrics").diverged)
    ok = simulate(plant2, dfs(dt=1e-3), DFSParams(55.0, 0.006), sc, output="metrics")
    assert not bool(ok.diverged) and np.isfinite(float(ok.tip_ise))
    # A float32 plant's dt (1e-3 rounded) is the same sample time.
    d32 = jf.discretize(jf.make_plant(jf.BeamParams(*(jnp.float32(v) if v is not None else None for v in jf.BeamParams())), 2), 1e-3, "rk4")
    jf.rollout(d32, dfs(), DFSParams(jnp.float32(55.0), jnp.float32(0.005)), paper_scenario(d32, horizon_s=0.01))


def test_bad_scenario_shapes_are_rejected(plant2):
    sc = paper_scenario(plant2, horizon_s=0.01)
    with pytest.raises(ValueError, match="x0 must have shape"):
        jf.rollout(plant2, open_loop(), OpenLoopParams(), sc._replace(x0=jnp.zeros(4)))
    with pytest.raises(ValueError, match="noise must have shape"):
        jf.rollout(plant2, open_loop(), OpenLoopParams(), sc._replace(noise=jnp.zeros((3, 2))))
    with pytest.raises(ValueError, match="dfs|dt must be"):
        dfs(dt=0.0)


def test_api_mix_ups_are_refused_by_name(plant2):
    """A continuous plant, an uncalled factory or a Controller without a check failed deep
    inside with an AttributeError or a TypeError ('NoneType' object is not callable)."""
    from jaxflex.controllers import Controller

    sc = paper_scenario(plant2, horizon_s=0.01)
    continuous = jf.make_plant(jf.BeamParams(), 2)
    with pytest.raises(ValueError, match=r"plant must be a DiscretePlant \(build one with jaxflex.discretize\(plant, dt, method\)\); got LinearPlant"):
        jf.rollout(continuous, open_loop(), OpenLoopParams(), sc)
    for factory in (dfs, fuzzy):
        with pytest.raises(ValueError, match=rf"controller must be a Controller \(build one with dfs\(...\), .*\); got the function {factory.__name__} itself: call it"):
            jf.rollout(plant2, factory, OpenLoopParams(), sc)
    loop = open_loop()
    with pytest.raises(ValueError, match=r"controller.check must be callable .*; got None"):
        jf.rollout(plant2, Controller(loop.init, loop.step, None), OpenLoopParams(), sc)
    with pytest.raises(ValueError, match=r"second must be a Controller .*; got the function pd itself: call it"):
        combine(dfs(), pd)


@pytest.mark.parametrize("u_shape", [(), (2,), (1, 1)])
def test_a_controller_returning_another_torque_shape_is_refused(plant2, u_shape):
    """A scalar failed deep in the scan; a (2,) torque ran, with its second entry in the effort."""
    from jaxflex.controllers import Controller

    own = Controller(lambda p, y0: (), lambda p, s, y: (s, -p * y[0] * jnp.ones(u_shape)), lambda p: None)
    with pytest.raises(ValueError, match=re.escape(f"the controller's step must return the torque u with shape (1,) (N*m); got shape {u_shape}")):
        jf.rollout(plant2, own, 5.0, paper_scenario(plant2, horizon_s=0.01), output="metrics")


def test_float32_rollout_preserves_dtype():
    params = jf.BeamParams(*(jnp.float32(v) if v is not None else None for v in jf.BeamParams()))
    d = jf.discretize(jf.make_plant(params, 2), 1e-3, "rk4")
    sc = paper_scenario(d, horizon_s=0.05)
    assert sc.x0.dtype == jnp.float32
    traj = jf.rollout(d, dfs(), DFSParams(jnp.float32(55.0), jnp.float32(0.005)), sc)
    assert traj.x.dtype == jnp.float32 and traj.u.dtype == jnp.float32


@pytest.mark.parametrize("controller, params", [(dfs(), DFSParams(55.0, 0.005)), (fuzzy(), fuzzy_params(1.02, 0.30, 1.0))])
def test_running_metrics_equal_trajectory_metrics(plant2, controller, params):
    steps = 1500
    force = np.zeros((steps, 1))
    force[100:110] = 0.5  # a 10 ms tip-force pulse at t = 0.1 s
    sc = Scenario(paper_scenario(plant2).x0, jnp.asarray(force), jnp.zeros((steps, 2)))
    traj = jf.rollout(plant2, controller, params, sc)
    freqs = np.array([13.3, 36.5])
    m = jf.rollout(plant2, controller, params, sc, output="metrics", mode_freqs_hz=freqs)
    tip, hub, dt = np.asarray(traj.z[:, 1]), np.asarray(traj.z[:, 0]), 1e-3
    t = np.arange(steps) * dt
    hann = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(steps) / steps)
    dft = [abs(np.sum(hann * tip * np.exp(-2j * np.pi * f * t)) * dt) ** 2 for f in freqs]
    np.testing.assert_allclose(np.asarray(m.modal_energy), dft, rtol=1e-9)
    np.testing.assert_allclose(m.peak_tip_m, np.abs(tip).max(), rtol=1e-12)
    np.testing.assert_allclose(m.tip_ise, np.sum(tip**2) * dt, rtol=1e-10)
    np.testing.assert_allclose(m.tip_iae, np.sum(np.abs(tip)) * dt, rtol=1e-10)
    np.testing.assert_allclose(m.hub_ise, np.sum(hub**2) * dt, rtol=1e-10)
    np.testing.assert_allclose(m.control_effort, np.sum(np.asarray(traj.u) ** 2) * dt, rtol=1e-10)
    x_end = np.asarray(plant2.Ad) @ np.asarray(traj.x[-1]) + np.asarray(plant2.Bd) @ np.asarray(traj.u[-1]) + np.asarray(plant2.Ed) @ np.asarray(sc.force[-1])
    np.testing.assert_allclose(m.final_hub_angle_rad, x_end[0], rtol=1e-10)
    outside = np.nonzero(np.abs(tip) > 0.02 * np.abs(tip).max())[0]
    expected = np.inf if outside[-1] == steps - 1 else (outside[-1] + 1) * dt
    np.testing.assert_allclose(m.settling_time_s, expected, rtol=1e-12)
    assert 0 < expected < 1.5
    np.testing.assert_allclose(m.peak_abs_state, np.abs(np.asarray(traj.x)).max(), rtol=1e-12)
    assert not bool(m.diverged)
    # the running settling time reads the band it is given, not the default 2 %
    for band in (0.25, 0.005):
        outside = np.nonzero(np.abs(tip) > band * np.abs(tip).max())[0]
        banded = np.inf if outside[-1] == steps - 1 else (outside[-1] + 1) * dt
        assert banded != expected
        m_band = jf.rollout(plant2, controller, params, sc, output="metrics", mode_freqs_hz=freqs, settling_band=band)
        np.testing.assert_allclose(m_band.settling_time_s, banded, rtol=1e-12)


def test_peak_abs_state_covers_samples_0_to_T_minus_1(plant2):
    """The metrics cover the samples k = 0..T-1 of the trajectory: over one sample the state's
    peak is the initial state's, not the state after it (which the trajectory does not hold)."""
    x0 = paper_scenario(plant2).x0
    for steps in (1, 3):
        sc = Scenario(x0, jnp.zeros((steps, 1)), jnp.zeros((steps, 2)))
        traj = jf.rollout(plant2, pd(), PDParams(5.0, 0.5), sc)
        m = jf.rollout(plant2, pd(), PDParams(5.0, 0.5), sc, output="metrics")
        np.testing.assert_allclose(m.peak_abs_state, np.abs(np.asarray(traj.x)).max(), rtol=1e-14)
    assert float(m.peak_abs_state) > 0
    one = jf.rollout(plant2, pd(), PDParams(5.0, 0.5), Scenario(x0, jnp.zeros((1, 1)), jnp.zeros((1, 2))), output="metrics")
    assert float(one.peak_abs_state) == float(np.abs(np.asarray(x0)).max())
    x1 = np.asarray(plant2.Ad) @ np.asarray(x0)  # the state after the one sample (u = 0 at rest)
    assert np.abs(x1).max() != np.abs(np.asarray(x0)).max()


def test_settling_time_at_the_two_ends(plant2):
    """A tip that never leaves zero has settled at t = 0; one still outside the band at the
    last sample (the open loop rings for seconds) has not settled: +inf, as the trajectory
    says."""
    steps = 200
    still = Scenario(jnp.zeros(6), jnp.zeros((steps, 1)), jnp.zeros((steps, 2)))
    assert float(jf.rollout(plant2, open_loop(), OpenLoopParams(), still, output="metrics").settling_time_s) == 0.0
    ringing = paper_scenario(plant2, horizon_s=0.2)
    tip = np.abs(np.asarray(jf.rollout(plant2, open_loop(), OpenLoopParams(), ringing).z[:, 1]))
    assert tip[-1] > 0.02 * tip.max()
    assert float(jf.rollout(plant2, open_loop(), OpenLoopParams(), ringing, output="metrics").settling_time_s) == np.inf


def test_running_metrics_report_divergence(plant2):
    sc = paper_scenario(plant2, horizon_s=2.0)
    m = jf.rollout(plant2, pd(), PDParams(-50.0, -1.0), sc, output="metrics")  # positive feedback
    assert bool(m.diverged)
    assert jf.rollout(plant2, pd(), PDParams(1.0, 0.1), sc, output="metrics").diverged.item() is False


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_running_peaks_on_bits_equal_jnp_maximum(dtype):
    """The running peaks (``peak_tip_m``, ``peak_abs_state``) take integer maxima of the
    magnitudes' bits: NumPy's ``maximum`` of ``abs`` over signed zeros, subnormals, the largest
    finite value, infinities and NaNs of either sign (NaN wins, and stays), exactly; and the
    derivatives of a chain of ``jnp.maximum``, ties included. (XLA's CPU arithmetic flushes
    subnormals to zero, so that chain's values differ from NumPy's there.)"""
    from jaxflex.rollout import _peak_abs, _peak_abs_exact

    info = jnp.finfo(dtype)
    specials = np.array([0.0, -0.0, float(info.smallest_subnormal), -float(info.smallest_subnormal), float(info.tiny), 1.0, -1.0, 2.5, -3.0, float(info.max), -float(info.max), np.inf, -np.inf, np.nan, -np.nan], dtype)
    rng = np.random.default_rng(0)
    peaks = np.concatenate([np.abs(specials), rng.uniform(0, 4, 64).astype(dtype)])  # a running peak is >= 0 or NaN
    values = tuple(jnp.asarray(np.concatenate([rng.permutation(specials), rng.normal(0, 2, 64).astype(dtype)])) for _ in range(3))
    peaks = jnp.asarray(peaks)
    for n in (1, 3):  # the tip's peak (one value), the state's (several)
        fast = np.asarray(_peak_abs(peaks, values[:n]))
        expected = np.maximum.reduce([np.asarray(peaks)] + [np.abs(np.asarray(v)) for v in values[:n]])
        assert fast.dtype == expected.dtype == dtype
        assert np.isnan(expected).sum() >= 2  # a NaN peak stays, a NaN value wins
        np.testing.assert_array_equal(fast, expected)  # NaN where NumPy has NaN, and bit for bit elsewhere
    # Derivatives where everything is finite, with exact ties between the peak and a value.
    finite_peaks = jnp.asarray(rng.uniform(0, 4, 32).astype(dtype))
    finite = tuple(jnp.asarray(rng.normal(0, 2, 32).astype(dtype)) for _ in range(3))
    finite = (finite[0].at[:4].set(-finite_peaks[:4]),) + finite[1:]
    tangents = (jnp.asarray(rng.normal(size=32).astype(dtype)), tuple(jnp.asarray(rng.normal(size=32).astype(dtype)) for _ in range(3)))
    out_fast, tan_fast = jax.jvp(_peak_abs, (finite_peaks, finite), tangents)
    out_exact, tan_exact = jax.jvp(_peak_abs_exact, (finite_peaks, finite), tangents)
    np.testing.assert_array_equal(out_fast, out_exact)
    np.testing.assert_array_equal(tan_fast, tan_exact)
    for n in (1, 3):
        grad_fast = jax.grad(lambda p: jnp.sum(_peak_abs(p, finite[:n])))(finite_peaks)
        grad_exact = jax.grad(lambda p: jnp.sum(_peak_abs_exact(p, finite[:n])))(finite_peaks)
        np.testing.assert_array_equal(grad_fast, grad_exact)
    tied = jax.grad(lambda p: jnp.sum(_peak_abs(p, finite[:1])))(finite_peaks)
    assert np.all(np.asarray(tied)[:4] == 0.5)  # the ties split half and half


def test_unknown_output_is_rejected(plant2):
    with pytest.raises(ValueError, match="output must be one of"):
        jf.rollout(plant2, open_loop(), OpenLoopParams(), paper_scenario(plant2, horizon_s=0.01), output="all")


def test_paper_scenario_follows_the_sampled_plant_and_rollout_names_bad_inputs(plant2):
    fast = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-4, "rk4")
    assert paper_scenario(fast, horizon_s=0.3).force.shape == (3000, 1)  # 0.3 s at the plant's 0.1 ms
    with pytest.raises(ValueError, match="differs from the sampled plant's dt"):
        paper_scenario(fast, horizon_s=0.3, dt=1e-3)
    with pytest.raises(ValueError, match="dtype must be a floating dtype"):
        paper_scenario(plant2, dtype=jnp.int32)
    sc = paper_scenario(plant2, horizon_s=0.01)
    controller, params = dfs(), DFSParams(55.0, 0.005)
    for band in (-1.0, 0.0, 1.0, 5.0, float("nan"), True, "0.1", jnp.asarray([0.1]), None):
        with pytest.raises(ValueError, match=r"settling_band must be a number in \(0, 1\)"):
            jf.rollout(plant2, controller, params, sc, output="metrics", settling_band=band)
    with pytest.raises(ValueError, match=r"settling_band must be a number in \(0, 1\) \(a fraction of the peak\), concrete \(not traced\)"):
        jax.jit(lambda band: jf.rollout(plant2, controller, params, sc, output="metrics", settling_band=band))(0.1)
    # A concrete jnp scalar is a number: the same run as the Python float (it was refused).
    as_float = jf.rollout(plant2, controller, params, sc, output="metrics", settling_band=0.25)
    as_array = jf.rollout(plant2, controller, params, sc, output="metrics", settling_band=jnp.asarray(0.25))
    assert all(np.array_equal(a, b) for a, b in zip(as_float, as_array))
    with pytest.raises(ValueError, match="mode_freqs_hz must be finite frequencies >= 0"):
        jf.rollout(plant2, controller, params, sc, output="metrics", mode_freqs_hz=[float("nan")])
    with pytest.raises(ValueError, match=re.escape("mode_freqs_hz must be a 1-D array of frequencies (Hz); got shape ()")):
        jf.rollout(plant2, controller, params, sc, output="metrics", mode_freqs_hz=13.3)  # failed deep in lax's broadcasting
    with pytest.raises(ValueError, match="mode_freqs_hz must be a 1-D array"):
        jf.rollout(plant2, controller, params, sc, output="metrics", mode_freqs_hz=[[1.0, 2.0], [3.0, 4.0]])
    # float32 plant and scenario (this suite runs with x64 on): float64 parameters would widen
    # the loop's carry, which lax.scan refuses with a message about carry types.
    plant32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), plant2)
    sc32 = paper_scenario(plant32, horizon_s=0.01)
    with pytest.raises(ValueError, match=r"scenario.x0 is float64 but the plant is float32"):
        jf.rollout(plant32, controller, params, sc)
    with pytest.raises(ValueError, match=r"params\.k1 is float64, wider than the plant's float32"):
        jf.rollout(plant32, *jf.controllers.by_name("fuzzy", dt=1e-3, dtype=jnp.float64), sc32)
    jf.rollout(plant32, *jf.controllers.by_name("fuzzy", dt=1e-3, dtype=jnp.float32), sc32)  # and in float32 it runs


@pytest.mark.parametrize("freqs", [[-1.0], [13.3, -0.5], [float("inf")]])
def test_negative_or_infinite_mode_frequencies_are_refused(plant2, freqs):
    sc = paper_scenario(plant2, horizon_s=0.01)
    with pytest.raises(ValueError, match="mode_freqs_hz must be finite frequencies >= 0"):
        jf.rollout(plant2, open_loop(), OpenLoopParams(), sc, output="metrics", mode_freqs_hz=freqs)


def test_a_mode_frequency_at_nyquist_is_refused_and_one_just_below_runs(plant2):
    """At the Nyquist frequency (500 Hz at 1 ms) a DFT bin reads an alias: refused there, not
    only above it."""
    sc = paper_scenario(plant2, horizon_s=0.01)
    with pytest.raises(ValueError, match=r"mode_freqs_hz must be below the Nyquist frequency, 500 Hz"):
        jf.rollout(plant2, open_loop(), OpenLoopParams(), sc, output="metrics", mode_freqs_hz=[13.3, 500.0])
    m = jf.rollout(plant2, open_loop(), OpenLoopParams(), sc, output="metrics", mode_freqs_hz=[13.3, np.nextafter(500.0, 0.0)])
    assert m.modal_energy.shape == (2,)


@pytest.mark.parametrize("name", ["Bd", "Ed", "C", "Cz"])
def test_plant_matrices_of_another_shape_are_refused_by_name(plant2, name):
    sc = paper_scenario(plant2, horizon_s=0.01)
    matrix = getattr(plant2, name)
    bad = plant2._replace(**{name: jnp.concatenate([matrix, matrix], axis=1)})
    with pytest.raises(ValueError, match=rf"plant\.{name} must have shape \({matrix.shape[0]}, {matrix.shape[1]}\) to match Ad \(6, 6\); got \({matrix.shape[0]}, {2 * matrix.shape[1]}\)"):
        jf.rollout(bad, open_loop(), OpenLoopParams(), sc, output="metrics")


def test_a_sample_time_a_tenth_of_a_percent_off_is_another_dt():
    """Only float32 round-off (1e-6 relative) counts as the same sample time: a plant at
    1.001 ms is refused by a 1 ms controller (eagerly by name, under jit by a diverged run),
    and two controllers 0.1 % apart are not combined."""
    near = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1.001e-3, "rk4")
    sc = paper_scenario(near, horizon_s=0.01)
    with pytest.raises(ValueError, match=r"controller was built for dt = 0.001 s but the plant is sampled at dt = 0.001001 s"):
        jf.rollout(near, dfs(dt=1e-3), DFSParams(55.0, 0.005), sc)
    simulate = jax.jit(jf.rollout, static_argnums=1, static_argnames="output")
    assert bool(simulate(near, dfs(dt=1e-3), DFSParams(55.0, 0.005), sc, output="metrics").diverged)
    with pytest.raises(ValueError, match=r"built for dt = 0.001 s and dt = 0.001001 s"):
        combine(dfs(dt=1e-3), dfs(dt=1.001e-3))


def test_a_scenario_that_is_not_a_scenario_of_finite_arrays_is_refused_by_name(plant2):
    """rollout read scenario.x0 without a look at what it was given: None or a bare tuple failed
    with an AttributeError, a Python list as x0 too; a concrete NaN or inf in x0, force or
    noise ran silently to a NaN trajectory; a string of frequencies failed in JAX's TypeError."""
    sc = paper_scenario(plant2, horizon_s=0.01)
    run = lambda s, **kw: jf.rollout(plant2, dfs(), DFSParams(55.0, 0.005), s, **kw)  # noqa: E731
    for bad in (None, (sc.x0, sc.force, sc.noise)):
        with pytest.raises(ValueError, match=r"scenario must be a Scenario \(build one with paper_scenario\(...\), .*; got (NoneType|tuple)"):
            run(bad)
    with pytest.raises(ValueError, match=r"scenario.x0 must be an array in the plant's dtype .*; got list"):
        run(sc._replace(x0=[0.0, 1e-3, 0.0, 0.0, 1e-5, 0.0]))
    for name, bad in (("x0", sc.x0.at[1].set(jnp.nan)), ("force", sc.force.at[3, 0].set(jnp.inf)), ("noise", sc.noise.at[0, 1].set(jnp.nan))):
        with pytest.raises(ValueError, match=rf"scenario.{name} must be finite; got inf or NaN"):
            run(sc._replace(**{name: bad}))
    with pytest.raises(ValueError, match=r"mode_freqs_hz must be a real number or an array of real numbers; got '13'"):
        run(sc, output="metrics", mode_freqs_hz="13")
    # traced scenarios are not checked: a NaN member of a batch reports itself diverged
    batch = jax.tree.map(lambda a: jnp.stack([a, a]), sc)._replace(plant=None)
    batch = batch._replace(x0=batch.x0.at[1, 1].set(jnp.nan))
    m = jax.vmap(lambda s: run(s, output="metrics"))(batch)
    assert m.diverged.tolist() == [False, True]


def test_a_zero_frequency_is_a_mode_frequency_and_an_empty_horizon_is_refused(plant2):
    """mode_freqs_hz accepts 0 Hz, as documented (>= 0): its modal energy is the squared
    Hann-windowed sum of the tip deflection, from the trajectory in NumPy. A scenario of no
    samples is refused by name (it failed in JAX's indexing of the empty noise)."""
    steps = 120
    sc = Scenario(paper_scenario(plant2).x0, jnp.zeros((steps, 1)).at[3:8, 0].set(0.2), jnp.zeros((steps, 2)))
    controller, params = dfs(), DFSParams(55.0, 0.005)
    m = jf.rollout(plant2, controller, params, sc, output="metrics", mode_freqs_hz=[0.0, 13.3])
    tip = np.asarray(jf.rollout(plant2, controller, params, sc).z[:, 1])
    hann = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(steps) / steps)
    t = np.arange(steps) * 1e-3
    expected = [abs(np.sum(hann * tip * np.exp(-2j * np.pi * f * t)) * 1e-3) ** 2 for f in (0.0, 13.3)]
    np.testing.assert_allclose(np.asarray(m.modal_energy), expected, rtol=1e-9)
    assert expected[0] > 0
    with pytest.raises(ValueError, match=r"scenario.force must have shape \(T, 1\) with T >= 1 \(one scenario\); got \(0, 1\)"):
        jf.rollout(plant2, controller, params, Scenario(sc.x0, jnp.zeros((0, 1)), jnp.zeros((0, 2))))


def test_parameters_narrower_than_the_plant_run_as_their_float64_values(plant2):
    """Only parameters wider than the plant are refused: float32 gains in a float64 loop
    promote, and give the run of the same values held in float64."""
    sc = paper_scenario(plant2, horizon_s=0.05)
    params32 = fuzzy_params(dtype=jnp.float32)
    run = lambda p: jf.rollout(plant2, fuzzy(), p, sc, output="metrics")  # noqa: E731
    tree_allclose(run(params32), run(jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), params32)), rtol=1e-12, atol=0)
    assert run(params32).tip_ise.dtype == jnp.float64


def test_an_unrolled_loop_computes_the_same_run(plant2):
    """``unroll`` changes how many samples one compiled loop iteration takes, not the run:
    trajectories and metrics agree with the plain loop (float64), also when the horizon is
    no multiple of it (lax.scan runs the remainder)."""
    controller, params = by_name("dfs", dt=1e-3)  # a carried ring buffer (the fuzzy surface unrolled is slow to compile)
    base = paper_scenario(plant2, horizon_s=0.05)  # 50 samples
    x0 = base.x0[None] + jnp.outer(jnp.arange(4.0), jnp.full(base.x0.shape, 1e-4))
    batch = Scenario(x0, base.force, base.noise)
    freqs = jnp.array([3.0, 20.0])
    for output in ("trajectory", "metrics"):
        plain = jf.rollout(plant2, controller, params, batch, output=output, **({"mode_freqs_hz": freqs} if output == "metrics" else {}))
        unrolled = jf.rollout(plant2, controller, params, batch, output=output, unroll=3, **({"mode_freqs_hz": freqs} if output == "metrics" else {}))
        tree_allclose(unrolled, plain, rtol=1e-12, atol=1e-18)
        jaxpr = jax.make_jaxpr(lambda p: jf.rollout(plant2, controller, p, batch, output=output, unroll=3))(params)
        assert [e.params["unroll"] for e in jaxpr.eqns if e.primitive.name == "scan"] == [3]  # reaches the loop


@pytest.mark.parametrize("unroll", [0, -2, 1.5, True, "8", None, 65, 10**5])
def test_a_bad_unroll_is_refused_by_name(plant2, unroll):
    """65 and up too: 10^5 never finished compiling (montecarlo's cap, now rollout's)."""
    with pytest.raises(ValueError, match=rf"unroll must be an integer in \[1, 64\]; got {re.escape(repr(unroll))}"):
        jf.rollout(plant2, open_loop(), OpenLoopParams(), paper_scenario(plant2, horizon_s=0.01), unroll=unroll)


def test_a_users_controller_is_told_what_its_step_returned_wrong(plant2):
    """A state that changes shape failed in lax.scan naming carry[1]; an int torque ran with a
    gradient of 0; a scalar torque of a one-scenario controller on a batch was told to be
    (1, B), which rollout builds itself by mapping it."""
    sc = paper_scenario(plant2, horizon_s=0.01)
    growing = Controller(lambda p, y0: jnp.zeros((1,), y0.dtype), lambda p, s, y: (jnp.concatenate([s, s]), -s[:1]), lambda p: None)
    with pytest.raises(ValueError, match=re.escape("the controller's step must return a state of the shapes and dtypes it was given (the loop carries it): float64[2] became float64[4]")):
        jf.rollout(plant2, growing, None, sc)
    counting = Controller(lambda p, y0: (), lambda p, s, y: (s, jnp.zeros((1,), jnp.int32)), lambda p: None)
    with pytest.raises(ValueError, match=r"the controller's step must return the torque u as floats, in the plant's dtype float64; got int32"):
        jf.rollout(plant2, counting, None, sc)
    scalar = Controller(lambda p, y0: (), lambda p, s, y: (s, -y[0]), lambda p: None)
    batch = sc._replace(x0=jnp.stack([sc.x0, 2 * sc.x0]))
    with pytest.raises(ValueError, match=re.escape("must return the torque u with shape (1,) for one scenario (N*m; rollout maps it over the batch of 2); got shape () per scenario")):
        jf.rollout(plant2, scalar, None, batch)


def test_controllers_whose_init_state_differs_from_their_steps_still_run(plant2):
    """The state check compares what the loop needs, a step's state with the next step's: an
    init that returns a list where step returns a tuple, a Python int counter that step makes
    int32, or a batched controller's scalar that step broadcasts, all ran before it."""
    sc = paper_scenario(plant2, horizon_s=0.01)
    as_list = Controller(lambda p, y0: [jnp.zeros(1)], lambda p, s, y: ((s[0] + 1.0,), -0.0 * y[:1]), lambda p: None)
    counter = Controller(lambda p, y0: 0, lambda p, s, y: (jnp.asarray(s, jnp.int32) + 1, -0.0 * y[:1]), lambda p: None)
    broadcast = Controller(lambda p, y0: 0.0, lambda p, s, y: (jnp.zeros(y.shape[1:]) + s, -0.0 * y[:1]), lambda p: None, batched=True)
    batch = sc._replace(x0=jnp.stack([sc.x0, 2 * sc.x0]))
    for controller, scenario in ((as_list, sc), (counter, sc), (broadcast, batch)):
        assert np.all(np.isfinite(np.asarray(jf.rollout(plant2, controller, None, scenario).x)))


# -- what a trajectory records, sample by sample (audit 14: a late y or a swapped noise channel passed) --


def _noisy_scenario(plant, steps=60, seed=1):
    """One of ``_batch_of_scenarios``: a random force and distinct noise on each channel and sample."""
    return jax.tree.map(lambda a: a[0], _batch_of_scenarios(plant, 1, steps, seed))


def test_a_trajectory_records_y_and_z_of_the_same_sample_as_x(plant2):
    """``y[k] = C x[k] + noise[k]`` and ``z[k] = Cz x[k]``, channel by channel."""
    sc = _noisy_scenario(plant2)
    traj = jf.rollout(plant2, pd(), PDParams(20.0, 0.5), sc)
    np.testing.assert_allclose(traj.y, np.asarray(traj.x) @ np.asarray(plant2.C).T + np.asarray(sc.noise), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(traj.z, np.asarray(traj.x) @ np.asarray(plant2.Cz).T, rtol=1e-12, atol=1e-16)


def test_pd_loop_matches_a_numpy_loop_that_reads_both_channels(plant2):
    """The DFS reference reads only y[0]; PD, ``u = -(kp y0 + kd y1)``, reads the velocity
    channel with its own noise too."""
    sc = _noisy_scenario(plant2)
    kp, kd = 20.0, 0.5
    Ad, Bd, Ed, C = (np.asarray(a) for a in (plant2.Ad, plant2.Bd, plant2.Ed, plant2.C))
    x, force, noise = np.asarray(sc.x0).copy(), np.asarray(sc.force), np.asarray(sc.noise)
    us = []
    for k in range(force.shape[0]):
        y = C @ x + noise[k]
        us.append(-(kp * y[0] + kd * y[1]))
        x = Ad @ x + Bd[:, 0] * us[-1] + Ed[:, 0] * force[k, 0]
    np.testing.assert_allclose(jf.rollout(plant2, pd(), PDParams(kp, kd), sc).u[:, 0], us, rtol=1e-9, atol=1e-14)


def _plants_at(*dts):
    plants = [jf.discretize(jf.make_plant(jf.BeamParams(), 2), dt, "zoh") for dt in dts]
    return jax.tree.map(lambda *a: jnp.stack(a), *plants)


def test_a_batch_of_plants_keeps_each_plants_sample_time():
    """Plants at 1 ms and 2 ms: each scenario's times step by its own dt, and a mode frequency
    must be below the slower plant's Nyquist frequency (250 Hz), not the faster one's."""
    plants, steps = _plants_at(1e-3, 2e-3), 5
    sc = Scenario(jnp.zeros((2, 6)), jnp.zeros((steps, 1)), jnp.zeros((steps, 2)))
    traj = jf.rollout(plants, open_loop(), OpenLoopParams(), sc)
    np.testing.assert_allclose(traj.t, [np.arange(steps) * 1e-3, np.arange(steps) * 2e-3], rtol=1e-12)
    with pytest.raises(ValueError, match=r"mode_freqs_hz must be below the Nyquist frequency, 250 Hz"):
        jf.rollout(plants, open_loop(), OpenLoopParams(), sc, output="metrics", mode_freqs_hz=[300.0])


def test_one_scenario_with_a_perturbation_runs_on_the_plant_it_is_given(plant2):
    """As documented: the perturbation is for ``scenarios.scenario_plant``; only a batch on one
    shared plant is refused, and one scenario runs on the plant passed."""
    sc = paper_scenario(plant2, horizon_s=0.01)
    perturbed = sc._replace(plant=PlantPerturbation(*(jnp.asarray(v) for v in (1.1, 1.0, 1.0, 0.0))))
    np.testing.assert_array_equal(jf.rollout(plant2, open_loop(), OpenLoopParams(), perturbed).x, jf.rollout(plant2, open_loop(), OpenLoopParams(), sc).x)


def test_a_non_square_Ad_and_numpy_scenarios(plant2):
    """A [5, 6] Ad is refused by name (not NumPy's matmul error); a scenario of NumPy arrays runs as
    its jnp twin."""
    with pytest.raises(ValueError, match=r"Ad must be square"):
        jf.rollout(plant2._replace(Ad=plant2.Ad[:5]), open_loop(), OpenLoopParams(), paper_scenario(plant2, horizon_s=0.01))
    sc = _noisy_scenario(plant2, steps=20)
    as_numpy = Scenario(*(np.asarray(a) for a in sc[:3]))
    np.testing.assert_array_equal(jf.rollout(plant2, open_loop(), OpenLoopParams(), as_numpy).x, jf.rollout(plant2, open_loop(), OpenLoopParams(), sc).x)


def test_a_users_one_scenario_controller_with_a_vector_state_keeps_each_scenarios_state(plant2):
    """A controller written for one scenario, with a 3-slot delay line as its state, on a batch
    of 3 (the state's length equals the batch: a transposed state would run without error):
    each member equals its own one-scenario rollout."""
    own = Controller(lambda p, y0: jnp.full((3,), y0[0]), lambda p, s, y: (jnp.concatenate([s[1:], y[:1]]), -p * (y[:1] - s[:1])), lambda p: None)
    x0 = np.tile(np.asarray(paper_scenario(plant2).x0), (3, 1))
    x0[:, 0] = [0.0, 0.05, -0.1]  # distinct hub angles: distinct delay lines
    force, noise = jnp.zeros((30, 1)), jnp.zeros((30, 2))
    batch = jf.rollout(plant2, own, 40.0, Scenario(jnp.asarray(x0), force, noise))
    for i in range(3):
        np.testing.assert_allclose(batch.u[i], jf.rollout(plant2, own, 40.0, Scenario(jnp.asarray(x0[i]), force, noise)).u, rtol=1e-12, atol=1e-15)
