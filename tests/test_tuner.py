"""The tuner: objectives against NumPy, the DFS loop matrix against a rollout, gradients,
compile-once, resume equals an uninterrupted run, held-out improvement, and bad input."""

import dataclasses
import math
import os
import json
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflex as jf
from jaxflex.controllers import DFSParams, dfs
from jaxflex.rollout import RunMetrics
from jaxflex.scenarios import ScenarioSpec, sample_scenarios
from tests.helpers import tree_allclose
from jaxflex.analysis import stability
from tuning import objectives
from tuning.objectives import ObjectiveSpec
from tuning.run import FIGURES
from tuning.tuner import CHECKPOINT, Problem, TuneConfig, recorded_steps, summarize, tune

RTOL_FD = 1e-5  # central differences, float64

SMALL = dict(n_scenarios=12, n_heldout=8, scenarios=ScenarioSpec(horizon_s=0.3, impulse_max_n=0.3))
# The batches of the tuning runs. Compilation, not the steps, is what a run costs (a step on
# these batches takes milliseconds), and every run builds its own jitted functions; the runs
# below share this one configuration (and so, through the session's compilation cache in
# conftest.py, their compiled programs) with the held-out improvement test.
SHARED = dict(n_scenarios=24, n_heldout=12, scenarios=ScenarioSpec(horizon_s=0.4, impulse_max_n=0.3, youngs_modulus_rel=0.1))
TINY = dict(n_scenarios=6, n_heldout=4, scenarios=ScenarioSpec(horizon_s=0.2, impulse_max_n=0.3))  # seconds per run, for checks of bookkeeping


def script_heldout(monkeypatch, values) -> list:
    """Make tune's held-out objective return ``values`` in turn (the training batch is left as
    it is); the Problems made are listed in the list returned."""
    import tuning.tuner

    script, made = iter(values), []

    class Scripted(tuning.tuner.Problem):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            evaluate = self.evaluate
            self.evaluate = lambda raw, batch: (jnp.float32(next(script)), None) if batch is self.heldout else evaluate(raw, batch)
            made.append(self)

    monkeypatch.setattr(tuning.tuner, "Problem", Scripted)
    return made


class Sampled(Exception):
    """Raised where tune would sample its scenarios: what it says or refuses before is probed."""


def fake_checkpoint(monkeypatch, tmp_path, config, **meta) -> None:
    """A checkpoint of ``config``'s run holding only the metadata ``meta``, and a Problem that
    raises Sampled."""
    import tuning.tuner

    meta = json.dumps({"fingerprint": config.fingerprint(), **meta}).encode()
    np.savez(tmp_path / CHECKPOINT, meta=np.frombuffer(meta, dtype=np.uint8))

    def problem(*args):
        raise Sampled

    monkeypatch.setattr(tuning.tuner, "Problem", problem)


@pytest.fixture(scope="module")
def plant2():
    return jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")


def test_reductions_against_numpy():
    losses = jnp.asarray(np.random.default_rng(0).uniform(size=40))
    l = np.asarray(losses)
    assert float(objectives.reduce_losses(losses, ObjectiveSpec(reduction="mean"))) == pytest.approx(l.mean(), rel=1e-12)
    worst4 = np.sort(l)[-4:].mean()
    assert float(objectives.reduce_losses(losses, ObjectiveSpec(reduction="cvar", cvar_level=0.9))) == pytest.approx(worst4, rel=1e-12)
    smooth = float(objectives.reduce_losses(losses, ObjectiveSpec(reduction="worst", worst_temperature=0.01)))
    assert l.max() - 0.01 * np.log(40) <= smooth <= l.max() + 1e-12
    # the closed form, written in NumPy: T (log sum exp(l / T) - log B)
    assert smooth == pytest.approx(0.01 * (np.log(np.sum(np.exp((l - l.max()) / 0.01))) + l.max() / 0.01 - np.log(40)), rel=1e-12)
    for batch in (1, 2, 40):  # equal losses score exactly their value (the - T log B), as the mean does
        equal = jnp.full(batch, 0.7)
        assert float(objectives.reduce_losses(equal, ObjectiveSpec(reduction="worst", worst_temperature=0.05))) == pytest.approx(0.7, rel=1e-12)
    # Levels whose tail (1 - level) * B is a whole number average exactly that many losses,
    # although the product rounds above it in floating point ((1 - 0.7) * 10 = 3.0000000000000004).
    # a fractional tail is rounded up: 0.1 of 15 averages the worst 2
    values = jnp.asarray([5.0, 1.0, 9.0, 2.0, 7.0, 3.0, 0.0, 4.0, 6.0, 8.0, 1.5, 2.5, 3.5, 4.5, 5.5])
    assert float(objectives.reduce_losses(values, ObjectiveSpec(reduction="cvar", cvar_level=0.9))) == pytest.approx(8.5, rel=1e-12)
    for level, batch in ((0.7, 10), (0.95, 100), (0.99, 100), (0.7, 1000)):
        tail = round((1 - level) * batch)
        values = jnp.arange(float(batch))
        expected = np.arange(batch)[-tail:].mean()
        got = float(objectives.reduce_losses(values, ObjectiveSpec(reduction="cvar", cvar_level=level)))
        assert got == pytest.approx(expected, rel=1e-12), (level, batch)


def test_scenario_losses_weigh_normalised_terms_and_leave_out_those_weighted_0():
    """sum of weight x term / scale over the weighted terms; a term weighted 0 is left out, not
    multiplied by 0, so a NaN or inf there (a term the tuner was not asked for) does not reach
    the loss or its gradient."""
    terms = objectives.Terms(jnp.asarray([2.0, 4.0]), jnp.asarray([1.0, 3.0]), jnp.asarray([5.0, 6.0]), jnp.asarray([jnp.nan, jnp.inf]))
    scales = objectives.Terms(*(jnp.asarray(v) for v in (2.0, 0.5, 10.0, 1.0)))
    spec = ObjectiveSpec(tip_ise=1.0, hub_ise=0.5, effort=2.0, vibration=0.0)
    expected = 1.0 * np.array([2.0, 4.0]) / 2.0 + 0.5 * np.array([1.0, 3.0]) / 0.5 + 2.0 * np.array([5.0, 6.0]) / 10.0
    np.testing.assert_allclose(objectives.scenario_losses(terms, scales, spec), expected, rtol=1e-12)


@pytest.mark.parametrize("spec", [ObjectiveSpec(reduction="cvar", cvar_level=0.7), ObjectiveSpec(reduction="worst", worst_temperature=0.05), ObjectiveSpec(reduction="mean")])
def test_reduction_gradients_match_central_differences(spec):
    """The tuner's objective was checked against central differences with the mean reduction
    only: the CVaR (top-k) and smooth worst case (logsumexp) gradients w.r.t. every loss of a
    batch, against central differences of NumPy's definitions (distinct losses, so the CVaR's
    tail is strict). h = 1e-6: the reductions are piecewise linear or analytic here."""
    l = np.random.default_rng(1).uniform(size=10)

    def reference(v):
        if spec.reduction == "cvar":
            return np.sort(v)[-3:].mean()  # ceil(0.3 * 10) = 3 worst
        if spec.reduction == "worst":
            t = spec.worst_temperature
            return t * (np.log(np.sum(np.exp((v - v.max()) / t))) + v.max() / t - np.log(v.size))
        return v.mean()

    g = np.asarray(jax.grad(lambda v: objectives.reduce_losses(v, spec))(jnp.asarray(l)))
    h = 1e-6
    fd = np.array([(reference(l + h * e) - reference(l - h * e)) / (2 * h) for e in np.eye(l.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    assert np.count_nonzero(g) == (3 if spec.reduction == "cvar" else l.size)


def test_fractional_loop_matrix_reproduces_rollout_and_deflation(plant2):
    """The stability penalty's loop map with a linearly interpolated delay is the rollout."""
    capacity, tau = 16, 0.0063
    loop = np.asarray(stability._loop_matrix(plant2, 55.0, tau / 1e-3, capacity))
    sc = jf.paper_scenario(plant2, horizon_s=0.2)
    traj = jf.rollout(plant2, dfs(1e-3, capacity, "linear"), DFSParams(55.0, tau), sc)
    z = np.concatenate([np.asarray(sc.x0), np.full(capacity, float(sc.x0[0]))])
    xs = np.asarray(traj.x)
    for k in range(199):
        z = loop @ z
        np.testing.assert_allclose(z[:6], xs[k + 1], rtol=1e-10, atol=1e-16)
    eig_full = np.linalg.eigvals(loop)
    reduced = stability.deflated_loop_matrix(plant2, 55.0, tau / 1e-3, capacity)
    eig_red = np.linalg.eigvals(np.asarray(reduced))
    # the deflated spectrum is the full one with exactly one eigenvalue 1 removed
    i = np.argmin(np.abs(eig_full - 1))
    assert abs(eig_full[i] - 1) < 1e-9
    np.testing.assert_allclose(np.sort_complex(np.delete(eig_full, i)), np.sort_complex(eig_red), atol=1e-7)
    rho = np.abs(eig_red).max()
    assert float(objectives.log_spectral_radius(reduced)) == pytest.approx(np.log(rho), rel=1e-12)


@pytest.mark.parametrize("k, delay_steps", [(200.0, 20.3), (150.0, 12.4), (300.0, 25.5), (55.0, 5.3)])
def test_log_spectral_radius_gradient_matches_fd(plant2, k, delay_steps):
    """The stability penalty's derivative against central differences of NumPy's eigenvalues,
    in k and in the fractional delay. The first three loops have a complex dominant pair (where
    Gelfand's formula, the earlier estimate, had derivatives of the wrong sign); the last a
    real one. The delay line's unused tail gives defective zero eigenvalues throughout."""
    capacity = 32

    def exact(k, d):
        return np.log(np.abs(np.linalg.eigvals(np.asarray(stability.deflated_loop_matrix(plant2, k, d, capacity)))).max())

    f = lambda k, d: objectives.log_spectral_radius(stability.deflated_loop_matrix(plant2, k, d, capacity))
    g_k, g_d = jax.grad(f, argnums=(0, 1))(jnp.asarray(k), jnp.asarray(delay_steps))
    h_k, h_d = 1e-5 * k, 1e-5
    fd_k = (exact(k + h_k, delay_steps) - exact(k - h_k, delay_steps)) / (2 * h_k)
    fd_d = (exact(k, delay_steps + h_d) - exact(k, delay_steps - h_d)) / (2 * h_d)
    assert float(g_k) == pytest.approx(fd_k, rel=RTOL_FD)
    assert float(g_d) == pytest.approx(fd_d, rel=RTOL_FD)


@pytest.mark.parametrize("delay_steps", [3.0, 5.0])
def test_log_spectral_radius_gradient_at_a_whole_delay(plant2, delay_steps):
    """At a whole number of samples the interpolated delay has a kink in d, and the derivative
    is the one from above (the rollout's convention). It once lost the term of slot d + 1, which
    was left out of the live history there, and had the wrong sign (+0.0059 against -0.0024 at
    d = 5, k = 55, the tuner's usual start after the to_raw round trip)."""
    capacity = 8

    def exact(d):
        return np.log(np.abs(np.linalg.eigvals(np.asarray(stability.deflated_loop_matrix(plant2, 55.0, d, capacity)))).max())

    g_d = jax.grad(lambda d: objectives.log_spectral_radius(stability.deflated_loop_matrix(plant2, 55.0, d, capacity)))(jnp.asarray(delay_steps))
    h = 1e-6
    from_above = (exact(delay_steps + 2 * h) - exact(delay_steps + h)) / h  # one-sided, clear of the kink
    assert float(g_d) == pytest.approx(from_above, rel=1e-4)


def test_log_spectral_radius_derivative_where_two_modes_tie_in_modulus():
    """Eigenvalues 0.9 and -0.9: the derivative is that of one of the two, d log|lam_i| =
    Re(w_i dM v_i / lam_i) from NumPy's eigenvectors (v_i, and w_i the rows of their inverse).
    A left eigenvector taken by modulus alone can belong to the other one, orthogonal to v_i:
    the derivative was then 1e16 or inf."""
    rng = np.random.default_rng(0)
    for _ in range(10):
        basis = rng.standard_normal((4, 4))
        matrix = basis @ np.diag([0.9, -0.9, 0.3, -0.2]) @ np.linalg.inv(basis)
        direction = rng.standard_normal((4, 4))
        _, tangent = jax.jvp(objectives.log_spectral_radius, (jnp.asarray(matrix),), (jnp.asarray(direction),))
        values, right = np.linalg.eig(matrix)
        left = np.linalg.inv(right)
        tied = [np.real(left[i] @ direction @ right[:, i] / values[i]) for i in range(4) if abs(abs(values[i]) - 0.9) < 1e-9]
        assert len(tied) == 2 and any(float(tangent) == pytest.approx(d, rel=1e-8) for d in tied)


def test_objective_terms_read_their_own_metrics():
    """Each weight of [objective] acts on its own metric (distinct values, so a swap shows),
    and the vibration term sums the energy of every mode."""
    m = RunMetrics(*(jnp.asarray(v) for v in (0.1, 2.0, 0.3, 5.0, 7.0, 0.0, 0.2, 1.0, False)), jnp.asarray([11.0, 13.0]))
    terms = objectives.terms_from_metrics(m)
    assert [float(t) for t in terms] == [2.0, 5.0, 7.0, 24.0]
    assert objectives.TERMS == objectives.Terms._fields == ("tip_ise", "hub_ise", "effort", "vibration")


def test_vibration_term_is_measured_at_each_scenarios_own_modes():
    """With plant uncertainty, a scenario's vibration term is the tip's energy at the modes of
    the arm it ran on, as jaxflex montecarlo measures it. It was measured at the nominal arm's
    modes, beside the peaks of a stiffer or heavier drawn arm."""
    from jaxflex import beam
    from jaxflex.rollout import rollout
    from jaxflex.scenarios import perturbed_params

    spec = ScenarioSpec(horizon_s=0.5, youngs_modulus_rel=0.3, payload_max_kg=0.1)
    cfg = TuneConfig(controller="dfs", n_scenarios=4, n_heldout=1, scenarios=spec, objective=ObjectiveSpec(tip_ise=0.0, vibration=1.0))
    problem = Problem(cfg)
    params = problem.tc.to_physical(problem.paper_raw)
    got = np.asarray(jax.jit(problem._terms)(problem.paper_raw, problem.train).vibration)
    nominal_hz = beam.natural_frequencies_hz(cfg.beam, 2)
    moved = 0
    for i in range(cfg.n_scenarios):
        scenario = jax.tree.map(lambda a: a[i], problem.train)
        arm = perturbed_params(cfg.beam, scenario.plant)
        plant = jf.discretize(jf.make_plant(arm, 2), spec.dt, cfg.method)
        at = {"own": beam.natural_frequencies_hz(arm, 2), "nominal": nominal_hz}
        energy = {k: float(jnp.sum(rollout(plant, problem.tc.controller, params, scenario, output="metrics", mode_freqs_hz=f).modal_energy)) for k, f in at.items()}
        assert got[i] == pytest.approx(energy["own"], rel=1e-4)
        moved += abs(energy["nominal"] / energy["own"] - 1) > 0.05
    assert moved >= 2  # the draws move the modes enough for the nominal ones to miss the peaks


def test_stability_penalty_is_in_decay_rate_per_second():
    """The penalty compares the slowest mode's decay rate -log(radius) / dt (1/s) with
    min_decay_rate: half the minimum costs weight * (min / 2)^2, twice the minimum nothing,
    whatever the sample time."""
    spec = ObjectiveSpec(stability_weight=3.0, min_decay_rate=2.0)
    for dt in (1e-3, 1e-4):
        assert float(objectives.stability_penalty(jnp.asarray(-dt * 1.0), dt, spec)) == pytest.approx(3.0 * 1.0**2, rel=1e-12)
        assert float(objectives.stability_penalty(jnp.asarray(-dt * 4.0), dt, spec)) == 0.0
        # a deficit other than 1 shows the square: a loop that does not decay at all costs 3 * 2^2
        assert float(objectives.stability_penalty(jnp.asarray(0.0), dt, spec)) == pytest.approx(12.0, rel=1e-12)
    # the paper's loop (k = 55, tau = 5 ms) decays at about 9 /s: the default does not penalise it
    plant = jf.discretize(jf.make_plant(n_modes=2), 1e-3, "zoh")
    log_r = float(np.log(stability.spectral_radius(plant, 55.0, 5)))
    assert 5.0 < -log_r / 1e-3 < 20.0
    assert float(objectives.stability_penalty(jnp.asarray(log_r), 1e-3, ObjectiveSpec())) == 0.0


def test_tuner_objective_gradient_matches_fd():
    cfg = TuneConfig(controller="dfs", **SMALL, objective=ObjectiveSpec(tip_ise=1.0, hub_ise=0.3, effort=0.1, vibration=0.5, min_decay_rate=50.0))
    problem = Problem(cfg)
    raw = problem.tc.to_raw(DFSParams(80.0, 0.0043))
    # One compilation: the gradient, and the objective values for the differences (the forward
    # pass of the same program).
    vg = jax.jit(jax.value_and_grad(lambda r: problem._objective(r, problem.train), has_aux=True))
    (_, aux), grads = vg(raw)
    for name in ("log_k", "tau_z"):
        h = 1e-5
        fd = (float(vg({**raw, name: raw[name] + h})[0][0]) - float(vg({**raw, name: raw[name] - h})[0][0])) / (2 * h)
        np.testing.assert_allclose(float(grads[name]), fd, rtol=RTOL_FD)
    assert float(aux["penalty"]) > 0  # the penalty is active here


# The objective's other controllers and delay reads, each through the tuner's raw parameters
# (the test above covers DFS with the linear read and an active stability penalty). The faithful
# fuzzy controller (the tuner's default temperature; the smooth mode's gradients are checked in
# test_fuzzy.py, and its tuner program compiles ~3x slower) and fractional delays, away from the
# kinks of the buffer reads. One program per case (its value gives the differences).
H_RAW = 1e-5  # central-difference step in the raw (log, logit) coordinates, i.e. relative
# Error of the difference, relative to the gradient: truncation ~h^2 L''' / (6 L') < 1e-10
# (measured: 2e-7 at h = 1e-3, falling as h^2), round-off ~eps |L| / (h |dL|) ~ 2e-9 for the
# smallest component here (log_k1, |dL| ~ 0.02 against L ~ 2); measured at most 3.4e-9.
RTOL_FD_RAW = 1e-6


@pytest.mark.parametrize(
    "options",
    [
        dict(controller="fuzzy", reduction="cvar"),
        dict(controller="dfs+fuzzy", delay="cubic", reduction="mean"),
        dict(controller="dfs", delay="pade", reduction="worst"),
    ],
    ids=["fuzzy", "dfs+fuzzy-cubic", "dfs-pade"],
)
def test_tuner_objective_gradient_matches_fd_for_other_controllers_and_delays(options):
    """The gradient the optax loop takes (``Problem._objective`` w.r.t. every leaf of the raw
    parameters) against central differences of the same function, float64: the fuzzy gains
    alone (log_k1..3), DFS and fuzzy combined with the cubic buffer read (the pair of raw
    trees; tau_z through the Lagrange weights), and DFS with the Pade delay (tau_z through the
    filter sampled in ``init``). Each case also takes another batch reduction (CVaR, mean, smooth
    worst case) on all four terms. tau = 4.3 ms, 4.3 samples: the differences stay inside one
    sample interval (the cubic read has a kink at whole samples); the stability penalty is off
    (default min_decay_rate), so tau_z's gradient is that of the rollout alone. The faithful
    fuzzy surface has kinks too: at h = 1e-4 a difference already crosses one (dfs+fuzzy:
    log_k2 1.4e-4 off), at H_RAW none does along these runs."""
    options = dict(options)
    objective = ObjectiveSpec(tip_ise=1.0, hub_ise=0.3, effort=0.1, vibration=0.5, reduction=options.pop("reduction"), cvar_level=0.7)
    initial = {} if options["controller"] == "fuzzy" else {"tau_s": 0.0043}
    problem = Problem(TuneConfig(**options, **SMALL, objective=objective, initial=initial))
    raw = problem.initial_raw
    vg = jax.jit(jax.value_and_grad(lambda r: problem._objective(r, problem.train), has_aux=True))
    (_, aux), grads = vg(raw)
    if "penalty" in aux:
        assert float(aux["penalty"]) == 0.0
    assert problem.penalised == ("penalty" in aux)  # what loss.png's legend says the loss holds
    if options["controller"] == "dfs":  # with no weight the penalty is 0: the legend names none
        assert not Problem(TuneConfig(**options, **SMALL, objective=dataclasses.replace(objective, stability_weight=0.0), initial=initial)).penalised
    leaves, treedef = jax.tree_util.tree_flatten_with_path(raw)
    names, values = [jax.tree_util.keystr(path) for path, _ in leaves], [value for _, value in leaves]
    assert len(names) == {"fuzzy": 3, "dfs+fuzzy": 5, "dfs": 2}[options["controller"]]

    def loss(i, step):
        shifted = values[:i] + [values[i] + step] + values[i + 1:]
        return float(vg(jax.tree.unflatten(treedef, shifted))[0][0])

    mismatches = []
    for i, (name, g) in enumerate(zip(names, jax.tree.leaves(grads))):
        g, fd = float(g), (loss(i, H_RAW) - loss(i, -H_RAW)) / (2 * H_RAW)
        assert g != 0 and np.isfinite(g), name
        if not abs(g - fd) <= RTOL_FD_RAW * abs(fd):
            mismatches.append(f"{name}: grad {g!r}, central difference {fd!r} ({(g - fd) / fd:+.1e})")
    assert not mismatches, mismatches


def test_any_optax_optimizer_is_accepted(tmp_path):
    import optax

    state = tune(TuneConfig(controller="dfs", steps=3, eval_every=1, **SHARED), tmp_path, progress=False, optimizer=optax.sgd(1e-3, momentum=0.9))
    assert state["step"] == 3 and "trace" in type(state["opt_state"][1][0]).__name__.lower()


def test_second_train_step_does_not_retrace():
    problem = Problem(TuneConfig(controller="fuzzy", **SHARED))
    calls = []
    original = problem._objective
    problem._objective = lambda *a: calls.append(1) or original(*a)
    raw, opt = problem.initial_raw, problem.optimizer.init(problem.initial_raw)
    for _ in range(3):
        raw, opt, info = problem.train_step(raw, opt, problem.train)
    assert len(calls) == 1
    assert np.isfinite(float(info["loss"]))
    # the held-out scenarios are drawn apart from the training ones: no initial state in common
    train, heldout = np.asarray(problem.train.x0), np.asarray(problem.heldout.x0)
    assert not np.any(np.all(train[:, None, :] == heldout[None, :, :], axis=-1))


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    """``get(controller) -> (config, out_dir, state)``: an uninterrupted tuning run of SHARED,
    made once for the module (the held-out test and the resume test both use it)."""
    runs = {}

    def get(controller):
        if controller not in runs:
            config = TuneConfig(controller=controller, steps=30, eval_every=5, checkpoint_every=4, **SHARED)
            out_dir = tmp_path_factory.mktemp(f"tuned-{controller}")
            runs[controller] = (config, out_dir, tune(config, out_dir, progress=False))
        return runs[controller]

    return get


def test_resume_after_interrupt_equals_uninterrupted(tmp_path, tuned, monkeypatch):
    import tuning.tuner

    cfg, _, full = tuned("dfs")

    def interrupt(step):
        if step == 6:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        tune(cfg, tmp_path / "cut", progress=False, on_step=interrupt)
    with np.load(tmp_path / "cut" / CHECKPOINT) as data:
        assert json.loads(bytes(data["meta"]).decode())["step"] == 4  # lost at most one interval
    assert recorded_steps(tmp_path / "cut") == 30 and recorded_steps(tmp_path / "empty") is None  # the target a bare --resume goes on to
    with pytest.raises(ValueError, match=r"pass --resume \(resume=True\) to continue it, choose another --out \(out_dir\), or delete the folder to start over in it"):
        tune(cfg, tmp_path / "cut", progress=False)  # never overwrite a run silently
    # saved more often after the interruption: when a run is saved is not what it computes
    resumed = tune(dataclasses.replace(cfg, checkpoint_every=3), tmp_path / "cut", resume=True, progress=False)
    assert resumed["step"] == full["step"] == 30
    # validated at steps 0, eval_every, 2 eval_every, ... and at the final point, after the last update
    assert [h["step"] for h in full["history"] if h.get("val_objective") is not None] == [0, 5, 10, 15, 20, 25, 30]
    tree_allclose(resumed["raw"], full["raw"], rtol=0)
    tree_allclose(resumed["best_raw"], full["best_raw"], rtol=0)
    assert [h["loss"] for h in resumed["history"]] == [h["loss"] for h in full["history"]]
    with pytest.raises(ValueError, match=r"has taken 30 steps already; steps = 20 cannot undo them \(pass --steps 30 or more\)"):
        tune(dataclasses.replace(cfg, steps=20), tmp_path / "cut", resume=True, progress=False)
    again = tune(cfg, tmp_path / "cut", resume=True, progress=False)  # a finished run resumed with its own steps: nothing to do
    assert again["step"] == 30 and len(again["history"]) == 31
    with pytest.raises(ValueError, match="--resume: no checkpoint at"):
        tune(cfg, tmp_path / "empty", resume=True, progress=False)
    with pytest.raises(ValueError, match=r"another configuration \(changed: seed: 0 -> 1;.*\): resume with the command that started it, its --config and options, and --resume$"):
        tune(dataclasses.replace(cfg, seed=1), tmp_path / "cut", resume=True, progress=False)
    # another controller has other arrays: the configuration is compared before they are read,
    # and before any scenario is sampled or compiled
    def no_problem(*args, **kwargs):
        raise AssertionError("Problem built before the checkpoint's configuration was checked")

    monkeypatch.setattr(tuning.tuner, "Problem", no_problem)
    with pytest.raises(ValueError, match=r"another configuration \(changed: controller: 'dfs' -> 'fuzzy';"):
        tune(dataclasses.replace(cfg, controller="fuzzy"), tmp_path / "cut", resume=True, progress=False)
    with pytest.raises(ValueError, match="pass --resume"):
        tune(cfg, tmp_path / "cut", progress=False)


def test_early_stop_after_patience_validations_without_improvement(tmp_path):
    """An optimizer that climbs the objective: the held-out value worsens at every validation
    (eval_every = 1), and with patience = 2 the run stops after the second one, at step 3."""
    import optax

    state = tune(TuneConfig(controller="dfs", steps=20, eval_every=1, patience=2, **SHARED), tmp_path, progress=False, optimizer=optax.sgd(-0.05))
    vals = [h["val_objective"] for h in state["history"]]
    assert state["stopped_early"] and state["step"] == 3 and state["best_step"] == 0
    assert vals[0] == state["best_val"] and len(vals) == 3  # row 0 holds the initial point's validation
    vals = vals[1:]
    assert vals[0] > state["best_val"] and vals[1] > state["best_val"]


def test_patience_counts_validations_in_a_row_and_the_penalty_reads_the_delay(tmp_path, monkeypatch):
    """Held-out values 5, 6, 4, 6, 6 with patience 2: the improvement at step 2 resets the
    count, so the run stops after the validation at step 4 (a plain reading of the rule)."""
    from jaxflex.analysis import stability

    made = script_heldout(monkeypatch, [5.0, 6.0, 4.0, 6.0, 6.0, 6.0])
    state = tune(TuneConfig(controller="dfs", steps=20, eval_every=1, patience=2, **SHARED), tmp_path, progress=False)
    best, bad, stop_at = math.inf, 0, None
    for step, val in enumerate([5.0, 6.0, 4.0, 6.0, 6.0]):
        best, bad = (val, 0) if val < best else (best, bad + 1)
        if bad >= 2:
            stop_at = step + 1
            break
    assert state["stopped_early"] and state["step"] == stop_at == 5 and state["best_step"] == 2
    # the stability penalty's radius is that of the loop at the delay asked for (5 samples)
    problem = made[0]
    expected = np.log(float(stability.spectral_radius(problem.nominal, 55.0, 5)))
    assert float(problem.dfs_log_radius(DFSParams(55.0, 0.005))) == pytest.approx(expected, rel=1e-5)


def test_a_tie_is_no_improvement(tmp_path, monkeypatch):
    """Held-out values 5, 5, 5 with patience 2: equal is not better, so the run stops after
    the validation at step 2 and keeps step 0 (counted as better, it never stopped)."""
    script_heldout(monkeypatch, [5.0, 5.0, 5.0, 5.0])
    state = tune(TuneConfig(controller="dfs", steps=20, eval_every=1, patience=2, **SHARED), tmp_path, progress=False)
    assert state["best_step"] == 0 and state["stopped_early"] and state["step"] == 3


def test_the_final_point_never_stops_early(tmp_path, monkeypatch):
    """Held-out values 5, 6, 7 over 2 updates with patience 2: the second bad validation is the
    run's final point, so it ends as finished, not stopped early."""
    script_heldout(monkeypatch, [5.0, 6.0, 7.0])
    state = tune(TuneConfig(controller="dfs", steps=2, eval_every=1, patience=2, **SHARED), tmp_path, progress=False)
    assert state["bad_evals"] == 2 and not state["stopped_early"] and state["step"] == 2


def test_the_kept_gains_are_those_validated_at_the_best_step(tmp_path):
    """An optimizer that climbs the objective keeps step 0: its parameters are the starting
    ones (not those after the last update), and summarize scores them, so 'after' equals
    'before' on both batches."""
    import optax

    state = tune(TuneConfig(controller="dfs", steps=20, eval_every=1, patience=2, **SHARED), tmp_path, progress=False, optimizer=optax.sgd(-0.05))
    assert state["best_step"] == 0 and state["step"] == 3
    tree_allclose(state["best_raw"], state["problem"].initial_raw, rtol=0)
    summary = summarize(state)
    assert summary["params"] == summary["initial_params"]
    for batch in ("train", "heldout"):
        assert summary["objective"][batch]["after"] == summary["objective"][batch]["before"]


def test_a_resume_keeps_the_count_of_validations_without_improvement(tmp_path, monkeypatch):
    """Interrupted after one bad validation (5, 6), the resumed run needs one more to stop,
    as the uninterrupted run did (5, 6, 7): the count is in the checkpoint, not restarted."""
    config = TuneConfig(controller="dfs", steps=20, eval_every=1, patience=2, checkpoint_every=1, **SHARED)
    script_heldout(monkeypatch, [5.0, 6.0, 7.0, 7.0, 7.0])
    full = tune(config, tmp_path / "full", progress=False)
    assert full["stopped_early"] and full["step"] == 3

    def interrupt(step):
        if step == 2:
            raise KeyboardInterrupt

    script_heldout(monkeypatch, [5.0, 6.0])
    with pytest.raises(KeyboardInterrupt):
        tune(config, tmp_path / "cut", progress=False, on_step=interrupt)
    script_heldout(monkeypatch, [7.0, 7.0, 7.0])
    resumed = tune(config, tmp_path / "cut", resume=True, progress=False)
    for key in ("step", "best_step", "bad_evals", "stopped_early"):
        assert resumed[key] == full[key], key


def test_a_finished_run_resumed_stops_where_the_longer_run_would(tmp_path, monkeypatch):
    """Patience 1: a 1-step run ends on a worse final point (5, 6), which does not stop it; a
    resume to 5 steps counts that point and stops at once, as the 5-step run did at step 2."""
    config = TuneConfig(controller="dfs", steps=5, eval_every=1, patience=1, **SHARED)
    script_heldout(monkeypatch, [5.0, 6.0, 4.0, 4.0, 4.0, 4.0])
    full = tune(config, tmp_path / "full", progress=False)
    assert full["stopped_early"] and full["step"] == 2
    script_heldout(monkeypatch, [5.0, 6.0])
    tune(dataclasses.replace(config, steps=1), tmp_path / "cut", progress=False)
    script_heldout(monkeypatch, [4.0, 4.0, 4.0, 4.0])
    resumed = tune(config, tmp_path / "cut", resume=True, progress=False)
    for key in ("step", "best_step", "bad_evals", "stopped_early"):
        assert resumed[key] == full[key], key


def test_the_final_point_is_scored_and_may_be_kept(tmp_path, monkeypatch):
    """Held-out values 5 (step 0) then 4 (the parameters after the last of 3 updates, off the
    eval_every schedule): the final point is kept. Resumed with more steps, that point becomes
    an ordinary row and the run goes on to its new final point, with each step once."""
    import tqdm.auto

    script_heldout(monkeypatch, [5.0, 4.0, 3.0, 2.0])

    class Bar:  # tqdm's calls, recorded: the bar opens after each process's first (compiling) step
        made = []

        def __init__(self, total, initial, **kwargs):
            self.total, self.initial, self.n, self.postfix = total, initial, initial, None
            Bar.made.append(self)

        def update(self, n):
            self.n += n

        def set_postfix(self, **kwargs):
            self.postfix = kwargs

        def close(self):
            pass

    monkeypatch.setattr(tqdm.auto, "tqdm", Bar)
    config = TuneConfig(controller="dfs", steps=3, eval_every=10, **SHARED)
    state = tune(config, tmp_path)
    assert [(h["step"], h.get("val_objective")) for h in state["history"]] == [(0, 5.0), (1, None), (2, None), (3, 4.0)]
    assert state["best_step"] == 3 and state["step"] == 3 and not state["stopped_early"]
    tree_allclose(state["best_raw"], state["raw"], rtol=0)
    longer = tune(dataclasses.replace(config, steps=5), tmp_path, resume=True)
    assert [(h["step"], h.get("val_objective")) for h in longer["history"]] == [(0, 5.0), (1, None), (2, None), (3, 4.0), (4, None), (5, 3.0)]
    assert longer["best_step"] == 5 and "grad_norm" in longer["history"][3]
    assert [(bar.total, bar.initial, bar.n) for bar in Bar.made] == [(3, 1, 3), (5, 4, 5)]
    # each bar ends on its final point's scores (it showed the step before's: best_val 5, a
    # training loss of other parameters, beside a summary that said 4)
    for bar, run in zip(Bar.made, (state, longer)):
        assert bar.postfix == {"loss": f"{run['history'][-1]['loss']:.4g}", "best_val": f"{run['history'][-1]['val_objective']:.4g}"}


def test_a_finished_run_resumed_with_more_steps_equals_the_longer_run(tmp_path):
    """Validated at every update with patience 1: the 2-step run's final point (its best) is
    counted once, not again when the resumed run passes it (which stopped it at once)."""
    config = TuneConfig(controller="dfs", steps=4, eval_every=1, patience=1, **SHARED)
    full = tune(config, tmp_path / "full", progress=False)
    tune(dataclasses.replace(config, steps=2), tmp_path / "cut", progress=False)
    resumed = tune(config, tmp_path / "cut", resume=True, progress=False)
    for key in ("step", "best_step", "bad_evals", "stopped_early", "best_val"):
        assert resumed[key] == full[key], key
    assert [(h["step"], h["loss"], h.get("val_objective")) for h in resumed["history"]] == [(h["step"], h["loss"], h.get("val_objective")) for h in full["history"]]
    tree_allclose(resumed["best_raw"], full["best_raw"], rtol=0)


def test_a_final_point_with_a_non_finite_objective_is_not_kept(tmp_path, monkeypatch):
    """The final point is evaluated, not updated from, so its NaN cannot stop a run as an
    update's does: it is recorded, left unvalidated, and the best earlier point is kept."""
    import tuning.tuner

    class NaNAtTheEnd(tuning.tuner.Problem):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            evaluate = self.evaluate
            self.evaluate = lambda raw, batch: (jnp.nan, {"objective": jnp.nan}) if batch is self.train else evaluate(raw, batch)

    monkeypatch.setattr(tuning.tuner, "Problem", NaNAtTheEnd)
    state = tune(TuneConfig(controller="dfs", steps=3, eval_every=1, **SHARED), tmp_path, progress=False)
    last = state["history"][-1]
    assert last["step"] == 3 and math.isnan(last["loss"]) and "val_objective" not in last
    assert state["best_step"] < 3 and not state["stopped_early"]


@pytest.mark.parametrize("controller", ["dfs", "fuzzy"])
def test_tuning_lowers_heldout_objective(tuned, controller):
    cfg, out_dir, state = tuned(controller)
    summary = summarize(state)
    obj = summary["objective"]
    assert obj["train"]["before"] == pytest.approx(1.0, rel=1e-9)  # normalised by the paper's gains
    assert obj["heldout"]["after"] < 0.97 * obj["heldout"]["before"]
    assert obj["train"]["after"] < obj["train"]["before"]
    if controller == "dfs":
        assert summary["stability"]["stable"] and summary["stability"]["decay_rate_per_s"] > cfg.objective.min_decay_rate
    assert set(summary["params"]) == ({"k", "tau_s"} if controller == "dfs" else {"k1", "k2", "k3"})
    assert (out_dir / "history.csv").read_text().count("\n") == summary["steps_run"] + 2
    # Each history row is one point: row n holds the parameters after n updates (the initial
    # ones in row 0, the final ones in the last row) and the objectives there (the loss once
    # sat beside the next parameters).
    problem, rows, names = state["problem"], state["history"], list(summary["params"])
    assert [h["step"] for h in rows] == list(range(summary["steps_run"] + 1))
    assert "grad_norm" not in rows[-1] and all("grad_norm" in h for h in rows[:-1])  # no update from the final point
    assert [rows[-1][n] for n in names] == pytest.approx(list(problem.tc.named(problem.tc.to_physical(state["raw"])).values()), rel=1e-12)
    assert [rows[0][n] for n in names] == pytest.approx([summary["initial_params"][n] for n in names], rel=1e-12)
    for row in (rows[0], next(h for h in rows if h.get("val_objective") is not None), rows[-1]):
        raw = problem.tc.to_raw(problem.tc.from_named({n: row[n] for n in names}))
        assert float(problem.evaluate(raw, problem.train)[0]) == pytest.approx(row["loss"], rel=1e-9)
        if row.get("val_objective") is not None:
            assert float(problem.evaluate(raw, problem.heldout)[0]) == pytest.approx(row["val_objective"], rel=1e-9)
    best = next(h for h in rows if h["step"] == summary["best_step"])
    assert [best[n] for n in names] == pytest.approx([summary["params"][n] for n in names], rel=1e-12)


def test_bad_input_is_refused(tmp_path):
    # out-of-range starting values are refused by the config, before tune() makes its folder
    for initial, reason in (({"tau_s": 0.1}, r"tau_s must be in \[0.001, 0.032\]"), ({"tau_s": -0.1}, r"tau_s must be in \[0.001, 0.032\]"), ({"k": -5.0}, r"k must be")):
        with pytest.raises(ValueError, match=r"^initial " + reason + r".* \(a name missing from initial takes the paper's value\)$"):
            TuneConfig(controller="dfs", initial=initial, **SHARED)
    # a sample time the paper's 5 ms delay does not fit: the message says why the paper's gains matter
    coarse = dict(SHARED, scenarios=ScenarioSpec(horizon_s=0.4, dt=0.01))
    with pytest.raises(ValueError, match=r"the paper's gains, which set the objective's scales, cannot be run with dt = 0.01 s"):
        TuneConfig(controller="dfs", initial={"tau_s": 0.05}, **coarse)
    # so without an initial tau_s too: that was refused as the initial one, which the user had not given
    with pytest.raises(ValueError, match=r"^the paper's gains, which set the objective's scales, cannot be run with dt = 0.01 s and capacity = 32: tau_s must be in \[0.01, 0.32\] s"):
        TuneConfig(controller="dfs", **coarse)
    # an arm on which the paper's gains diverge (hub inertia / 33: sampled radius 1.13) over 8 s:
    # said at the start, not as a NaN objective blamed on the learning rate
    light_hub = jf.BeamParams(hub_inertia_kg_m2=jf.BeamParams().hub_inertia_kg_m2 * 0.03)
    with pytest.raises(ValueError, match=r"the paper's gains, which set the objective's scales, diverge on the training scenarios: check the arm"):
        Problem(TuneConfig(controller="dfs", n_scenarios=4, n_heldout=2, method="zoh", beam=light_hub, scenarios=ScenarioSpec(horizon_s=8.0)))
    with pytest.raises(ValueError, match="controller must be one of"):
        TuneConfig(controller="lqr")
    with pytest.raises(ValueError, match="delay must be one of"):
        TuneConfig(delay="sinc")
    for temperature in (-0.1, 1e155):
        with pytest.raises(ValueError, match=r"fuzzy_temperature must be 0 \(the faithful controller\) or a Python float in \[1e-05, 1\]"):
            TuneConfig(fuzzy_temperature=temperature)
    with pytest.raises(ValueError, match=r"unknown config key\(s\) \['stepz'\]"):
        TuneConfig.from_mapping({"stepz": 3})
    with pytest.raises(ValueError, match=r"unknown scenario key\(s\) \['noise'\]"):
        TuneConfig.from_mapping({"scenarios": {"noise": 1.0}})
    with pytest.raises(ValueError, match=r"unknown objective key\(s\)"):
        TuneConfig.from_mapping({"objective": {"tip": 1.0}})
    for table in ("scenarios", "objective"):
        with pytest.raises(ValueError, match=f"{table[:-1] if table == 'scenarios' else table} must be a table of keys"):
            TuneConfig.from_mapping({table: 5})
    with pytest.raises(ValueError, match="initial must be a table of parameter values"):
        TuneConfig.from_mapping({"initial": 5})
    with pytest.raises(ValueError, match=r"seed must be an integer in \[-2\*\*63, 2\*\*63\)"):
        TuneConfig(seed=-(2**63) - 1)
    with pytest.raises(ValueError, match="matrix must be a square 2-D array"):
        objectives.log_spectral_radius(jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="matrix must be finite"):
        objectives.log_spectral_radius(jnp.array([[1.0, jnp.nan], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="objective must be an ObjectiveSpec"):
        TuneConfig(objective=None)
    with pytest.raises(ValueError, match="scenarios must be a ScenarioSpec"):
        TuneConfig(scenarios={"horizon_s": 1.0})
    with pytest.raises(ValueError, match=r"cvar_level must be a number in \[0, 1\)"):
        ObjectiveSpec(cvar_level="0.9")
    with pytest.raises(ValueError, match="worst_temperature must be a finite number > 0"):
        ObjectiveSpec(worst_temperature="hot")
    with pytest.raises(ValueError, match="youngs_modulus_rel must be in"):
        ScenarioSpec(youngs_modulus_rel=1.5)
    with pytest.raises(ValueError, match="noise_angle_rad must be a finite number >= 0"):
        ScenarioSpec(noise_angle_rad=-1.0)
    with pytest.raises(ValueError, match="n \\(number of scenarios\\) must be an integer >= 1"):
        sample_scenarios(ScenarioSpec(), jax.random.key(0), 0)
    # an objective that becomes NaN/inf stops with a clear message and keeps the last checkpoint
    cfg = TuneConfig(controller="dfs", steps=10, checkpoint_every=1, learning_rate=50.0, clip_norm=1e6, **SHARED)
    # the advice says where to start again: a --resume keeps the run's learning rate and meets the same NaN
    with pytest.raises(ValueError, match=rf"the objective became .* at step .*: start again with a lower learning_rate \(--lr\) or clip_norm \(a config key\), or check the scenarios, in another --out or after deleting {tmp_path}"):
        tune(cfg, tmp_path, progress=False)
    assert (tmp_path / CHECKPOINT).exists()
    # NaN where the run starts: no update was taken, so the learning rate is not blamed
    cfg = TuneConfig(controller="dfs", steps=2, initial={"k": 1e300}, **SHARED)
    with pytest.raises(ValueError, match=r"the objective is nan at the starting parameters, before any update: check \[initial\]"):
        tune(cfg, tmp_path / "start", progress=False)
    # Over 2 samples DFS's torque reaches no tip deflection yet: every update would be zero,
    # and the run ended saying only that none improved the held-out objective.
    cfg = TuneConfig(controller="dfs", steps=2, **{**SHARED, "scenarios": ScenarioSpec(horizon_s=0.002)})
    with pytest.raises(ValueError, match=r"gradient is exactly zero at the starting parameters, so no update can move them: over the horizon of 0.002 s \(2 samples"):
        tune(cfg, tmp_path / "short", progress=False)
    assert not (tmp_path / "short" / CHECKPOINT).exists()


@pytest.mark.parametrize("best_step", [0, 3])
def test_cli_tune_says_when_no_update_helped(monkeypatch, tmp_path, capsys, best_step):
    from jaxflex import cli
    from tuning import run

    objective = {"train": {"before": 1.0, "after": 1.0}, "heldout": {"before": 1.8, "after": 1.8}}
    summary = {"controller": "fuzzy", "params": {"k1": 1.0}, "paper_params": {"k1": 1.0}, "objective": objective, "steps_run": 5, "best_step": best_step, "stopped_early": False}
    monkeypatch.setattr(run, "run_tune", lambda config, out, resume, progress, on_step: summary)
    assert cli.main(["tune", "--controller", "fuzzy", "--scenarios", "7", "--steps", "5", "--lr", "0.01", "--out", str(tmp_path), "--no-progress"]) == 0
    note = "note: no update improved the held-out objective, so the starting gains are kept; more training scenarios (now 7) or a lower learning_rate (now 0.01) may help"
    assert (note in capsys.readouterr().err) == (best_step == 0)


def test_cli_tune_with_toml_config(tmp_path, capsys):
    from jaxflex import cli

    config = tmp_path / "tune.toml"
    # The run of SHARED (whose programs the session has compiled already), with a non-default
    # value in each table that leaves the compiled objective as it is (cvar_level is read by
    # the "cvar" reduction only).
    config.write_text(
        'controller = "dfs"\nn_heldout = 12\neval_every = 2\n'
        "[scenarios]\nhorizon_s = 0.4\nimpulse_max_n = 0.3\nyoungs_modulus_rel = 0.1\n"
        "[objective]\ncvar_level = 0.8\n"
    )
    assert cli.main(["tune", "--config", str(config), "--scenarios", "24", "--steps", "4", "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    saved = json.loads((tmp_path / "o" / "tuned.json").read_text())
    assert saved["config"]["objective"]["cvar_level"] == 0.8 and saved["config"]["scenarios"]["horizon_s"] == 0.4
    assert saved["config"]["n_heldout"] == 12 and saved["config"]["n_scenarios"] == 24 and saved["steps_run"] == 4
    assert saved["dtype"] == "float64"  # the tests run under jax_enable_x64 (conftest.py)
    printed = capsys.readouterr()
    out = printed.out
    assert f"tune: sampling 24 training and 12 held-out scenarios on {jax.device_count()} device(s), compiling\n" in printed.err  # without the bar too
    best = saved["best_step"]
    assert f"updates 4 of 4; the tuned gains are the point after {best} update{'s' * (best != 1)}\n" in out
    st = saved["stability"]  # the verdict is printed, with digits enough to see it below 1
    assert f"sampled-loop spectral radius {st['spectral_radius']:.8f}, {'stable' if st['stable'] else 'UNSTABLE'} (decay rate" in out
    for name in saved["figures"]:
        assert (tmp_path / "o" / name).read_bytes()[:4] == b"\x89PNG"
    assert sorted(saved["figures"]) == sorted(FIGURES)  # every figure a run may draw (paper and 3 held-out scenarios): what the next run removes
    bad = tmp_path / "bad.toml"
    bad.write_text("learning_rat = 0.1\n")
    assert cli.main(["tune", "--config", str(bad), "--out", str(tmp_path / "b"), "--no-progress"]) == 2
    # a sample time the arm's mode 1 (13.32 Hz) aliases at is refused before the run, naming the key
    bad.write_text('method = "zoh"\nreference = "initial"\n[initial]\ntau_s = 0.04\n[scenarios]\ndt = 0.04\n')
    capsys.readouterr()
    assert cli.main(["tune", "--config", str(bad), "--out", str(tmp_path / "b"), "--no-progress"]) == 2
    assert f"jaxflex tune: error: [scenarios] dt of {bad} must be below 0.0375 s, for the arm's first flexible mode, 13.32 Hz" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_checkpoint_round_trips_an_infinite_best_value(tmp_path):
    """JSON has no inf: a run whose initial held-out objective was not finite resumes with
    best_val = inf (any finite value improves on it), not None; the current point, the
    optimizer state and the best point come back each as saved."""
    from tuning.tuner import _load_checkpoint, _save_checkpoint

    raw = {"log_k": jnp.zeros(()), "tau_z": jnp.ones(())}
    best = {"log_k": jnp.full((), 0.25), "tau_z": jnp.full((), 0.5)}
    opt_state = (jnp.arange(3.0),)
    state = {"raw": raw, "opt_state": opt_state, "best_raw": best, "best_val": float("inf"), "step": 3, "history": [], "fingerprint": "f" * 16}
    _save_checkpoint(str(tmp_path / CHECKPOINT), state)
    loaded = _load_checkpoint(str(tmp_path / CHECKPOINT), (raw, opt_state, raw))
    assert loaded["best_val"] == float("inf") and loaded["step"] == 3
    tree_allclose((loaded["raw"], loaded["opt_state"], loaded["best_raw"]), (raw, opt_state, best), rtol=0)


def test_tuned_json_is_there_only_for_a_finished_run(tmp_path, monkeypatch):
    """A refused resume keeps the finished run's tuned.json and figures; a resume removes
    them until its own end, so that an interrupted one leaves no tuned.json or figure older
    than checkpoint.npz (its figures stayed, drawn for the shorter run)."""
    import tuning.run
    from tuning.run import run_tune

    figures = ["loss.png", "psd_0.png", "psd_1.png", "response_0.png", "response_1.png"]
    assert set(figures) <= set(FIGURES)

    def draw(state, out_dir, paper_objective):  # the figures themselves: tested elsewhere
        for name in figures:
            (Path(out_dir) / name).write_text(f"after {state['step']} steps")
        return figures

    monkeypatch.setattr(tuning.run, "_figures", draw)
    theirs = ["response_notes.png", "response_1_old.png", "psd_2020.png"]
    for name in theirs:
        (tmp_path / name).write_text("the user's")
    config = TuneConfig(controller="dfs", steps=2, eval_every=1, **SHARED)
    run_tune(config, tmp_path, progress=False)
    assert json.loads((tmp_path / "tuned.json").read_text())["steps_run"] == 2
    with pytest.raises(ValueError, match="another configuration"):
        run_tune(dataclasses.replace(config, seed=1), tmp_path, resume=True, progress=False)
    assert (tmp_path / "tuned.json").exists() and all((tmp_path / name).exists() for name in figures)

    def interrupt(step):
        if step == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_tune(dataclasses.replace(config, steps=4), tmp_path, resume=True, progress=False, on_step=interrupt)
    assert not (tmp_path / "tuned.json").exists()
    assert not any((tmp_path / name).exists() for name in figures)
    assert all((tmp_path / name).read_text() == "the user's" for name in theirs)

    # stopped while drawing, after the updates: the figures drawn so far stayed, with no
    # tuned.json beside them; now they are staged and moved in with it, or not at all
    def draw_and_stop(state, out_dir, paper_objective):
        (Path(out_dir) / "loss.png").write_text("drawn")
        raise KeyboardInterrupt

    monkeypatch.setattr(tuning.run, "_figures", draw_and_stop)
    with pytest.raises(KeyboardInterrupt):
        run_tune(dataclasses.replace(config, steps=4), tmp_path, resume=True, progress=False)
    assert json.loads(np.load(tmp_path / CHECKPOINT)["meta"].tobytes())["step"] == 4  # the updates were done
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix in (".png", ".json") or p.name.startswith(".tmp-")) == sorted(theirs)


@pytest.mark.parametrize("meta", [b"", b"not a zip file", json.dumps({"step": 3}).encode(), json.dumps([1, 2]).encode()])
def test_resume_from_an_unreadable_checkpoint_is_refused(tmp_path, meta):
    path = tmp_path / CHECKPOINT
    if not meta.startswith((b"{", b"[")):
        path.write_bytes(meta)  # empty, or not an archive
    else:  # an archive whose metadata lacks the fingerprint, or is not a mapping
        with open(path, "wb") as f:
            np.savez(f, meta=np.frombuffer(meta, dtype=np.uint8))
    with pytest.raises(ValueError, match=f"--resume: {path} is damaged or not a checkpoint of jaxflex tune") as err:
        tune(TuneConfig(controller="dfs", steps=1, **SMALL), tmp_path, resume=True, progress=False)
    assert "pickle" not in str(err.value)


def test_resume_from_a_checkpoint_with_arrays_of_other_shapes_is_refused(tmp_path):
    """A checkpoint with the run's fingerprint but an array of another shape (edited by hand,
    or written by other code) was accepted, and the run went on from a broken state."""
    config = TuneConfig(controller="dfs", steps=1, **SMALL)
    tune(config, tmp_path, progress=False)
    path = tmp_path / CHECKPOINT
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["leaf_0"] = np.zeros((0,), arrays["leaf_0"].dtype)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(ValueError, match=re.escape(f"--resume: {path} is damaged or not a checkpoint of jaxflex tune (its arrays have shapes [(0,), ()")):
        tune(dataclasses.replace(config, steps=2), tmp_path, resume=True, progress=False)


def test_command_line_flags_beat_the_config_file():
    config = TuneConfig.from_mapping({"n_scenarios": 5, "steps": 7, "seed": 2}, n_scenarios=3, steps=None, seed=0)
    assert (config.n_scenarios, config.steps, config.seed) == (3, 7, 0)


def test_numpy_scalars_are_accepted_and_stored_as_plain_numbers():
    """Values read from arrays or files may be NumPy scalars: accepted, stored as int/float, same fingerprint."""
    numpy_cfg = TuneConfig(
        capacity=np.int64(64),
        pade_order=np.int32(8),
        steps=np.int64(10),
        seed=np.int64(3),
        learning_rate=np.float32(0.5),
        fuzzy_temperature=np.float64(0.02),
        scenarios=ScenarioSpec(dt=np.float64(1e-3), horizon_s=np.float64(0.5)),
        objective=ObjectiveSpec(cvar_level=np.float64(0.8), tip_ise=np.float64(2.0)),
    )
    plain_cfg = TuneConfig(
        capacity=64,
        pade_order=8,
        steps=10,
        seed=3,
        learning_rate=float(np.float32(0.5)),
        fuzzy_temperature=0.02,
        scenarios=ScenarioSpec(dt=1e-3, horizon_s=0.5),
        objective=ObjectiveSpec(cvar_level=0.8, tip_ise=2.0),
    )
    assert type(numpy_cfg.capacity) is int and type(numpy_cfg.seed) is int and type(numpy_cfg.learning_rate) is float
    assert type(numpy_cfg.scenarios.dt) is float and type(numpy_cfg.objective.cvar_level) is float
    assert numpy_cfg.fingerprint() == plain_cfg.fingerprint()
    for bad in (True, np.bool_(True)):
        with pytest.raises(ValueError, match=re.escape("capacity must be an integer in [2, 2048] (samples)")):
            TuneConfig(capacity=bad)
    # the range each message states is the range each config accepts (TuneConfig said ">= 1",
    # then ">= 2" for 1; both configs took a Pade order of 10^6 unless delay was "pade")
    from jaxflex.montecarlo import MCConfig

    for config, name, (low, high) in ((TuneConfig, "capacity", (2, 2048)), (MCConfig, "capacity", (1, 1_000_000)), (TuneConfig, "pade_order", (1, 100)), (MCConfig, "pade_order", (1, 100))):
        for bad in (low - 1, high + 1):
            with pytest.raises(ValueError, match=re.escape(f"{name} must be an integer in [{low}, {high}]")):
                config(**{name: bad})
        # a delay that fits the smallest buffer
        room = {TuneConfig: {"reference": "initial", "initial": {"tau_s": 0.001}}, MCConfig: {"params": {"tau_s": 0.001}}}[config] if name == "capacity" else {}
        config(**{name: low}, **room), config(**{name: high}, **room)


def test_config_beam_is_the_arm_that_is_tuned():
    """A [beam] table sets the nominal arm of the run (its plant), and
    is part of the fingerprint, so a resume onto another arm is refused."""
    from jaxflex.beam import BeamParams
    from jaxflex.plant import discretize, make_plant

    table = {"controller": "dfs", "n_scenarios": 2, "n_heldout": 1, "scenarios": {"horizon_s": 0.05}, "beam": {"length_m": 0.6, "payload_mass_kg": 0.05}}
    cfg = TuneConfig.from_mapping(table)
    arm = BeamParams(length_m=0.6, payload_mass_kg=0.05)
    assert cfg.beam == arm and cfg.to_dict()["beam"]["length_m"] == 0.6
    assert cfg.fingerprint() != dataclasses.replace(cfg, beam=BeamParams()).fingerprint()
    problem = Problem(cfg)
    tree_allclose(problem.nominal, discretize(make_plant(arm, 2), 1e-3, cfg.method))
    with pytest.raises(ValueError, match=r"unknown beam key\(s\) \['length'\]"):
        TuneConfig.from_mapping({"beam": {"length": 0.6}})


def test_readme_config_example_is_a_valid_config(tmp_path):
    """The README's example config file is accepted as written, [beam] table included."""
    import pathlib
    import re

    from jaxflex import fileio
    from jaxflex.beam import BeamParams

    readme = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    (block,) = re.findall(r"```toml\n(.*?)```", readme.split("## Monte Carlo", 1)[0], re.S)  # the tune section's (montecarlo's has its own test)
    path = tmp_path / "tune.toml"
    path.write_text(block)
    cfg = TuneConfig.from_mapping(fileio.read_toml(path))
    assert cfg.controller == "dfs+fuzzy" and cfg.objective.reduction == "cvar" and cfg.scenarios.payload_max_kg == 0.05
    assert cfg.beam == BeamParams(length_m=0.6, thickness_m=4e-3, hub_inertia_kg_m2=2e-3, payload_mass_kg=0.1)


def test_objective_spec_refuses_bad_weights_and_levels_by_name():
    """All-zero term weights, cvar_level = 1 (the interval is [0, 1)) and a negative stability
    weight are refused, each naming what is wrong; the edge values that are allowed pass."""
    with pytest.raises(ValueError, match="at least one objective weight"):
        ObjectiveSpec(tip_ise=0.0, hub_ise=0.0, effort=0.0, vibration=0.0)
    with pytest.raises(ValueError, match="cvar_level"):
        ObjectiveSpec(cvar_level=1.0)
    with pytest.raises(ValueError, match="stability_weight"):
        ObjectiveSpec(stability_weight=-1.0)
    assert ObjectiveSpec(tip_ise=0.0, vibration=0.5, cvar_level=0.0, stability_weight=0.0).cvar_level == 0.0


@pytest.mark.parametrize("name", ["dfs", "fuzzy", "dfs+fuzzy"])
@pytest.mark.parametrize("delay", ["linear", "pade"])
def test_transforms_round_trip_each_parameter(name, delay):
    """to_physical(to_raw(p)) is p, parameter by parameter (distinct values, so a swap shows)."""
    from tuning.transforms import tuned_controller

    t = tuned_controller(name, delay=delay)
    given = {"k": 41.0, "tau_s": 0.0073, "k1": 0.8, "k2": 0.45, "k3": 1.7}
    params = t.from_named(given)
    back = t.named(t.to_physical(t.to_raw(params)))
    assert sorted(back) == sorted(t.named(params))
    for key, value in back.items():
        assert value == pytest.approx(given[key], rel=1e-12), key


def test_reference_scales_are_batch_means_so_the_reference_gains_score_the_weights():
    """Each term is divided by its batch mean under the paper's gains: those gains then score
    the sum of the weights under "mean", and a term that is 0 in every scenario is floored."""
    terms = objectives.Terms(*(jnp.asarray(v) for v in ([1.0, 2.0, 6.0], [0.0, 0.0, 0.0], [3.0, 5.0, 4.0], [1e-3, 2e-3, 0.0])))
    scales = objectives.reference_scales(terms)
    np.testing.assert_allclose([float(s) for s in scales], [3.0, np.finfo(np.float64).tiny, 4.0, 1e-3], rtol=1e-12)
    spec = ObjectiveSpec(tip_ise=1.0, effort=0.5, vibration=2.0)
    losses = objectives.scenario_losses(terms, scales, spec)
    np.testing.assert_allclose(float(objectives.reduce_losses(losses, spec)), 3.5, rtol=1e-12)


def test_dfs_transform_accepts_tau_at_both_ends():
    """tau in [dt, capacity dt] closed: both ends pass check_tau, and to_raw maps them to
    finite raw values (the fraction is clipped inside (0, 1)) that map back near the ends."""
    from tuning.transforms import check_tau, tuned_controller

    dt, capacity = 1e-3, 32
    check_tau(dt, dt, capacity)
    check_tau(capacity * dt, dt, capacity)
    with pytest.raises(ValueError, match="tau_s"):
        check_tau(0.5 * dt, dt, capacity)
    t = tuned_controller("dfs", dt=dt, capacity=capacity)
    for tau in (dt, capacity * dt):
        raw = t.to_raw(DFSParams(55.0, tau))
        assert np.isfinite(float(raw["tau_z"])) and np.isfinite(float(raw["log_k"]))
        back = t.to_physical(raw)
        assert float(back.tau_s) == pytest.approx(tau, rel=1e-4)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_fuzzy_transform_refuses_nonpositive_gains_by_name(bad):
    from jaxflex.controllers.fuzzy import fuzzy_params
    from tuning.transforms import tuned_controller

    t = tuned_controller("fuzzy")
    with pytest.raises(ValueError, match="k1 must be finite and > 0"):
        t.to_raw(fuzzy_params()._replace(k1=bad))


def test_dfs_plus_fuzzy_transform_keeps_the_pade_delay():
    """A dfs+fuzzy transform built with delay="pade" rolls out as by_name("dfs+fuzzy",
    delay="pade") (same Pade order), not as the linear-interpolation delay."""
    from jaxflex.controllers import by_name
    from tuning.transforms import tuned_controller

    plant = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")
    sc = jf.paper_scenario(plant, horizon_s=0.1)
    pade = tuned_controller("dfs+fuzzy", dt=1e-3, capacity=16, delay="pade", pade_order=4)
    linear = tuned_controller("dfs+fuzzy", dt=1e-3, capacity=16, delay="linear")
    ref_ctrl, ref_params = by_name("dfs+fuzzy", dt=1e-3, capacity=16, delay="pade", pade_order=4)
    run = lambda c, p: np.asarray(jf.rollout(plant, c, p, sc).x)
    got = run(pade.controller, pade.paper)
    np.testing.assert_allclose(got, run(ref_ctrl, ref_params), rtol=1e-12, atol=1e-15)
    assert np.max(np.abs(got - run(linear.controller, linear.paper))) > 1e-6 * np.max(np.abs(got))


def test_config_and_optimizer_of_the_wrong_kind_are_refused(tmp_path):
    """A dict for the config, or optax.adam uncalled, failed deep inside with an AttributeError."""
    import optax

    with pytest.raises(ValueError, match=r"config must be a TuneConfig \(build one with TuneConfig\(...\)\); got dict"):
        tune({"controller": "dfs"}, tmp_path)
    with pytest.raises(ValueError, match=r"optimizer must be a GradientTransformation \(e.g. optax.adam\(1e-2\)\); got the function adam itself: call it"):
        tune(TuneConfig(controller="dfs", **SHARED), tmp_path, optimizer=optax.adam)
    assert not os.listdir(tmp_path)


def test_an_arm_that_overflows_the_run_dtype_is_refused_with_the_config():
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match=r"BeamParams.youngs_modulus_pa must be in \[1.175e-38, 3.403e\+38\] to be simulated in float32"):
            TuneConfig(beam=jf.BeamParams(youngs_modulus_pa=1e39), method="zoh")


@pytest.mark.parametrize(
    "steps, state, said",
    [
        (40, {"step": 25}, "tune: resuming from {ckpt}, after 25 of 40 updates"),
        (40, {"step": 40, "history": [{"step": 40}]}, "tune: the run in {out} has finished all 40 updates; writing its results again (--steps above 40 goes on)"),
        (40, {"step": 30, "history": [{"step": 30}], "stopped_early": True}, "tune: the run in {out} stopped early after 30 updates; writing its results again"),
        # its last update checkpointed, the final point not scored yet (rows up to 39): it goes on
        (40, {"step": 40, "history": [{"step": 39}]}, "tune: resuming from {ckpt}, after 40 of 40 updates"),
        # stopped early at 30 (rows up to 29), resumed with --steps 30: still stopped early
        (30, {"step": 30, "history": [{"step": 29}], "stopped_early": True}, "tune: the run in {out} stopped early after 30 updates; writing its results again"),
    ],
)
@pytest.mark.parametrize("progress", [True, False], ids=["bar", "no bar"])
def test_resume_says_from_which_checkpoint(tmp_path, monkeypatch, capsys, steps, state, said, progress):
    """A resumed run says so, with the step it goes on from (it said nothing until its
    progress bar, after the compile, opened part-way); a finished or early-stopped one says
    that it only writes its results again (it said "after 40 of 40 updates"). It says so
    without the bar too (--no-progress, as under a scheduler): it said nothing there."""
    config = TuneConfig(steps=steps)
    fake_checkpoint(monkeypatch, tmp_path, config, **state)
    with pytest.raises(Sampled):  # the message comes before the sampling and compiling
        tune(config, tmp_path, resume=True, progress=progress)
    assert said.format(ckpt=tmp_path / CHECKPOINT, out=tmp_path) in capsys.readouterr().err


def test_tuning_sharded_over_devices_equals_one_device(tmp_path):
    """`jaxflex tune --cpu-devices 2` in a fresh process shards the scenarios over 2 devices
    (7 training and 5 held-out scenarios: both padded to an even count) and takes the steps of
    the 1-device run, to the tuned gains and objectives (float64: only the order of additions
    differs)."""
    from jaxflex import fileio

    config = tmp_path / "tune.toml"
    config.write_text('controller = "dfs"\nn_scenarios = 7\nn_heldout = 5\nsteps = 3\neval_every = 1\n[scenarios]\nhorizon_s = 0.2\nyoungs_modulus_rel = 0.1\n')
    runs = {}
    in_process = jax.default_backend() == "cpu" and jax.device_count() == 1 and not os.environ.get("XLA_FLAGS")
    if in_process:  # conftest.py enables float64 here, as --x64 does in the subprocess; no figures
        runs[1] = summarize(tune(TuneConfig.from_mapping(fileio.read_toml(str(config))), tmp_path / "d1", progress=False))
    for devices in (2,) if in_process else (1, 2):
        command = [sys.executable, "-m", "jaxflex.cli", "tune", "--config", str(config), "--x64", "--cpu-devices", str(devices), "--no-progress", "--out", str(tmp_path / f"d{devices}")]
        out = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=600)
        assert out.returncode == 0, out.stderr
        runs[devices] = json.loads((tmp_path / f"d{devices}" / "tuned.json").read_text())
    assert runs[1]["devices"] == 1 and runs[2]["devices"] == 2 and runs[2]["dtype"] == "float64"
    assert runs[1]["best_step"] == runs[2]["best_step"]
    for name, value in runs[1]["params"].items():
        np.testing.assert_allclose(runs[2]["params"][name], value, rtol=1e-10, err_msg=name)
    for batch in ("train", "heldout"):
        for when in ("before", "after", "paper"):
            np.testing.assert_allclose(runs[2]["objective"][batch][when], runs[1]["objective"][batch][when], rtol=1e-10, err_msg=f"{batch}.{when}")
    history = {devices: np.genfromtxt(tmp_path / f"d{devices}" / "history.csv", delimiter=",", names=True) for devices in (1, 2)}
    assert history[1].dtype.names == history[2].dtype.names and len(history[1]) == 4  # rows 0-3
    for name in history[1].dtype.names:  # every point's parameters, objectives and gradient norm
        np.testing.assert_allclose(history[2][name], history[1][name], rtol=1e-10, err_msg=name)
    assert np.all(np.diff(history[2]["k"]) != 0)  # each update moved the gains
    assert runs[1]["devices_from_step"] == [{"from_step": 0, "devices": 1}] and runs[2]["devices_from_step"] == [{"from_step": 0, "devices": 2}]
    # the 2-device run resumed on 1 device for one more update: tuned.json says which count took which steps
    command = [sys.executable, "-m", "jaxflex.cli", "tune", "--config", str(config), "--x64", "--cpu-devices", "1", "--no-progress", "--resume", "--steps", "4", "--out", str(tmp_path / "d2")]
    out = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=600)
    assert out.returncode == 0, out.stderr
    mixed = json.loads((tmp_path / "d2" / "tuned.json").read_text())
    assert mixed["steps_run"] == 4 and mixed["devices"] == 1
    assert mixed["devices_from_step"] == [{"from_step": 0, "devices": 2}, {"from_step": 3, "devices": 1}]
    assert "tune: note: the run took steps on 2 device(s) and goes on on 1: its result matches an uninterrupted run's within rounding" in out.stderr  # said, not only recorded


def test_initial_gains_may_set_the_scales_where_the_papers_cannot_run(tmp_path, monkeypatch):
    """At dt = 10 ms the paper's 5 ms delay does not fit the buffer, and DFS could not be tuned
    at all: the paper's gains set the objective's scales. reference = "initial" scales it by
    the [initial] gains, which then score 1 (the mean of one unit weight)."""
    import tuning.run
    from tuning.run import run_tune

    coarse = dict(SHARED, n_scenarios=8, n_heldout=4, scenarios=ScenarioSpec(horizon_s=0.4, dt=0.01))
    with pytest.raises(ValueError, match=r"tau_s must be in \[0.01, 0.32\] s \(one sample to the delay buffer's capacity, 32 samples: capacity sets it\); got 0.005; set reference = .initial. to scale the objective by the \[initial\] gains instead$"):
        TuneConfig(controller="dfs", initial={"tau_s": 0.02}, **coarse)
    with pytest.raises(ValueError, match=r"reference must be one of \('paper', 'initial'\); got 'nominal'"):
        TuneConfig(reference="nominal")
    values = {"controller": "dfs", "reference": "initial", "initial": {"k": 40.0, "tau_s": 0.02}, "steps": 2, "eval_every": 1, "n_scenarios": 8, "n_heldout": 4}
    config = TuneConfig.from_mapping({**values, "scenarios": {"horizon_s": 0.4, "dt": 0.01}})  # as a TOML file has it
    problem = Problem(config)
    assert problem.paper_raw is None
    terms = jax.jit(problem._terms)(problem.initial_raw, problem.train)  # the scales are the initial gains' means
    np.testing.assert_allclose(np.asarray(problem.scales.tip_ise), np.mean(np.asarray(terms.tip_ise)), rtol=1e-12)
    summary = run_tune(config, tmp_path, progress=False)
    assert summary["objective"]["train"]["before"] == pytest.approx(1.0, rel=1e-12)
    assert summary["objective"]["train"]["paper"] is None and summary["objective"]["heldout"]["paper"] is None
    assert "under the initial gains" in summary["objective"]["definition"]
    assert summary["stability"]["paper_spectral_radius"] is None and summary["stability"]["spectral_radius"] > 0
    assert json.loads((tmp_path / "tuned.json").read_text())["config"]["reference"] == "initial"
    # an arm on which the paper's gains diverge (test_bad_input_is_refused's; sampled radius 1.13)
    # tunes from gains that hold it (tau = 2 ms: 0.9957)
    light_hub = jf.BeamParams(hub_inertia_kg_m2=jf.BeamParams().hub_inertia_kg_m2 * 0.03)
    held = Problem(TuneConfig(controller="dfs", n_scenarios=4, n_heldout=2, method="zoh", beam=light_hub, scenarios=ScenarioSpec(horizon_s=8.0), reference="initial", initial={"tau_s": 0.002}))
    assert all(np.isfinite(float(t)) and float(t) > 0 for t in held.scales)
    # on the paper's arm the paper's gains still score 1 by default, and the initial ones under
    # "initial"; loss.png names the objective of those reference gains
    drawn = []
    monkeypatch.setattr(tuning.run, "_figures", lambda state, out, reference_objective: drawn.append(reference_objective) or [])
    for reference, scored in (("paper", "paper"), ("initial", "before")):
        config = TuneConfig(controller="dfs", reference=reference, initial={"k": 80.0}, steps=1, **dict(SHARED, n_scenarios=8, n_heldout=4))
        objective = run_tune(config, tmp_path / reference, progress=False)["objective"]["train"]
        assert objective[scored] == pytest.approx(1.0, rel=1e-12)
        assert objective["before"] != pytest.approx(objective["paper"], rel=1e-3)  # k = 80 is not the paper's 55
        assert drawn[-1] == objective[scored]


def test_reported_spectral_radius_is_float64_in_a_float32_run(tmp_path):
    """tuned.json's sampled-loop radius is computed in float64 as `jaxflex stability`'s is,
    whatever the run's dtype: the float32 loop matrix moved the paper's 0.99065454 to
    0.99065495, and tune and stability then disagreed in the 7th digit."""
    with jax.enable_x64(False):
        state = tune(TuneConfig(controller="dfs", steps=1, eval_every=1, **SHARED), tmp_path, progress=False)
        assert jax.tree.leaves(state["best_raw"])[0].dtype == jnp.float32  # the run itself is float32
        summary = summarize(state)
        st = summary["stability"]
    # history.csv and tuned.json give each float32 number the digits float32 holds and no more:
    # the initial k, exp(log(55)), is 55.000008, which they wrote as 55.00000762939453
    numbers = [s for line in (tmp_path / "history.csv").read_text().splitlines()[1:] for s in line.split(",")[1:] if s]
    numbers += [repr(v) for v in (*summary["params"].values(), *summary["initial_params"].values(), summary["objective"]["heldout"]["after"])]
    assert len(numbers) == 7 + 6 + 5 and all(str(np.float32(s)) == s for s in numbers), numbers
    with jax.enable_x64(True):
        plant = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")  # TuneConfig's default method
        paper = float(stability.spectral_radius(plant, 55.0, 5))  # the paper's k = 55, tau = 5 ms
    assert 0.99 < paper < 0.991
    assert st["paper_spectral_radius"] == pytest.approx(paper, rel=1e-9, abs=0)
    # a tuned delay at the top of its range: float32's 0.064 s is 64.000003 samples of 1 ms,
    # which the float64 radius refused after the whole run (no tuned.json)
    with jax.enable_x64(False):
        state = tune(TuneConfig(controller="dfs", steps=1, eval_every=1, capacity=64, **SHARED), tmp_path / "top", progress=False)
        state["best_raw"] = {**state["best_raw"], "tau_z": jnp.float32(30.0)}
        assert float(state["problem"].tc.to_physical(state["best_raw"]).tau_s) / 1e-3 > 64  # the case itself
        st = summarize(state)["stability"]
    with jax.enable_x64(True):
        top = float(stability.spectral_radius(plant, float(jnp.exp(state["best_raw"]["log_k"])), 64))
    assert st["spectral_radius"] == pytest.approx(top, rel=1e-6, abs=0)


def test_a_pade_or_cubic_run_reports_and_penalises_its_own_loop(tmp_path, capsys):
    """With delay = "pade" the radius and penalty were the buffer's, a different loop: at
    k = 150, tau = 5 ms the order-1 loop decays (0.989) where the buffer's grows (1.063)."""
    config = TuneConfig(controller="dfs", delay="pade", pade_order=1, steps=1, **SHARED)
    problem, at = Problem(config), jnp.asarray([150.0, 0.005])
    log_radius = lambda p: problem.dfs_log_radius(DFSParams(p[0], p[1]))
    with jax.enable_x64(True):
        nominal = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, config.method)
        pade1, buffer = (float(jnp.max(jnp.abs(jnp.linalg.eigvals(m)))) for m in (
            stability.deflated_pade_loop_matrix(nominal, 150.0, 0.005, 1), stability.deflated_loop_matrix(nominal, 150.0, 5.0, config.capacity)))
    assert pade1 < 1 < buffer
    assert float(log_radius(at)) == pytest.approx(math.log(pade1), rel=1e-9)
    # its derivative in k and tau, which the penalty follows, against central differences
    grad = jax.grad(log_radius)(at)
    for i, h in enumerate((1e-3, 1e-8)):
        step = jnp.zeros(2).at[i].set(h)
        fd = (log_radius(at + step) - log_radius(at - step)) / (2 * h)
        assert float(grad[i]) == pytest.approx(float(fd), rel=1e-5)
    state = tune(config, tmp_path, progress=False)
    summary = summarize(state)
    with jax.enable_x64(True):
        paper = float(jnp.max(jnp.abs(jnp.linalg.eigvals(stability.deflated_pade_loop_matrix(nominal, 55.0, 0.005, 1)))))
    assert summary["stability"]["paper_spectral_radius"] == pytest.approx(paper, rel=1e-12)
    # without the bar, a line for a log: every 30 s and at the end (it said nothing), with the
    # final point's scores (it gave the best held-out before the final point was scored)
    line = re.search(r"\ntune: 1 of 1 updates \(100 %\) after \d+ s; loss (\S+), best held-out (\S+)\n", capsys.readouterr().err)
    assert line and line.groups() == (f"{state['history'][-1]['loss']:.4g}", f"{min(row['val_objective'] for row in state['history']):.4g}")
    # the cubic read's loop likewise (the linear read's, the same loop at whole samples only)
    cubic = Problem(dataclasses.replace(config, delay="cubic"))
    with jax.enable_x64(True):
        loops = [stability.deflated_loop_matrix(nominal, 55.0, 4.3, config.capacity, read) for read in ("cubic", "linear")]
        radii = [float(jnp.max(jnp.abs(jnp.linalg.eigvals(m)))) for m in loops]
    value = float(cubic.dfs_log_radius(DFSParams(55.0, 0.0043)))
    assert value == pytest.approx(math.log(radii[0]), rel=1e-9) and value != pytest.approx(math.log(radii[1]), rel=1e-6)
    # and its derivative, inside one sample interval (the cubic read has kinks at whole samples)
    cubic_log_radius, at = (lambda p: cubic.dfs_log_radius(DFSParams(p[0], p[1]))), jnp.asarray([55.0, 0.0043])
    grad = jax.grad(cubic_log_radius)(at)
    for i, h in enumerate((1e-3, 1e-8)):
        step = jnp.zeros(2).at[i].set(h)
        fd = (cubic_log_radius(at + step) - cubic_log_radius(at - step)) / (2 * h)
        assert float(grad[i]) != 0 and float(grad[i]) == pytest.approx(float(fd), rel=1e-5)


def test_a_run_resumed_after_its_last_update_ends_its_log_at_100_percent(tmp_path, capsys):
    """Stopped after the last update's checkpoint, before the final point was scored: the
    resumed run's --no-progress line counted the final point as an update ('3 of 2 updates
    (150 %)')."""
    config = TuneConfig(controller="dfs", steps=2, checkpoint_every=2, **SMALL)

    def interrupt(step):
        if step == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        tune(config, tmp_path, progress=False, on_step=interrupt)
    capsys.readouterr()
    state = tune(config, tmp_path, resume=True, progress=False)
    err = capsys.readouterr().err
    assert re.search(r"\ntune: 2 of 2 updates \(100 %\) after \d+ s; loss (\S+), best held-out", err) and "3 of 2" not in err, err
    assert state["history"][-1]["step"] == 2


def test_a_bare_cli_resume_goes_on_to_the_runs_own_steps_and_a_new_run_keeps_an_earlier_result(tmp_path, capsys, monkeypatch):
    """`tune --resume` without --steps went on to the default 200 of a run started for 400 and
    wrote a final-looking tuned.json; a new run into a folder holding an earlier tuned.json
    (no checkpoint) removed it and its figures at its start, so that one stopped then lost them."""
    import tuning.run
    from jaxflex import cli

    cfg = TuneConfig(controller="dfs", steps=7, checkpoint_every=1, **{**SHARED, "n_scenarios": 4, "n_heldout": 2, "scenarios": ScenarioSpec(horizon_s=0.05)})

    def interrupt(step):
        if step == 2:
            raise KeyboardInterrupt

    config = tmp_path / "c.toml"
    config.write_text("[scenarios]\nhorizon_s = 0.05\n")
    with pytest.raises(KeyboardInterrupt):
        tune(cfg, tmp_path / "run", progress=False, on_step=interrupt)
    asked = []
    monkeypatch.setattr(tuning.run, "run_tune", lambda config, *a, **k: asked.append(config.steps) or (_ for _ in ()).throw(KeyboardInterrupt))
    args = ["tune", "--config", str(config), "--scenarios", "4", "--heldout", "2", "--out", str(tmp_path / "run"), "--resume", "--no-progress"]
    assert cli.main(args) == 130 and asked == [7]
    assert f"tune: --resume: --steps 7, as the run in {tmp_path / 'run'} recorded" in capsys.readouterr().err
    assert cli.main([*args, "--steps", "9"]) == 130 and asked[-1] == 9  # an explicit --steps extends it
    config.write_text("steps = 11\n[scenarios]\nhorizon_s = 0.05\n")  # so does the config's: README's "unless given others"
    assert cli.main(args) == 130 and asked[-1] == 11
    assert "--resume: --steps" not in capsys.readouterr().err
    monkeypatch.undo()
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "tuned.json").write_text("{}")
    (earlier / "loss.png").write_bytes(b"png")
    with pytest.raises(ValueError, match=rf"{earlier} holds the tuned.json of an earlier run: choose another --out \(out_dir\), or remove that tuned.json"):
        tuning.run.run_tune(cfg, earlier, progress=False)
    assert sorted(p.name for p in earlier.iterdir() if not p.name.startswith(".")) == ["loss.png", "tuned.json"]


def test_the_same_starting_point_written_otherwise_has_the_same_fingerprint():
    """[initial] k = 55 edited to k = 55.0, or the paper's values written out, refused a resume
    with "the configuration changed", naming nothing: the fingerprint holds the starting point."""
    base = TuneConfig(controller="dfs", **SHARED)
    for initial in ({"k": 55}, {"k": 55.0}, {"k": 55.0, "tau_s": 0.005}):
        assert dataclasses.replace(base, initial=initial).fingerprint() == base.fingerprint(), initial
    assert dataclasses.replace(base, initial={"k": 56.0}).fingerprint() != base.fingerprint()
    assert dataclasses.replace(base, initial={"k": 55}).to_dict()["initial"] == {"k": 55}  # tuned.json keeps what was given


def test_a_full_disk_names_where_and_that_the_run_resumes(tmp_path, capsys, monkeypatch):
    """A full disk printed only "[Errno 28] No space left on device": no folder, and no word
    that the checkpoint is kept and --resume goes on once there is space."""
    import errno

    import tuning.run
    from jaxflex import cli

    out = tmp_path / "run"

    def full(config, out_dir, **kwargs):
        os.makedirs(out_dir, exist_ok=True)
        (out / CHECKPOINT).write_bytes(b"")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(tuning.run, "run_tune", full)
    assert cli.main(["tune", "--out", str(out), "--no-progress"]) == 2
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said == f"jaxflex tune: error: cannot write into {out}: {os.strerror(errno.ENOSPC)}; what was written is kept: free space, then the same command with --resume continues from the last checkpoint"


@pytest.mark.parametrize("command", ["tune", "montecarlo"])
def test_a_full_disk_before_anything_to_resume_from_promises_no_resume(tmp_path, capsys, monkeypatch, command):
    """The full-disk message's "--resume continues" holds only once a checkpoint (tune) or a
    run record (montecarlo) is written: before one, it sent the user to a --resume that is
    refused (Ctrl-C says "nothing was written to resume from")."""
    import errno

    import tuning.run
    from jaxflex import cli, montecarlo

    out = tmp_path / "run"

    def full(config, out_dir, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(tuning.run, "run_tune", full)
    monkeypatch.setattr(montecarlo, "run_montecarlo", full)
    assert cli.main([command, "--out", str(out), "--no-progress"]) == 2
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said == f"jaxflex {command}: error: cannot write into {out}: {os.strerror(errno.ENOSPC)}"


def test_a_log_file_gets_lines_not_a_progress_bar(tmp_path, monkeypatch):
    """tune's bar, written to a log file, left two redraws per step there (22 KB for 200 steps):
    off a terminal the commands write --no-progress's lines."""
    import io

    import tuning.run
    from jaxflex import cli, montecarlo

    asked = []
    monkeypatch.setattr(tuning.run, "run_tune", lambda *a, progress, **k: asked.append(progress) or (_ for _ in ()).throw(KeyboardInterrupt))
    monkeypatch.setattr(montecarlo, "run_montecarlo", lambda *a, progress, **k: asked.append(progress) or (_ for _ in ()).throw(KeyboardInterrupt))

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    for stream, expected in ((io.StringIO(), False), (Terminal(), True)):
        monkeypatch.setattr(sys, "stderr", stream)
        for command in ("tune", "montecarlo"):
            assert cli.main([command, "--out", str(tmp_path / command)]) == 130
            assert cli.main([command, "--out", str(tmp_path / command), "--no-progress"]) == 130
            assert asked[-2:] == [expected, False], (command, expected)


# -- audit 13 (tuner.py, objectives.py): ranges, the CVaR count, the fingerprint, resume edge cases, history.csv --


# each range a docstring or message names is the range accepted
@pytest.mark.parametrize("name", ["n_heldout", "eval_every", "patience", "checkpoint_every"])
def test_integer_settings_below_1_are_refused_by_name(name):
    with pytest.raises(ValueError, match=rf"^{name} must be an integer >= 1"):
        TuneConfig(**{name: 0})


@pytest.mark.parametrize("name", ["learning_rate", "clip_norm"])
@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_step_size_and_clip_must_be_positive(name, bad):
    with pytest.raises(ValueError, match=rf"^{name} must be a finite number > 0"):
        TuneConfig(**{name: bad})


def test_objective_refuses_a_negative_min_decay_rate_a_zero_temperature_and_a_bool_level():
    with pytest.raises(ValueError, match="min_decay_rate must be a finite number >= 0"):
        ObjectiveSpec(min_decay_rate=-1.0)
    with pytest.raises(ValueError, match="worst_temperature must be a finite number > 0"):
        ObjectiveSpec(worst_temperature=0.0)
    with pytest.raises(ValueError, match=r"cvar_level must be a number in \[0, 1\)"):
        ObjectiveSpec(cvar_level=False)


# CVaR count: ceil((1 - level) B), at least 1
@pytest.mark.parametrize("level, batch, tail", [(0.9, 25, 3), (0.98, 51, 2), (0.9, 35, 4), (1 - 1e-12, 4, 1)])
def test_cvar_averages_ceil_of_the_tail_and_at_least_one(level, batch, tail):
    values = np.random.default_rng(batch).permutation(np.arange(float(batch)))
    got = float(objectives.reduce_losses(jnp.asarray(values), ObjectiveSpec(reduction="cvar", cvar_level=level)))
    assert got == pytest.approx(np.sort(values)[-tail:].mean(), rel=1e-12)


def test_log_spectral_radius_refuses_empty_and_infinite_matrices():
    with pytest.raises(ValueError, match="matrix must be a square 2-D array"):
        objectives.log_spectral_radius(jnp.zeros((0, 0)))
    with pytest.raises(ValueError, match="matrix must be finite"):
        objectives.log_spectral_radius(jnp.array([[1.0, jnp.inf], [0.0, 1.0]]))


def test_fingerprint_holds_the_dtype():
    """A float32 checkpoint must not be resumed by a float64 run (the docstring: the dtype is
    part of what a resume must share)."""
    cfg = TuneConfig()
    with jax.enable_x64(False):
        f32 = cfg.fingerprint()
    assert f32 != cfg.fingerprint()


@pytest.fixture(scope="module")
def slow_decay_problem():
    """DFS with a min_decay_rate far above the paper loop's (about 9 /s): the penalty acts."""
    return Problem(TuneConfig(controller="dfs", objective=ObjectiveSpec(min_decay_rate=100.0, stability_weight=1e-3), **TINY))


def test_the_training_loss_adds_the_active_penalty(slow_decay_problem):
    p = slow_decay_problem
    value, aux = p.evaluate(p.paper_raw, p.train)
    decay = -math.log(float(stability.spectral_radius(p.nominal, 55.0, 5))) / 1e-3
    penalty = 1e-3 * (100.0 - decay) ** 2
    assert float(aux["penalty"]) == pytest.approx(penalty, rel=1e-6)
    assert float(aux["objective"]) == pytest.approx(1.0, rel=1e-9)  # the paper's gains set the scales
    assert float(value) == pytest.approx(1.0 + penalty, rel=1e-6)


def test_history_grad_norm_is_the_norm_of_the_loss_gradient(tmp_path):
    """grad_norm in row 0: the gradient of the loss at the starting point, by central differences
    on the raw parameters (clip_norm tiny, so the update's norm differs from it)."""
    cfg = TuneConfig(controller="dfs", steps=1, clip_norm=1e-6, initial={"k": 50.0, "tau_s": 0.0053}, **TINY)  # off a whole-sample kink
    state = tune(cfg, tmp_path, progress=False)
    p = state["problem"]
    raw0 = p.initial_raw
    fd = []
    for name in sorted(raw0):
        h = 1e-5
        plus = {**raw0, name: raw0[name] + h}
        minus = {**raw0, name: raw0[name] - h}
        fd.append((float(p.evaluate(plus, p.train)[0]) - float(p.evaluate(minus, p.train)[0])) / (2 * h))
    assert state["history"][0]["grad_norm"] == pytest.approx(float(np.linalg.norm(fd)), rel=1e-4)


def test_heldout_batch_does_not_hold_the_training_paper_scenario(slow_decay_problem):
    p = slow_decay_problem
    paper_x0 = np.asarray(p.train.x0[0])
    assert not np.any(np.all(np.asarray(p.heldout.x0) == paper_x0, axis=1))
    assert np.all(np.any(np.asarray(p.heldout.force) != 0, axis=(1, 2)))  # every held-out scenario is a random draw


def scripted_train_step(monkeypatch, at_call, **replace):
    """Make the train step's info at its ``at_call``-th call (0-based) take ``replace``'s values."""
    import tuning.tuner

    class Scripted(tuning.tuner.Problem):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            step, calls = self.train_step, [0]

            def train_step(raw, opt_state, batch):
                raw, opt_state, info = step(raw, opt_state, batch)
                if calls[0] == at_call:
                    info = {**info, **{k: jnp.asarray(v) for k, v in replace.items()}}
                calls[0] += 1
                return raw, opt_state, info

            self.train_step = train_step

    monkeypatch.setattr(tuning.tuner, "Problem", Scripted)


@pytest.mark.parametrize("checkpoint_every", [1, 25])
def test_a_nan_after_the_first_update_names_its_step_and_what_is_kept(tmp_path, monkeypatch, checkpoint_every):
    """The objective turns NaN at the point after 1 update: that is not 'the starting
    parameters'; the step named is the update that failed (the one after those on_step counted),
    and the message says whether a checkpoint is there to keep."""
    scripted_train_step(monkeypatch, 1, loss=float("nan"))
    done = []
    with pytest.raises(ValueError) as err:
        tune(TuneConfig(controller="dfs", steps=5, checkpoint_every=checkpoint_every, **TINY), tmp_path, progress=False, on_step=done.append)
    msg = str(err.value)
    assert done == [1] and "starting parameters" not in msg
    assert f"the objective became nan at step {done[-1] + 1}:" in msg
    written = (tmp_path / CHECKPOINT).exists()
    assert written == (checkpoint_every == 1)
    assert ("the last checkpoint in" in msg) == written and ("no checkpoint was written yet" in msg) == (not written)


def test_an_exactly_zero_gradient_after_the_start_does_not_stop_the_run(tmp_path, monkeypatch):
    """Only at the start does a zero gradient mean the objective cannot depend on the gains."""
    scripted_train_step(monkeypatch, 1, grad_norm=0.0)
    state = tune(TuneConfig(controller="dfs", steps=3, **TINY), tmp_path, progress=False)
    assert state["step"] == 3


@pytest.fixture(scope="module")
def summary_from_k40(tmp_path_factory):
    cfg = TuneConfig(controller="dfs", steps=1, initial={"k": 40.0}, **TINY)
    state = tune(cfg, tmp_path_factory.mktemp("k40"), progress=False)
    return state, summarize(state)


def test_summary_scores_the_initial_and_paper_gains_on_each_batch(summary_from_k40):
    state, summary = summary_from_k40
    p = state["problem"]
    obj = summary["objective"]
    assert summary["initial_params"]["k"] == pytest.approx(40.0, rel=1e-12)
    assert obj["train"]["paper"] == pytest.approx(1.0, rel=1e-9)  # the reference (paper) scores 1 on the training batch
    initial = p.tc.to_raw(DFSParams(40.0, 0.005))
    assert obj["train"]["before"] == pytest.approx(float(p.evaluate(initial, p.train)[1]["objective"]), rel=1e-9)
    assert obj["train"]["before"] != pytest.approx(1.0, rel=1e-3)
    assert obj["heldout"]["before"] == pytest.approx(float(p.evaluate(initial, p.heldout)[1]["objective"]), rel=1e-9)
    assert obj["heldout"]["paper"] == pytest.approx(float(p.evaluate(p.paper_raw, p.heldout)[1]["objective"]), rel=1e-9)
    assert obj["heldout"]["paper"] != pytest.approx(1.0, rel=1e-6)


def test_summary_paper_radius_is_the_paper_loops(summary_from_k40):
    state, summary = summary_from_k40
    with jax.enable_x64(True):
        nominal = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")
        paper = float(stability.spectral_radius(nominal, 55.0, 5))
    assert summary["stability"]["paper_spectral_radius"] == pytest.approx(paper, rel=1e-9)


@pytest.mark.parametrize("k", [93.5, 95.0])
def test_stable_means_a_radius_below_1(summary_from_k40, k):
    """A loop just inside the unit circle (k = 93.5: radius ~0.9993) is stable; k = 95 (1.0013)
    is not: the verdict is radius < 1, whatever its distance from 1."""
    state, _ = summary_from_k40
    tc = state["problem"].tc
    summary = summarize({**state, "best_raw": tc.to_raw(DFSParams(k, 0.005))})
    st = summary["stability"]
    with jax.enable_x64(True):
        nominal = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")
        radius = float(stability.spectral_radius(nominal, k, 5))
    assert st["spectral_radius"] == pytest.approx(radius, rel=1e-9)
    assert abs(radius - 1) < 2e-3 and st["stable"] == (radius < 1)


def test_a_resume_to_fewer_steps_than_taken_is_refused_by_one_too(tmp_path, monkeypatch):
    config = TuneConfig(steps=29)
    fake_checkpoint(monkeypatch, tmp_path, config, step=30, history=[{"step": 29}])
    with pytest.raises(ValueError, match=r"has taken 30 steps already; steps = 29 cannot undo them"):
        tune(config, tmp_path, resume=True, progress=False)


def test_a_checkpoint_without_its_step_is_damaged(tmp_path, monkeypatch):
    config = TuneConfig(steps=40)
    fake_checkpoint(monkeypatch, tmp_path, config)  # the fingerprint, no step
    with pytest.raises(ValueError, match=r"is damaged or not a checkpoint of jaxflex tune \(its metadata lacks the run's fingerprint and step\)"):
        tune(config, tmp_path, resume=True, progress=False)


def test_history_csv_holds_every_column_exactly_and_is_written_at_checkpoints(tmp_path):
    """history.csv (README: step, loss, objective, penalty, val_objective, grad_norm, the
    parameters) holds each row's values exactly (a float's repr round-trips), and an interrupted
    run leaves it beside its checkpoint with the rows taken up to that checkpoint."""
    import csv

    def interrupt(step):
        if step == 3:
            raise KeyboardInterrupt

    config = TuneConfig(controller="dfs", steps=5, checkpoint_every=2, eval_every=1, **TINY)
    with pytest.raises(KeyboardInterrupt):
        tune(config, tmp_path, progress=False, on_step=interrupt)
    with open(tmp_path / "history.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [0, 1]
    state = tune(config, tmp_path, resume=True, progress=False)
    with open(tmp_path / "history.csv") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == ["step", "loss", "objective", "penalty", "val_objective", "grad_norm", "k", "tau_s"]
        rows = list(reader)
    assert len(rows) == len(state["history"]) == 6
    for row, h in zip(rows, state["history"]):
        for name, text in row.items():
            if name == "step":
                assert int(text) == h["step"]
            elif text == "":
                assert h.get(name) is None, name
            else:
                assert float(text) == h[name], name
    assert all(r["penalty"] != "" for r in rows)  # a DFS run's penalty is there, 0 where inactive


def test_dfs_plus_fuzzy_reports_its_dfs_parts_radius(tmp_path):
    """README: a dfs+fuzzy run's reported spectral radius is that of its DFS part alone."""
    state = tune(TuneConfig(controller="dfs+fuzzy", steps=1, **TINY), tmp_path, progress=False)
    summary = summarize(state)
    st = summary["stability"]
    with jax.enable_x64(True):
        nominal = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")
        from jaxflex.analysis.stability import deflated_loop_matrix

        k, tau = summary["params"]["k"], summary["params"]["tau_s"]
        radius = float(np.max(np.abs(np.linalg.eigvals(np.asarray(deflated_loop_matrix(nominal, k, tau / 1e-3, 32, "linear"))))))
        paper = float(stability.spectral_radius(nominal, 55.0, 5))
    assert st["spectral_radius"] == pytest.approx(radius, rel=1e-9)
    assert st["paper_spectral_radius"] == pytest.approx(paper, rel=1e-9)
    assert "fuzzy part of dfs+fuzzy is not included" in st["note"]


def test_any_finite_first_validation_sets_the_best(tmp_path, monkeypatch):
    """best_val starts at inf: a huge but finite first held-out value (1e31) is the best so far,
    so with patience 1 the run stops after the next (equal) one, at step 2, keeping step 0."""
    script_heldout(monkeypatch, [1e31] * 5)
    state = tune(TuneConfig(controller="dfs", steps=10, eval_every=1, patience=1, **TINY), tmp_path, progress=False)
    assert state["best_step"] == 0 and state["best_val"] == pytest.approx(1e31, rel=1e-6) and state["step"] == 2 and state["stopped_early"]


def test_a_non_finite_first_validation_counts_against_patience(tmp_path, monkeypatch):
    """An inf held-out value at step 0 is no improvement: with patience 1 the run stops there."""
    script_heldout(monkeypatch, [math.inf, 1.0, 1.0, 1.0])
    state = tune(TuneConfig(controller="dfs", steps=10, eval_every=1, patience=1, **TINY), tmp_path, progress=False)
    assert state["stopped_early"] and state["step"] == 1 and state["bad_evals"] == 1


def test_fingerprint_holds_the_program(monkeypatch):
    """README: a resumed run must have the same program (a hash of jaxflex's source, jax's and
    jaxlib's versions); after an upgrade a checkpoint is refused."""
    from jaxflex import fileio

    before = TuneConfig().fingerprint()
    monkeypatch.setattr(fileio, "program", lambda: "another program")
    assert TuneConfig().fingerprint() != before


def test_a_finished_run_resumed_with_the_same_steps_is_left_as_it_was(tmp_path, monkeypatch):
    """Held-out 5, 6, 7 over 2 updates with patience 2: the run finishes (its final point never
    stops it early); a --resume with the same steps only writes its results again: it must not
    turn into 'stopped early' nor change its history."""
    config = TuneConfig(controller="dfs", steps=2, eval_every=1, patience=2, **TINY)
    script_heldout(monkeypatch, [5.0, 6.0, 7.0])
    first = tune(config, tmp_path, progress=False)
    assert not first["stopped_early"] and first["bad_evals"] == 2
    rows = [dict(h) for h in first["history"]]
    script_heldout(monkeypatch, [])
    again = tune(config, tmp_path, resume=True, progress=False)
    assert not again["stopped_early"] and again["step"] == 2 and again["bad_evals"] == 2
    assert again["history"] == rows


def test_a_carried_final_point_off_schedule_does_not_stop_the_resumed_run(tmp_path, monkeypatch):
    """Patience 1, eval_every 2: a 1-step run ends on a worse final point (5, 6) at step 1, off
    the validation schedule. Resumed to 5 steps, the run may only stop at a scheduled
    validation (step 2, 4), as a longer run would: not at step 1."""
    config = TuneConfig(controller="dfs", steps=5, eval_every=2, patience=1, **TINY)
    script_heldout(monkeypatch, [5.0, 6.0])
    tune(dataclasses.replace(config, steps=1), tmp_path, progress=False)
    script_heldout(monkeypatch, [4.0, 4.0, 4.0])
    resumed = tune(config, tmp_path, resume=True, progress=False)
    assert [(h["step"], h.get("val_objective")) for h in resumed["history"]][:3] == [(0, 5.0), (1, 6.0), (2, 4.0)]
    assert resumed["best_step"] == 2


def test_a_resume_with_more_steps_records_its_new_target(tmp_path):
    config = TuneConfig(controller="dfs", steps=1, **TINY)
    tune(config, tmp_path, progress=False)
    assert recorded_steps(tmp_path) == 1
    tune(dataclasses.replace(config, steps=2), tmp_path, resume=True, progress=False)
    assert recorded_steps(tmp_path) == 2


def test_a_run_without_a_bar_ends_its_log_with_one_line_at_100_percent(tmp_path, capsys):
    """--no-progress: the last update's line is withheld for the final point's scores, so the
    log has one '2 of 2' line, and it holds the final point's loss."""
    state = tune(TuneConfig(controller="dfs", steps=2, **TINY), tmp_path, progress=False)
    done = [line for line in capsys.readouterr().err.splitlines() if "2 of 2 updates (100 %)" in line]
    assert len(done) == 1 and f"; loss {state['history'][-1]['loss']:.4g}," in done[0], done


def test_the_loss_is_labelled_penalised_only_with_a_stability_weight(slow_decay_problem):
    """Problem.penalised, which labels the loss curve "objective + stability penalty": DFS
    with a stability_weight above 0; with 0 the penalty adds nothing."""
    assert slow_decay_problem.penalised
    assert not Problem(TuneConfig(controller="dfs", objective=ObjectiveSpec(stability_weight=0.0), **TINY)).penalised
