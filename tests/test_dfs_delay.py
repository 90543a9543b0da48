"""tau as a differentiable DFS parameter: closed-loop gradients against finite differences
for the linear and cubic buffer reads and the Pade filter, one-sided derivatives where the
buffer reads have kinks (whole samples), convergence of the Pade loop to the buffer loop,
no retracing when tau changes, and validation.

Each jitted function is built once per module and reused (compilation dominates the cost).
"""

import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflex as jf
from jaxflex.controllers import DFSParams, dfs
from jaxflex.scenarios import paper_scenario

DT = 1e-3
STEPS = 300  # 0.3 s of the paper scenario: the transient where the tip moves most
K = 55.0
TAU_GENERIC = 0.0053  # 5.3 samples: the +-h stencils stay inside one sample interval
TAU_WHOLE = 0.005  # exactly 5 samples (0.005 / 1e-3 == 5.0 in float64): a kink of the buffer reads
RTOL_FD = 1e-5  # the brief's bar for gradients against finite differences, float64
H_REL = 1e-4  # FD step relative to the parameter: truncation ~1e-8, round-off ~1e-11 (measured)
H_REL_KINK = 1e-5  # central FD across a kink has an O(h) error (the 2nd derivative jumps too)
PADE_ORDER = 8


class Jitted(NamedTuple):
    """``value_and_grad`` of the tip ISE, with the q1 trajectory as aux, jitted once."""

    vg: Callable[[DFSParams], Any]  # -> ((loss, q1 [STEPS]), grads)
    traces: list  # [number of times the loss body was traced]

    def loss(self, k, tau):
        return float(self.vg(DFSParams(jnp.asarray(k), jnp.asarray(tau)))[0][0])

    def grad(self, k, tau):
        g = self.vg(DFSParams(jnp.asarray(k), jnp.asarray(tau)))[1]
        return float(g.k), float(g.tau_s)

    def q1(self, tau):
        return np.asarray(self.vg(DFSParams(jnp.asarray(K), jnp.asarray(tau)))[0][1])


CONTROLLERS = {
    "linear": dict(interpolation="linear"),
    "cubic": dict(interpolation="cubic"),
    "pade": dict(approximation="pade", pade_order=PADE_ORDER),
}


@pytest.fixture(scope="module")
def plant2():
    return jf.discretize(jf.make_plant(jf.BeamParams(), 2), DT, "rk4")


@pytest.fixture(scope="module")
def jitted(plant2):
    """Lazily built ``Jitted`` per controller name (module scope: compile once)."""
    cache = {}
    sc = paper_scenario(plant2, horizon_s=STEPS * DT)

    def get(name):
        if name not in cache:
            ctrl = dfs(DT, **CONTROLLERS[name])
            traces = [0]

            def loss(params):
                traces[0] += 1  # Python side effect: runs only while tracing
                traj = jf.rollout(plant2, ctrl, params, sc)
                return jnp.sum(traj.z[:, 1] ** 2) * DT, traj.x[:, 1]

            cache[name] = Jitted(jax.jit(jax.value_and_grad(loss, has_aux=True)), traces)
        return cache[name]

    return get


def _central(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def _one_sided(f, x, h):
    """Second-order one-sided difference: from above for h > 0, from below for h < 0."""
    return (-3 * f(x) + 4 * f(x + h) - f(x + 2 * h)) / (2 * h)


@pytest.mark.parametrize("name", ["linear", "cubic", "pade"])
@pytest.mark.parametrize("tau", [TAU_GENERIC, TAU_WHOLE])
def test_gradient_wrt_k_matches_central_difference(jitted, name, tau):
    """k enters linearly in u: the loss is smooth in k for every delay approximation."""
    j = jitted(name)
    gk, _ = j.grad(K, tau)
    fd = _central(lambda k: j.loss(k, tau), K, H_REL * K)
    assert gk != 0 and np.isfinite(gk)
    np.testing.assert_allclose(gk, fd, rtol=RTOL_FD)


@pytest.mark.parametrize("name", ["linear", "cubic", "pade"])
def test_gradient_wrt_tau_matches_central_difference_at_generic_tau(jitted, name):
    j = jitted(name)
    _, gt = j.grad(K, TAU_GENERIC)
    fd = _central(lambda t: j.loss(K, t), TAU_GENERIC, H_REL * TAU_GENERIC)
    assert gt != 0 and np.isfinite(gt)
    np.testing.assert_allclose(gt, fd, rtol=RTOL_FD)


def test_pade_gradient_wrt_tau_at_a_whole_sample_is_smooth(jitted):
    """The Pade loop has no kink at whole samples: central differences apply there too."""
    j = jitted("pade")
    _, gt = j.grad(K, TAU_WHOLE)
    np.testing.assert_allclose(gt, _central(lambda t: j.loss(K, t), TAU_WHOLE, H_REL * TAU_WHOLE), rtol=RTOL_FD)


@pytest.mark.parametrize("name, min_kink", [("linear", 1e-2), ("cubic", 1e-4)])
def test_gradient_wrt_tau_at_a_whole_sample_is_the_derivative_from_above(jitted, name, min_kink):
    """Buffer reads are only C0 in tau at whole samples, so the loss has a kink at tau = 5 ms.

    Honest statement: JAX returns the derivative from above (floor(d) picks the stencil of
    [5, 6) samples); it matches a one-sided difference from above to RTOL_FD. The
    derivative from below differs by more than ``min_kink`` (measured: 12 % linear,
    2.1e-4 cubic), and a central difference straddling the kink gives their mean, so it
    would *not* match the JAX gradient (by half the jump): that comparison is not made.
    """
    j = jitted(name)
    _, gt = j.grad(K, TAU_WHOLE)

    def f(t):
        return j.loss(K, t)

    h = H_REL * TAU_WHOLE
    from_above, from_below = _one_sided(f, TAU_WHOLE, h), _one_sided(f, TAU_WHOLE, -h)
    np.testing.assert_allclose(gt, from_above, rtol=RTOL_FD)
    assert abs(from_below - from_above) > min_kink * abs(from_above)
    central = _central(f, TAU_WHOLE, H_REL_KINK * TAU_WHOLE)
    np.testing.assert_allclose(central, 0.5 * (from_above + from_below), rtol=RTOL_FD)
    assert abs(central - gt) > RTOL_FD * abs(gt)


def test_changing_tau_does_not_retrace(jitted):
    for name in ("cubic", "pade"):
        j = jitted(name)
        j.loss(K, TAU_GENERIC)  # compiled here or by an earlier test
        before = j.traces[0]
        for tau in (0.0041, 0.0062, 0.0093):
            j.grad(K, tau)
        assert j.traces[0] == before == 1


def _pade_q1(plant, order, hold, tau):
    ctrl = dfs(DT, approximation="pade", pade_order=order, pade_hold=hold)
    sc = paper_scenario(plant, horizon_s=STEPS * DT)
    return np.asarray(jax.jit(lambda t: jf.rollout(plant, ctrl, DFSParams(K, t), sc).x[:, 1])(tau))


def test_pade_loop_converges_to_the_buffer_loop(plant2, jitted):
    """tau = 5 whole samples, where the buffer read is the exact delay. Max |q1 error| over
    0.3 s (max |q1| = 1e-3 m): falls with N up to N = 4, then a plateau (~1.6e-6 m, 0.16 %)
    for N = 4..12, set by the sample interpolant's images at w tau = 31, which only orders
    above ~16 follow (documented in jaxflex.pade). Orders 8 and 12 are finite."""
    exact = jitted("linear").q1(TAU_WHOLE)  # linear read at whole samples = the exact delay
    err = {}
    for order in (1, 2, 4, 8, 12):
        q1 = jitted("pade").q1(TAU_WHOLE) if order == PADE_ORDER else _pade_q1(plant2, order, "foh", TAU_WHOLE)
        assert np.all(np.isfinite(q1))
        err[order] = np.max(np.abs(q1 - exact))
    assert err[1] > 3 * err[2] > 3 * 1.5 * err[4]
    assert max(err[8], err[12]) < 1.1 * err[4] < 2.5e-6
    # With the held staircase ("zoh") the loop does not approach the buffer at all.
    err_zoh = np.max(np.abs(_pade_q1(plant2, PADE_ORDER, "zoh", TAU_WHOLE) - exact))
    assert err_zoh > 20 * err[PADE_ORDER]


def test_validation():
    with pytest.raises(ValueError, match="pade_order must be an integer in \\[1, 100\\]"):
        dfs(approximation="pade", pade_order=0)
    with pytest.raises(ValueError, match="pade_order must be an integer in \\[1, 100\\]"):
        dfs(approximation="pade", pade_order=3.0)
    with pytest.raises(ValueError, match="approximation must be one of"):
        dfs(approximation="thiran")
    with pytest.raises(ValueError, match="pade_hold must be one of"):
        dfs(approximation="pade", pade_hold="tustin")
    with pytest.raises(ValueError, match="interpolation must be one of"):
        dfs(interpolation="quintic")
    for kwargs in (dict(interpolation="linear"), dict(interpolation="cubic"), dict(approximation="pade")):
        ctrl = dfs(DT, capacity=16, **kwargs)
        for tau in (0.0, -0.001, float("nan"), float("inf")):
            with pytest.raises(ValueError, match="tau_s must be finite and > 0"):
                ctrl.check(DFSParams(K, tau))
        ctrl.check(DFSParams(K, 0.0153))  # fractional, within the buffer
        with pytest.raises(ValueError, match=r"k must be a real number; got '55'"):
            ctrl.check(DFSParams("55", 0.0153))  # NumPy would read it as 55.0; jit would not
        with pytest.raises(ValueError, match=r"params must be a DFSParams \(k, tau_s\); got dict"):
            ctrl.check({"k": K, "tau_s": 0.0153})
    for interpolation in ("linear", "cubic"):
        with pytest.raises(ValueError, match=r"tau_s must be in \(0, 0.016\]"):
            dfs(DT, capacity=16, interpolation=interpolation).check(DFSParams(K, 0.0161))
    dfs(DT, capacity=16, approximation="pade").check(DFSParams(K, 0.5))  # no capacity limit
    dfs(DT, capacity=16, interpolation="cubic").check(DFSParams(K, 0.016))  # the capacity itself
    assert 0.07 / 0.01 > 7  # 7.000000000000001: the capacity, to round-off
    dfs(0.01, capacity=7, interpolation="linear").check(DFSParams(K, 0.07))


def test_traced_tau_outside_the_buffer_is_not_clamped(jitted, plant2):
    """Under jit, check() cannot see tau: a delay beyond the buffer (or <= 0) used to be read
    clamped, silently simulating another delay; the torque is NaN instead and the run reports
    itself diverged. The buffer's own ends stay valid."""
    j = jitted("linear")  # capacity 64: tau up to 64 ms
    for tau in (0.0641, 0.5, 0.0, -0.001):
        assert math.isnan(j.loss(K, tau)), tau
    for tau in (0.064, 0.001):
        assert math.isfinite(j.loss(K, tau)) and all(math.isfinite(g) for g in j.grad(K, tau)), tau
    sc = paper_scenario(plant2, horizon_s=STEPS * DT)
    metrics = jax.jit(lambda t: jf.rollout(plant2, dfs(DT), DFSParams(K, t), sc, output="metrics"))
    assert bool(metrics(0.5).diverged) and not bool(metrics(0.005).diverged)


def test_a_traced_vector_gain_is_named_by_its_shape(plant2):
    """A vector k under jit was refused as "the controller's step must return the torque u with
    shape (1,)"; its shape is known when traced, so it is named as eagerly. vmap over k, whose
    traced k is a scalar, still runs."""
    sc = paper_scenario(plant2, horizon_s=STEPS * DT)
    run = lambda k, tau: jf.rollout(plant2, dfs(DT), DFSParams(k, tau), sc, output="metrics")  # noqa: E731
    for k, tau, name in ((jnp.array([K, 60.0]), 0.005, "k"), (K, jnp.array([0.005, 0.004]), "tau_s")):
        with pytest.raises(ValueError, match=rf"^{name} must be a scalar; got shape \(2,\) \(traced\)"):  # no $: JAX appends a note to errors raised while tracing
            jax.jit(run)(k, tau)
    assert jax.vmap(run, (0, None))(jnp.array([K, 60.0]), 0.005).peak_tip_m.shape == (2,)


def test_traced_fractional_tau_with_nearest_reads_is_not_rounded(plant2):
    """check() refuses a nearest-sample DFS delay between samples; under jit (the README's
    tour, with a tuned 2.44 ms at 1 ms) it used to be rounded to a whole sample silently, and
    is NaN instead. Whole delays, float32's 4.9999995 samples among them, still run."""
    sc = paper_scenario(plant2, horizon_s=STEPS * DT)
    metrics = jax.jit(lambda t: jf.rollout(plant2, dfs(DT), DFSParams(K, t), sc, output="metrics"))
    for tau in (0.00244, 0.0055, 0.0049):
        assert bool(metrics(tau).diverged), tau
    for tau in (0.005, np.float32(0.005), 0.001, 0.064):
        assert not bool(metrics(tau).diverged), tau
    linear = jax.jit(lambda t: jf.rollout(plant2, dfs(DT, interpolation="linear"), DFSParams(K, t), sc, output="metrics"))
    assert not bool(linear(0.00244).diverged)


def test_traced_tau_at_the_capacity_to_round_off_is_held():
    """The traced delay's bound is the buffer's capacity to round-off, as check()'s: 0.07 s
    at 0.01 s is 7.000000000000001 samples and float32's 64 ms at 1 ms 64.000003; both are
    the capacity and give the delayed angle, not a NaN torque. A whole sample beyond is NaN.
    (One controller step, tau traced: y(0) = 0.2 rad, then 0.5 rad, so the delayed angle
    is the history, 0.2 rad, and u = -k (0.5 - 0.2).)"""
    for dt, capacity, tau, beyond in ((0.01, 7, 0.07, 0.08), (1e-3, 64, np.float32(0.064), np.float32(0.065))):
        for interpolation in ("nearest", "linear", "cubic"):
            ctrl = dfs(dt, capacity=capacity, interpolation=interpolation)
            ctrl.check(DFSParams(K, tau))  # concrete: accepted

            @jax.jit
            def first_torques(tau):
                params = DFSParams(K, tau)
                state = ctrl.init(params, jnp.array([0.2, 0.0]))
                state, u0 = ctrl.step(params, state, jnp.array([0.2, 0.0]))
                return u0[0], ctrl.step(params, state, jnp.array([0.5, 0.0]))[1][0]

            u0, u1 = first_torques(tau)
            assert float(u0) == 0.0, (dt, tau, interpolation)
            np.testing.assert_allclose(float(u1), -K * (0.5 - 0.2), rtol=1e-12, err_msg=f"{dt} {tau} {interpolation}")
            assert math.isnan(float(first_torques(beyond)[1])), (dt, beyond, interpolation)
