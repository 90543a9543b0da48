"""PD-type fuzzy controller: the closed-form Mamdani centroid against scikit-fuzzy and a
brute-force numeric centroid, odd symmetry, the singleton defuzzifier, the controller under
jit/vmap, gradients against finite differences, validation and dtype preservation; then the
smooth mode (temperature > 0): NumPy references for both defuzzifiers, convergence to the
faithful surface as T -> 0, the T = 0 program, smoothness across the faithful kinks, gradients
at those kinks and through a closed loop, ranges, symmetry, NaN-free gradients, float32 and
validation."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import skfuzzy
from jax.test_util import check_grads, check_jvp, check_vjp

from jaxflex.controllers.fuzzy import (
    MAX_TEMPERATURE,
    MIN_TEMPERATURE,
    PAPER_RULES,
    SET_NAMES,
    FuzzyParams,
    fuzzy,
    fuzzy_params,
    fuzzy_surface,
    memberships,
)

PAPER_CENTRES = (-1.0, -0.5, 0.0, 0.5, 1.0)

# scikit-fuzzy reference: universe of 2001 points, step DU_SKFUZZY = 1e-3. skfuzzy's
# centroid integrates the piecewise-linear interpolant of the sampled output membership
# exactly, and the set centres and the crossings of neighbouring sets (+-0.25, +-0.75) lie on
# the grid, so its only error comes from the clip kinks that fall between two samples. Each
# such kink (slope change 2 = 2 / half-width) moves the area by at most DU^2 / 4, and the
# first moment by as much (|u| <= 1); there are at most 8 of them (at most 4 rules fire, 2
# kinks per clipped set), so the centroid error is at most
# 8 * DU^2 / 4 * (1 + |F|) / area <= KINK_BOUND * DU^2 / area with KINK_BOUND = 4, where
# area is the area under the aggregated output membership. The tolerance is that bound per
# point, capped at one universe step (the typical tolerance is ~1e-5; observed errors are
# ~16x below the bound).
N_SKFUZZY = 2001
DU_SKFUZZY = 2.0 / (N_SKFUZZY - 1)
KINK_BOUND = 4.0
# Brute-force reference: trapezoid on 200001 points (step 1e-5), the same kink model generalised
# to uneven centres (slope change 1/h_j), plus the trapezoid error on the quadratic pieces of
# u * mu (skfuzzy integrates those exactly) and float64 rounding; see _brute_tol.
N_BRUTE = 200001
ATOL_ROUND = 1e-12  # float64 rounding: a handful of operations on O(1) numbers, or 2e5-term sums
ATOL_F32 = 1e-6  # float32 against float64: a few float32 ulps of an O(1) output


def _feet(centres):
    """[n + 2] centres with the mirrored outer feet."""
    c = np.asarray(centres, dtype=np.float64)
    return np.concatenate([[2 * c[0] - c[1]], c, [2 * c[-1] - c[-2]]])


def _rule_strengths_np(e, e_dot, rules, angle_centres, velocity_centres):
    """[n_rules] firing strengths in numpy (np.interp triangles), inputs clipped."""
    ma, mv = [], []
    for x, c, out in ((e, angle_centres, ma), (e_dot, velocity_centres, mv)):
        x = np.clip(x, c[0], c[-1])
        feet = _feet(c)
        for j in range(len(c)):
            out.append(np.interp(x, feet[j : j + 3], [0.0, 1.0, 0.0]))
    return np.array([min(ma[SET_NAMES.index(a)], mv[SET_NAMES.index(v)]) for a, v, _ in rules])


# -- 0. memberships ----------------------------------------------------------------------------


def test_memberships_are_skfuzzy_trimf_and_a_partition_of_unity():
    centres = np.array([-1.3, -0.4, 0.1, 0.35, 1.2])  # uneven on purpose
    feet = _feet(centres)
    x = np.linspace(-2.0, 2.0, 801)
    mu = np.asarray(jax.vmap(lambda xi: memberships(xi, jnp.asarray(centres)))(jnp.asarray(x)))  # [801, 5]
    x_clipped = np.clip(x, centres[0], centres[-1])
    for j in range(5):
        np.testing.assert_allclose(
            mu[:, j], skfuzzy.trimf(x_clipped, list(feet[j : j + 3])), rtol=0, atol=ATOL_ROUND
        )
    np.testing.assert_allclose(mu.sum(axis=1), 1.0, rtol=0, atol=ATOL_ROUND)
    np.testing.assert_array_equal(np.asarray(memberships(0.1, jnp.asarray(centres))), [0, 0, 1, 0, 0])


# -- 1. scikit-fuzzy -------------------------------------------------------------------------


def _skfuzzy_mamdani(e, e_dot, universe, mfs):
    """Mamdani min/min/max with skfuzzy's membership, fuzzy ops and centroid.

    Returns (centroid, area under the aggregated membership), or (nan, 0) when no rule fires.
    """
    mu_angle = {n: skfuzzy.interp_membership(universe, mfs[n], e) for n in SET_NAMES}
    mu_vel = {n: skfuzzy.interp_membership(universe, mfs[n], e_dot) for n in SET_NAMES}
    aggregated = np.zeros_like(universe)
    for a, v, t in PAPER_RULES:
        strength = np.fmin(mu_angle[a], mu_vel[v])
        aggregated = np.fmax(aggregated, np.fmin(strength, mfs[t]))
    area = np.trapezoid(aggregated, universe)
    if not area > 0:
        return np.nan, 0.0
    return skfuzzy.defuzz(universe, aggregated, "centroid"), area


def test_against_skfuzzy():
    universe = np.linspace(-1.0, 1.0, N_SKFUZZY)
    feet = _feet(PAPER_CENTRES)
    mfs = {n: skfuzzy.trimf(universe, list(feet[j : j + 3])) for j, n in enumerate(SET_NAMES)}
    rng = np.random.default_rng(0)
    pairs = rng.uniform(-1.0, 1.0, size=(1000, 2))

    ref, area = np.array([_skfuzzy_mamdani(e, ed, universe, mfs) for e, ed in pairs]).T
    params = fuzzy_params()
    ours = np.asarray(jax.jit(jax.vmap(lambda e, ed: fuzzy_surface(params, e, ed)))(pairs[:, 0], pairs[:, 1]))

    fires = area > 0
    assert 50 < np.sum(~fires) < 500  # the two corners (0.5, 1]^2 and [-1, -0.5)^2 fire nothing
    np.testing.assert_array_equal(ours[~fires], 0.0)
    tol = np.minimum(KINK_BOUND * DU_SKFUZZY**2 / area[fires], DU_SKFUZZY)
    err = np.abs(ours[fires] - ref[fires])
    assert np.all(err <= tol), f"max error {err.max():.3g}; worst err/tol {np.max(err / tol):.3g}"
    assert np.max(np.abs(ref[fires])) > 0.5  # the comparison covers a non-trivial range


# -- 2. odd symmetry -------------------------------------------------------------------------


@pytest.mark.parametrize("defuzz", ["centroid", "singleton"])
def test_odd_symmetry(defuzz):
    params = fuzzy_params()
    grid = jnp.linspace(-1.2, 1.2, 49)
    e, ed = jnp.meshgrid(grid, grid, indexing="ij")
    surface = jax.jit(jax.vmap(jax.vmap(lambda a, b: fuzzy_surface(params, a, b, defuzz=defuzz))))
    f = np.asarray(surface(e, ed))
    f_mirror = np.asarray(surface(-e, -ed))
    np.testing.assert_allclose(f_mirror, -f, rtol=0, atol=ATOL_ROUND)
    assert np.max(np.abs(f)) > 0.5  # not trivially zero


# -- 3. exact closed form against a brute-force centroid ------------------------------------


def _brute_centroid(e, e_dot, rules, angle_centres, velocity_centres, torque_centres):
    """Numeric Mamdani centroid on a fine grid (trapezoid); returns (centroid, area)."""
    w = _rule_strengths_np(e, e_dot, rules, angle_centres, velocity_centres)
    u = np.linspace(torque_centres[0], torque_centres[-1], N_BRUTE)
    feet = _feet(torque_centres)
    aggregated = np.zeros_like(u)
    for w_r, (_, _, t) in zip(w, rules):
        j = SET_NAMES.index(t)
        aggregated = np.maximum(aggregated, np.minimum(w_r, np.interp(u, feet[j : j + 3], [0.0, 1.0, 0.0])))
    area = np.trapezoid(aggregated, u)
    if not area > 0:
        return 0.0, 0.0
    return np.trapezoid(u * aggregated, u) / area, area


def _brute_tol(area, torque_centres):
    """Error bound of the brute-force centroid (see the constants at the top), plus rounding."""
    c = np.asarray(torque_centres)
    du = (c[-1] - c[0]) / (N_BRUTE - 1)
    kinks = 2 * du**2 * np.max(np.abs(c)) / np.min(np.diff(c))  # <= 8 kinks, slope change 1/h
    smooth = 2 * du**2  # trapezoid on the quadratic pieces of u * mu: du^2 / 12 * int |(u mu)''|
    return (kinks + smooth) / area + ATOL_ROUND


def test_closed_form_centroid_against_brute_force():
    rng = np.random.default_rng(1)
    n_fired = 0
    for trial in range(40):
        if trial < 20:
            params = fuzzy_params()
        else:  # uneven widths, shifted universes: exercises h_j and c_j in the closed form
            centres = [np.sort(rng.uniform(-2.0, 2.0, 5)) for _ in range(3)]
            params = fuzzy_params()._replace(
                angle_centres=jnp.asarray(centres[0]),
                velocity_centres=jnp.asarray(centres[1]),
                torque_centres=jnp.asarray(centres[2]),
            )
        cs = [np.asarray(c) for c in params[3:]]
        e = rng.uniform(cs[0][0], cs[0][-1])
        ed = rng.uniform(cs[1][0], cs[1][-1])
        ref, area = _brute_centroid(e, ed, PAPER_RULES, *cs)
        ours = float(fuzzy_surface(params, e, ed))
        if area == 0:
            assert ours == 0.0
            continue
        n_fired += 1
        assert abs(ours - ref) <= _brute_tol(area, cs[2]), (trial, e, ed, ours, ref)
    assert n_fired >= 30


def test_closed_form_with_random_rule_tables():
    """Random rule tables reach clip-level pairs the paper's table does not, e.g. two
    neighbouring output sets at the same level above 1/2 (a rule repeated with a neighbouring
    consequent) and several rules sharing a consequent (the segment max)."""
    rng = np.random.default_rng(2)
    params = fuzzy_params()
    cs = [np.asarray(c) for c in params[3:]]
    for _ in range(30):
        rules = [tuple(SET_NAMES[i] for i in rng.integers(0, 5, size=3)) for _ in range(8)]
        a, v, t = rules[0]
        neighbour = SET_NAMES[SET_NAMES.index(t) + 1 if t != "PM" else 3]
        rules.append((a, v, neighbour))
        rules = tuple(rules)
        e = rng.uniform(-1.0, 1.0)
        ed = rng.uniform(-1.0, 1.0)
        ref, area = _brute_centroid(e, ed, rules, *cs)
        ours = float(fuzzy_surface(params, e, ed, rules=rules))
        if area == 0:
            assert ours == 0.0
        else:
            assert abs(ours - ref) <= _brute_tol(area, cs[2]), (rules, e, ed, ours, ref)
    # Deterministic high-level case: a = b = 0.9 on [0, 0.5] (cc = 1/2 branch).
    rules = (("ZE", "ZE", "ZE"), ("ZE", "ZE", "PS"))
    ref, area = _brute_centroid(0.05, 0.0, rules, *cs)
    assert abs(float(fuzzy_surface(params, 0.05, 0.0, rules=rules)) - ref) <= _brute_tol(area, cs[2])


# -- 4. singleton ------------------------------------------------------------------------------


def test_singleton_against_numpy():
    c = np.asarray(PAPER_CENTRES)
    # Each universe its own centres, so that a surface reading another universe's sets fails.
    angle_c, velocity_c, torque_c = c * 1.1, np.array([-0.9, -0.55, 0.05, 0.4, 1.05]), np.array([-1.04, -0.51, 0.01, 0.49, 1.02])
    params = fuzzy_params()._replace(angle_centres=jnp.asarray(angle_c), velocity_centres=jnp.asarray(velocity_c), torque_centres=jnp.asarray(torque_c))
    consequent_centres = np.array([torque_c[SET_NAMES.index(t)] for _, _, t in PAPER_RULES])
    rng = np.random.default_rng(3)
    pairs = rng.uniform(-1.0, 1.0, size=(200, 2))
    # All 200 points in one compiled call (200 op-by-op evaluations take longer).
    surface = jax.jit(jax.vmap(lambda e, ed: fuzzy_surface(params, e, ed, defuzz="singleton")))
    ours_all = np.asarray(surface(pairs[:, 0], pairs[:, 1]))
    n_fired = 0
    for (e, ed), ours in zip(pairs, ours_all):
        w = _rule_strengths_np(e, ed, PAPER_RULES, angle_c, velocity_c)
        expected = np.sum(w * consequent_centres) / np.sum(w) if np.sum(w) > 0 else 0.0
        n_fired += np.sum(w) > 0
        np.testing.assert_allclose(ours, expected, rtol=0, atol=ATOL_ROUND)
    assert 100 < n_fired < 200
    # A hand-checked point: e = -0.25 is half NS, half ZE; e_dot = 0 is ZE. Rules 2 (NS,ZE->PS)
    # and 6 (ZE,ZE->ZE) fire at 0.5 each: (0.5 * 0.5 + 0.5 * 0) / 1 = 0.25.
    assert float(fuzzy_surface(fuzzy_params(), -0.25, 0.0, defuzz="singleton")) == pytest.approx(0.25, abs=ATOL_ROUND)


# -- 5. controller -----------------------------------------------------------------------------


def test_controller_step_jit_vmap_and_clipping():
    controller = fuzzy()
    params = fuzzy_params(k1=1.3, k2=0.7, k3=2.5)
    controller.check(params)
    y = jnp.array([0.21, -0.9])
    state = controller.init(params, y)
    assert state == ()
    state, u = controller.step(params, state, y)
    assert state == () and u.shape == (1,)
    expected = 2.5 * fuzzy_surface(params, 1.3 * 0.21, 0.7 * -0.9)
    np.testing.assert_allclose(u[0], expected, rtol=0, atol=ATOL_ROUND)
    assert abs(float(u[0])) > 0.1

    # Restoring: a negative angle at rest gives a positive torque.
    _, u_neg = controller.step(params, (), jnp.array([-0.4, 0.0]))
    assert float(u_neg[0]) > 0
    # k3 scales the torque with its sign: check() takes a negative k3, and u = k3 F flips
    controller.check(params._replace(k3=-2.5))
    _, u_flipped = controller.step(params._replace(k3=-2.5), (), y)
    np.testing.assert_allclose(u_flipped[0], -u[0], rtol=0, atol=ATOL_ROUND)

    ys = jnp.asarray(np.random.default_rng(4).uniform(-1.5, 1.5, size=(16, 2)))
    step = lambda y: controller.step(params, (), y)[1]  # noqa: E731
    with jax.disable_jit():
        eager = np.stack([np.asarray(step(yi)) for yi in ys])
    step_jit = jax.jit(step)
    jitted = np.stack([np.asarray(step_jit(yi)) for yi in ys])
    batched = np.asarray(jax.jit(jax.vmap(step))(ys))
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=ATOL_ROUND)
    np.testing.assert_allclose(batched, eager, rtol=0, atol=ATOL_ROUND)
    assert batched.shape == (16, 1)

    # Inputs outside the universe are clipped to it.
    for e, ed, e_in, ed_in in ((5.0, 0.1, 1.0, 0.1), (-3.0, 0.2, -1.0, 0.2), (0.1, -7.0, 0.1, -1.0)):
        clipped = float(fuzzy_surface(params, e, ed))
        assert clipped == float(fuzzy_surface(params, e_in, ed_in))
        assert clipped != 0.0


# -- 6. gradients ------------------------------------------------------------------------------

# Generic measurements (rad, rad/s): away from set centres, rule ties and universe edges.
_GRAD_YS = np.array([[0.131, -0.274], [-0.317, 0.0731], [0.0423, 0.583], [-0.162, -0.811], [0.377, 0.046]])


def _loss(params, defuzz="centroid"):
    controller = fuzzy(defuzz=defuzz)
    u = jax.vmap(lambda y: controller.step(params, (), y)[1])(jnp.asarray(_GRAD_YS))
    return jnp.sum(u**2) + jnp.sum(u)


@pytest.mark.parametrize("defuzz", ["centroid", "singleton"])
def test_gradients_against_finite_differences(defuzz):
    params = fuzzy_params(k1=1.02, k2=0.30, k3=1.0)._replace(
        angle_centres=jnp.array([-1.1, -0.47, 0.03, 0.52, 0.96]),
        velocity_centres=jnp.array([-0.9, -0.55, -0.02, 0.48, 1.05]),
        torque_centres=jnp.array([-1.04, -0.51, 0.01, 0.49, 1.02]),
    )
    loss = jax.jit(lambda p: _loss(p, defuzz))
    check_grads(loss, (params,), order=1, modes=["fwd", "rev"], eps=1e-6)
    grads = jax.grad(loss)(params)  # the reverse pass check_grads compiled, reused
    for leaf in jax.tree.leaves(grads):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert all(abs(float(g)) > 1e-3 for g in (grads.k1, grads.k2, grads.k3))


@pytest.mark.parametrize("defuzz", ["centroid", "singleton"])
def test_gradient_finite_where_no_rule_fires(defuzz):
    params = fuzzy_params()
    controller = fuzzy(defuzz=defuzz)
    y = jnp.array([0.8, 2.9])  # e = 0.816, e_dot = 0.87: angle PS/PM, velocity PS/PM, no rule
    assert float(controller.step(params, (), y)[1][0]) == 0.0

    def loss(p):
        return controller.step(p, (), y)[1][0]

    grads = jax.jit(jax.grad(loss))(params)
    for leaf in jax.tree.leaves(grads):
        assert np.all(np.isfinite(np.asarray(leaf)))
    grads_e = jax.jit(jax.grad(lambda e: fuzzy_surface(params, e, 0.87, defuzz=defuzz)))(0.816)
    assert np.isfinite(float(grads_e))


def test_the_documented_gradient_at_a_set_centre_tie():
    """What the module docstring and the README state about an input exactly on a set centre:
    both one-sided derivatives agree there (the derivative exists), but reverse mode splits
    each tied min/max half and half and returns something else: -0.375 against the slope
    -1.5 at the origin; on the paper scenario from rest, whose first sample is there, a
    quarter of the derivative in ``angle_centres[2]`` and 6 % less in ``velocity_centres[2]``.
    Moved off the tie (the same centre at +-0.01) the gradient is the derivative, and the
    centres no first sample ties (the torque centres) are exact: the tie, not the code."""
    from jaxflex import BeamParams, discretize, make_plant, paper_scenario, rollout

    unit = fuzzy_params(k1=1.0, k2=1.0, k3=1.0)
    h = 1e-6
    for f in (lambda x: fuzzy_surface(unit, x, 0.0), lambda x: fuzzy_surface(unit, 0.0, x)):
        above, below = (f(h) - f(0.0)) / h, (f(0.0) - f(-h)) / h
        np.testing.assert_allclose([above, below], -1.5, rtol=1e-5)
        assert float(jax.grad(f)(0.0)) == -0.375

    plant = discretize(make_plant(BeamParams(), 2), 1e-3, "rk4")
    scenario = paper_scenario(plant, horizon_s=0.04)
    params = fuzzy_params()

    def ise_in(name, i):
        def ise(c):
            centres = getattr(params, name).at[i].set(c)
            return rollout(plant, fuzzy(), params._replace(**{name: centres}), scenario, output="metrics").tip_ise

        return jax.jit(ise), jax.jit(jax.grad(ise))

    h = 1e-6
    for name, i, ratio in (("angle_centres", 2, 0.25), ("velocity_centres", 2, 0.9402), ("torque_centres", 2, 1.0)):
        ise, grad = ise_in(name, i)
        c0 = float(getattr(params, name)[i])
        # second-order one-sided differences (truncation O(h^2)), from above and from below
        above = (4 * ise(c0 + h) - ise(c0 + 2 * h) - 3 * ise(c0)) / (2 * h)
        below = (3 * ise(c0) - 4 * ise(c0 - h) + ise(c0 - 2 * h)) / (2 * h)
        np.testing.assert_allclose(below, above, rtol=1e-6)
        np.testing.assert_allclose(grad(c0) / above, ratio, rtol=1e-4)
        for off in (0.01, -0.01):
            if name != "torque_centres":
                difference = (ise(off + h) - ise(off - h)) / (2 * h)
                np.testing.assert_allclose(grad(off), difference, rtol=1e-6)


@pytest.mark.parametrize("defuzz, temperature", [("centroid", 0.0), ("singleton", 0.0), ("centroid", 0.02)])
def test_a_nan_measurement_gives_a_nan_torque_and_a_diverged_run(defuzz, temperature):
    """A NaN input made every rule strength NaN, and the no-rule guard (den > 0) turned the
    ratio into 0: the loop ran open loop under jit, reporting itself not diverged."""
    import jaxflex as jf

    params = fuzzy_params()
    for e, e_dot in ((jnp.nan, 0.0), (0.1, jnp.nan)):
        assert np.isnan(float(fuzzy_surface(params, e, e_dot, defuzz=defuzz, temperature=temperature)))
    plant = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3)
    scenario = jf.paper_scenario(plant, horizon_s=0.2)
    controller = fuzzy(defuzz=defuzz, temperature=temperature)
    run = jax.jit(lambda noise: jf.rollout(plant, controller, params, scenario._replace(noise=noise), output="metrics"))
    assert not bool(run(scenario.noise).diverged)
    assert bool(run(scenario.noise.at[50, 0].set(jnp.nan)).diverged)



@pytest.mark.parametrize("defuzz", ["centroid", "singleton"])
def test_traced_centres_that_check_refuses_give_a_nan_surface(defuzz):
    """Traced centres are not checked, and the select min and max drop a NaN in one argument
    (a NaN centre, or inf - inf and 0 / 0 in the memberships of infinite or equal centres gave
    a finite torque with them), so the surface tests the centres itself: NaN, infinite, equal
    or decreasing neighbours give NaN, for the input on a centre or between centres."""
    params = fuzzy_params()
    surface = jax.jit(lambda p, e, e_dot: fuzzy_surface(p, e, e_dot, defuzz=defuzz))
    points = ((0.3, -0.2), (-0.8, 0.6), (0.0, 0.0), (-0.5, -0.5))
    for field in ("angle_centres", "velocity_centres", "torque_centres"):
        c = getattr(params, field)
        bad = [c.at[i].set(v) for i in range(5) for v in (jnp.nan, jnp.inf, -jnp.inf)]
        bad += [c.at[i + 1].set(c[i]) for i in range(4)] + [c.at[i + 1].set(c[i] - 0.1) for i in range(4)]
        for centres in bad:
            for e, e_dot in points:
                assert np.isnan(float(surface(params._replace(**{field: centres}), e, e_dot))), (field, centres, e, e_dot)
    for e, e_dot in points:
        assert np.isfinite(float(surface(params, e, e_dot)))


def test_select_min_and_max_are_the_exact_ops_in_value_and_derivative():
    """The faithful surface's min and max are compare-and-select (one x86 instruction) with
    the derivative of jnp.minimum / jnp.maximum: equal values (a zero's sign aside), half
    and half at a tie, and the NaN of the first argument kept."""
    from jaxflex.controllers.fuzzy import _select_max, _select_min

    v = np.array([-np.inf, -2.0, -0.0, 0.0, 0.5, 3.0, np.inf])
    a, b = (x.ravel() for x in np.meshgrid(v, v))
    for select, exact in ((_select_min, jnp.minimum), (_select_max, jnp.maximum)):
        np.testing.assert_array_equal(jax.jit(select)(a, b), exact(a, b))
        for ta, tb in ((1.0, 0.0), (0.0, 1.0), (0.3, -1.7)):
            tangents = (jnp.full_like(a, ta), jnp.full_like(b, tb))
            _, got = jax.jvp(select, (a, b), tangents)
            _, want = jax.jvp(exact, (a, b), tangents)
            np.testing.assert_array_equal(got, want)
        grad = jax.grad(lambda x, y: select(x, y), argnums=(0, 1))
        assert grad(0.25, 0.25) == (0.5, 0.5)
        assert grad(0.25, 0.75) == ((1.0, 0.0) if exact is jnp.minimum else (0.0, 1.0))
        assert np.isnan(float(select(jnp.nan, 0.5)))

# -- 7. validation -----------------------------------------------------------------------------


def test_validation():
    with pytest.raises(ValueError, match=r"rules must hold at least one .* triple"):
        fuzzy(rules=[])
    with pytest.raises(ValueError, match=r"rule 1 names unknown set 'XX'.*accepted names.*NM"):
        fuzzy(rules=(("NM", "ZE", "PM"), ("XX", "ZE", "PS")))
    with pytest.raises(ValueError, match=r"rule 0 must be an \(angle, velocity, torque\) triple"):
        fuzzy(rules=(("NM", "ZE"),))
    with pytest.raises(ValueError, match=r"rule 0 must be"):
        fuzzy(rules=("NMZEPM",))
    with pytest.raises(ValueError, match=r"rule 2 names unknown set"):
        fuzzy_surface(fuzzy_params(), 0.0, 0.0, rules=PAPER_RULES[:2] + (("ZE", "ZE", "BIG"),))
    with pytest.raises(ValueError, match="defuzz"):
        fuzzy(defuzz="bisector")
    with pytest.raises(ValueError, match="defuzz"):
        fuzzy_surface(fuzzy_params(), 0.0, 0.0, defuzz="mom")

    check = fuzzy().check
    check(fuzzy_params())
    with pytest.raises(ValueError, match=r"k1 must be finite and > 0"):
        check(fuzzy_params(k1=0.0))
    with pytest.raises(ValueError, match=r"k1 must be finite and > 0"):
        check(fuzzy_params(k1=-1.0))
    with pytest.raises(ValueError, match=r"k2 must be finite and > 0"):
        check(fuzzy_params(k2=float("nan")))
    with pytest.raises(ValueError, match=r"k3 must be finite"):
        check(fuzzy_params(k3=float("inf")))
    with pytest.raises(ValueError, match=r"angle_centres must have shape \(5,\).*strictly increasing"):
        check(fuzzy_params()._replace(angle_centres=jnp.array([-1.0, -0.5, -0.5, 0.5, 1.0])))
    with pytest.raises(ValueError, match=r"torque_centres must have shape \(5,\).*strictly increasing"):
        check(fuzzy_params()._replace(torque_centres=jnp.array([1.0, 0.5, 0.0, -0.5, -1.0])))
    with pytest.raises(ValueError, match=r"velocity_centres must have shape \(5,\)"):
        check(fuzzy_params()._replace(velocity_centres=jnp.array([-1.0, 0.0, 1.0])))
    with pytest.raises(ValueError, match=r"velocity_centres .*finite"):
        check(fuzzy_params()._replace(velocity_centres=jnp.array([-1.0, -0.5, 0.0, 0.5, jnp.nan])))
    # an infinite outer centre still increases (np.diff gives inf > 0): refused as not finite
    with pytest.raises(ValueError, match=r"torque_centres .*finite"):
        check(fuzzy_params()._replace(torque_centres=jnp.array([-1.0, -0.5, 0.0, 0.5, jnp.inf])))
    for centres in ((-np.inf, -0.5, 0.0, 0.5, 1.0), (-1.0, -0.5, 0.0, 0.5, np.inf)):
        with pytest.raises(ValueError, match=r"centres .*finite"):
            fuzzy_params(centres=centres)
    # a string is named, whether NumPy could read it as a number or not
    with pytest.raises(ValueError, match=r"k1 must be a real number; got 'a'"):
        fuzzy_params("a")
    with pytest.raises(ValueError, match=r"k3 must be a real number; got '1\.0'"):
        fuzzy_params(k3="1.0")
    with pytest.raises(ValueError, match=r"centres must be a real number or an array of real numbers"):
        fuzzy_params(centres=("-1", "-0.5", "0", "0.5", "1"))
    # a value beyond the dtype's range is named with that range: cast, it became infinite and
    # `check` refused "[-inf, -1.0, ...]", which the caller had not given
    with pytest.raises(ValueError, match=r"centres must lie in \[-3\.403e\+38, 3\.403e\+38\] to be held in float32.*got \[-1e\+39, -1, 0, 1, 1e\+39\]"):
        fuzzy_params(centres=[-1e39, -1, 0, 1, 1e39], dtype=jnp.float32)
    with pytest.raises(ValueError, match=r"k3 must lie in .* to be held in bfloat16"):
        fuzzy_params(k3=-1e39, dtype=jnp.bfloat16)
    assert float(fuzzy_params(k3=1e39).k3) == 1e39  # float64 holds it
    # centres that no controller can use are refused here, by this argument's name (they were
    # taken, and refused later as "angle_centres", a name the caller had not given)
    with pytest.raises(ValueError, match=re.escape("centres must be a 1-D array of at least 2 set centres; got shape (1,)")):
        fuzzy_params(centres=[0.0])
    with pytest.raises(ValueError, match=re.escape("centres must have shape (3,), be finite and strictly increasing; got [-1.0, 0.0, 0.0]")):
        fuzzy_params(centres=[-1.0, 0.0, 0.0])
    # traced values are built as they are (checked where used), and bfloat16 is a real dtype
    assert float(jax.jit(lambda k: fuzzy_params(k, 0.3).k1)(2.0)) == 2.0
    assert float(jax.grad(lambda k: 3.0 * fuzzy_params(k).k1)(1.0)) == 3.0
    assert jax.vmap(lambda c: fuzzy_params(centres=c).angle_centres)(jnp.ones((2, 5))).shape == (2, 5)
    check(fuzzy_params(dtype=jnp.bfloat16))
    with pytest.raises(ValueError, match=r"k2 must be a real number; got True"):
        check(fuzzy_params()._replace(k2=True))
    with pytest.raises(ValueError, match=r"angle_centres must be an array \(jnp.asarray\(\.\.\.\), or build the parameters with fuzzy_params\(centres=\.\.\.\)\); got tuple"):
        check(fuzzy_params()._replace(angle_centres=("a",) * 5))
    with pytest.raises(ValueError, match=r"angle_centres must be a real number or an array"):
        check(fuzzy_params()._replace(angle_centres=np.array(["a"] * 5)))
    # the public surface and memberships check the centres too (decreasing ones gave 0 silently)
    with pytest.raises(ValueError, match=r"torque_centres must have shape \(5,\).*strictly increasing"):
        fuzzy_surface(fuzzy_params()._replace(torque_centres=jnp.array([1.0, 0.5, 0.0, -0.5, -1.0])), 0.3, 0.1)
    with pytest.raises(ValueError, match=r"centres must have shape \(3,\).*strictly increasing"):
        memberships(0.2, jnp.array([1.0, 0.0, -1.0]))
    with pytest.raises(ValueError, match="centres must be a 1-D array of at least 2"):
        memberships(0.2, jnp.array([[0.0, 1.0]]))


# -- 8. float32 --------------------------------------------------------------------------------


@pytest.mark.parametrize("defuzz", ["centroid", "singleton"])
def test_float32_preserved(defuzz):
    params32 = fuzzy_params(dtype=jnp.float32)
    assert all(leaf.dtype == jnp.float32 for leaf in params32)
    y32 = jnp.array([0.21, -0.9], dtype=jnp.float32)
    _, u = fuzzy(defuzz=defuzz).step(params32, (), y32)
    assert u.dtype == jnp.float32 and u.shape == (1,)
    _, u64 = fuzzy(defuzz=defuzz).step(fuzzy_params(), (), y32.astype(jnp.float64))
    np.testing.assert_allclose(float(u[0]), float(u64[0]), rtol=0, atol=ATOL_F32)
    f = fuzzy_surface(params32, jnp.float32(0.3), jnp.float32(-0.2), defuzz=defuzz)
    assert f.dtype == jnp.float32
    # float32 centres with float64 inputs compute in float64, the result type of the two (the
    # paper's centres are exact in float32, so the float64 centres' surface is the reference)
    e, e_dot = jnp.float64(0.123456789), jnp.float64(-0.0372)
    mixed = fuzzy_surface(params32, e, e_dot, defuzz=defuzz)
    assert mixed.dtype == jnp.float64
    np.testing.assert_allclose(mixed, fuzzy_surface(fuzzy_params(), e, e_dot, defuzz=defuzz), rtol=0, atol=ATOL_ROUND)
    assert abs(float(mixed) - float(f)) > 0  # another point than the float32 one above
    assert isinstance(params32, FuzzyParams)


# -- 9. smooth mode (temperature > 0) ----------------------------------------------------------

CONVERGENCE_TEMPERATURES = (0.1, 0.03, 0.01, 0.003, 0.001)
T_GRAD = 0.02  # a temperature in the recommended range 0.01-0.05, for gradient checks
# Convergence on the 101 x 101 grid of the square, every point but the faithful surface's
# jumps (below). Observed max |F_T - F|: 5.75 T, 16.1 T, 29.1 T, 38.6 T, 43.1 T for
# CONVERGENCE_TEMPERATURES; the constant settles near 45 (45.4 T at T = 1e-4). The error is
# about T / (what fires): the worst points lie next to the faithful jumps, where the faithful
# controller fires only 0.04 (e.g. (-1, 0.48)). C_GRID bounds it with ~10 % margin.
C_GRID = 50.0
# Where some rule fires with strength >= 0.1 and |e|, |e_dot| <= 0.9 (away from the universe
# edges, whose smooth clip moves the input by T log 2): observed 1.15-1.54 T.
C_BULK = 2.0
W_BULK = 0.1
# Faithful jumps: grid points whose faithful value changes by more than JUMP_MIN when the
# input moves by JUMP_PROBE (observed: 0.5-0.75 at the 106 jumps, <= 8e-8 elsewhere). They
# are points where no rule fires next to points where some do (the edges of the no-rule
# corners [0.5, 1]^2 and [-1, -0.5]^2, and isolated points such as (-0.5, 1)); no continuous
# surface converges to a jump uniformly.
JUMP_PROBE = 1e-9
JUMP_MIN = 1e-3
ATOL_NO_RULE = 1e-12  # T = 0.001 where no rule fires: strengths ~ exp(-0.04 / T) vs T^2; observed 2e-15
# Smoothness: |grad(x + d) - grad(x - d)| <= C_CURVATURE * 2 d / T across a faithful kink
# (the Hessian is O(1 / T); observed constant 0.6-1.0); the faithful jumps are >= 1.
KINK_STEP = 1e-7
C_CURVATURE = 2.0
FAITHFUL_KINK_JUMP = 1.0
# Central differences in float64 on a C-infinity loss with curvature ~1/T = 50: truncation
# ~EPS_FD^2 / T^2 ~ 1e-9, rounding ~1e-16 / EPS_FD = 1e-10, relative to O(1) derivatives.
EPS_FD = 1e-6
RTOL_FD_SMOOTH = 1e-6
ATOL_FD_SMOOTH = 1e-9  # the losses are O(1): relative tolerance dominates
# float32 against float64 in the smooth mode: rounding of the arguments x / T of softplus and
# sigmoid is amplified by ~1 / T (observed 9e-6 at T = 0.02 on a grid).
ATOL_F32_SMOOTH = 5e-5


def _surface_fn(params, temperature, **kwargs):
    """Jitted vectorised surface over flat arrays of (e, e_dot)."""
    return jax.jit(jax.vmap(lambda e, ed: fuzzy_surface(params, e, ed, temperature=temperature, **kwargs)))


def _max_strength_np(e, e_dot):
    """[...] largest faithful firing strength of the paper's rules (numpy, np.interp triangles)."""
    feet = _feet(PAPER_CENTRES)
    mu = {}
    for var, x in (("a", np.clip(e, -1.0, 1.0)), ("v", np.clip(e_dot, -1.0, 1.0))):
        for j, name in enumerate(SET_NAMES):
            mu[var, name] = np.interp(x, feet[j : j + 3], [0.0, 1.0, 0.0])
    return np.max([np.minimum(mu["a", a], mu["v", v]) for a, v, _ in PAPER_RULES], axis=0)


def test_smooth_surface_converges_to_faithful():
    params = fuzzy_params()
    grid = np.linspace(-1.0, 1.0, 101)
    e, ed = (a.ravel() for a in np.meshgrid(grid, grid, indexing="ij"))
    faithful_fn = _surface_fn(params, 0.0)
    faithful = np.asarray(faithful_fn(e, ed))

    probes = [(s1, s2) for s1 in (-JUMP_PROBE, 0.0, JUMP_PROBE) for s2 in (-JUMP_PROBE, 0.0, JUMP_PROBE)]
    moved = np.max([np.abs(np.asarray(faithful_fn(e + s1, ed + s2)) - faithful) for s1, s2 in probes], axis=0)
    jump = moved > JUMP_MIN
    strength = _max_strength_np(e, ed)
    no_rule = strength == 0
    assert np.all(no_rule[jump])  # the faithful surface jumps only where nothing fires ...
    assert 50 < np.sum(jump) < 0.02 * e.size  # ... on a small set (106 of the 10201 points)
    assert np.sum(no_rule & ~jump) > 1000  # the no-rule corners themselves are kept
    bulk = (strength >= W_BULK) & (np.abs(e) <= 0.9) & (np.abs(ed) <= 0.9)

    errs, bulk_errs = [], []
    for t in CONVERGENCE_TEMPERATURES:
        smooth = np.asarray(_surface_fn(params, t)(e, ed))
        diff = np.abs(smooth - faithful)
        errs.append(diff[~jump].max())
        bulk_errs.append(diff[bulk].max())
        assert errs[-1] <= C_GRID * t, (t, errs[-1] / t)
        assert bulk_errs[-1] <= C_BULK * t, (t, bulk_errs[-1] / t)
    assert np.all(np.diff(errs) < 0), errs  # monotone in T
    # O(T), not slower (sqrt(T), T log(1/T)): from T = 0.003 to 0.001 the bulk error falls by
    # 3^1.01 (observed), the error over the grid by 3^0.90.
    assert np.log(bulk_errs[-2] / bulk_errs[-1]) / np.log(3.0) == pytest.approx(1.0, abs=0.1)
    assert np.log(errs[-2] / errs[-1]) / np.log(3.0) > 0.85
    # Where no rule fires (off the jumps) the smooth output goes to the faithful 0.
    assert np.max(np.abs(smooth[no_rule & ~jump])) <= ATOL_NO_RULE


# The smooth singleton average against the faithful one, where a rule fires with >= W_BULK and
# |e|, |e_dot| <= 0.9: observed 2.54, 4.25, 4.86, 5.09, 5.16 T for CONVERGENCE_TEMPERATURES
# (the AND's O(T) error over a sum of strengths, not an area: larger than the centroid's).
C_BULK_SINGLETON = 6.0


def _smooth_memberships_np(x, centres, t):
    """The module docstring's smooth triangles, in NumPy: the input clip ``c_0 + sp(x - c_0) -
    sp(x - c_{n-1})``, the Boltzmann min of rise and fall, the clip ``sp(y) - sp(y - 1)``."""
    from scipy.special import expit

    def sp(v):
        return t * np.logaddexp(v / t, 0.0)

    c = np.asarray(centres, np.float64)
    x = c[0] + sp(x - c[0]) - sp(x - c[-1])
    feet = _feet(c)
    out = []
    for j in range(len(c)):
        rise, fall = (x - feet[j]) / (feet[j + 1] - feet[j]), (feet[j + 2] - x) / (feet[j + 2] - feet[j + 1])
        peak = fall + (rise - fall) * expit((fall - rise) / t)
        out.append(sp(peak) - sp(peak - 1))
    return out


def _smooth_levels_np(e, e_dot, rules, centres, t):
    """Smooth rule strengths ``a b / M_T(a, b)`` (``M_T`` the Boltzmann max) and the output
    sets' levels (the Boltzmann max over the rules naming each), in NumPy."""
    from scipy.special import expit

    mu_a, mu_v = _smooth_memberships_np(e, centres[0], t), _smooth_memberships_np(e_dot, centres[1], t)
    w = []
    for a_name, v_name, _ in rules:
        a, b = mu_a[SET_NAMES.index(a_name)], mu_v[SET_NAMES.index(v_name)]
        w.append(a * b / (b + (a - b) * expit((a - b) / t)))
    levels = []
    for name in SET_NAMES:
        group = np.array([w_r for w_r, (_, _, out) in zip(w, rules) if out == name])
        weights = np.exp((group - group.max(initial=0.0)) / t)
        levels.append(np.sum(group * weights) / np.sum(weights) if group.size else 0.0)
    return np.array(w), np.array(levels)


def _smooth_centroid_quadrature(e, e_dot, rules, centres, t):
    """The smooth centroid by trapezoid quadrature of its output density (N_BRUTE points):
    on each interval [c_j, c_{j+1}], at ``s = (u - c_j) / h_j``, ``min(a, 1 - s) + min(b, s)
    - min(cc, s, 1 - s)`` with levels ``a, b`` and ``cc = cap_T(AND_T(a, b))``, the no-fire
    mass ``T^2`` added to the area; returns (centroid, area)."""
    from scipy.special import expit

    _, levels = _smooth_levels_np(e, e_dot, rules, centres, t)
    c = np.asarray(centres[2], np.float64)
    u = np.linspace(c[0], c[-1], N_BRUTE)
    j = np.clip(np.searchsorted(c, u, side="right") - 1, 0, len(c) - 2)
    s = (u - c[j]) / (c[j + 1] - c[j])
    a, b = levels[j], levels[j + 1]
    both = a * b / (b + (a - b) * expit((a - b) / t))
    cc = both - t * (np.logaddexp((both - 0.5) / t, 0.0) - np.logaddexp(-0.5 / t, 0.0))
    density = np.minimum(a, 1 - s) + np.minimum(b, s) - np.minimum(cc, np.minimum(s, 1 - s))
    area = np.trapezoid(density, u)
    return np.trapezoid(u * density, u) / (area + t * t), area


@pytest.mark.parametrize("temperature", [0.02, 0.3])
def test_smooth_surfaces_against_numpy_references(temperature):
    """Both smooth defuzzifiers against NumPy written from the module docstring: the singleton
    average ``sum_r w_r c_r / (sum_r w_r + T^2)`` to rounding, the closed-form centroid against
    quadrature of its density (a second derivation of the algebra). Each universe has its own
    uneven centres, the points reach past the universe and into the no-rule corners."""
    angle_c, velocity_c, torque_c = np.asarray(PAPER_CENTRES) * 1.1, np.array([-0.9, -0.55, 0.05, 0.4, 1.05]), np.array([-1.04, -0.51, 0.01, 0.49, 1.02])
    centres = (angle_c, velocity_c, torque_c)
    params = fuzzy_params()._replace(angle_centres=jnp.asarray(angle_c), velocity_centres=jnp.asarray(velocity_c), torque_centres=jnp.asarray(torque_c))
    points = np.random.default_rng(5).uniform(-1.3, 1.3, size=(300, 2))
    consequent_c = np.array([torque_c[SET_NAMES.index(out)] for _, _, out in PAPER_RULES])
    singleton = np.asarray(_surface_fn(params, temperature, defuzz="singleton")(points[:, 0], points[:, 1]))
    for (e, ed), ours in zip(points, singleton):
        w, _ = _smooth_levels_np(e, ed, PAPER_RULES, centres, temperature)
        expected = np.sum(w * consequent_c) / (np.sum(w) + temperature**2)
        np.testing.assert_allclose(ours, expected, rtol=0, atol=ATOL_ROUND)
    centroid = np.asarray(_surface_fn(params, temperature)(points[:40, 0], points[:40, 1]))
    for (e, ed), ours in zip(points[:40], centroid):
        expected, area = _smooth_centroid_quadrature(e, ed, PAPER_RULES, centres, temperature)
        # up to 16 kinks (4 per interval), twice _brute_tol's 8
        assert abs(ours - expected) <= 2 * _brute_tol(area + temperature**2, torque_c), (e, ed, ours, expected)
    assert np.max(np.abs(singleton)) > 0.5 and np.max(np.abs(centroid)) > 0.3  # not trivially 0


def test_smooth_singleton_converges_to_faithful():
    """O(T) where rules fire, as the centroid (test_smooth_surface_converges_to_faithful)."""
    grid = np.linspace(-1.0, 1.0, 101)
    e, ed = (a.ravel() for a in np.meshgrid(grid, grid, indexing="ij"))
    bulk = (_max_strength_np(e, ed) >= W_BULK) & (np.abs(e) <= 0.9) & (np.abs(ed) <= 0.9)
    faithful = np.asarray(_surface_fn(fuzzy_params(), 0.0, defuzz="singleton")(e, ed))
    errs = []
    for t in CONVERGENCE_TEMPERATURES:
        errs.append(np.max(np.abs(np.asarray(_surface_fn(fuzzy_params(), t, defuzz="singleton")(e, ed)) - faithful)[bulk]))
        assert errs[-1] <= C_BULK_SINGLETON * t, (t, errs[-1] / t)
    assert np.log(errs[-2] / errs[-1]) / np.log(3.0) == pytest.approx(1.0, abs=0.1)


SMOOTH_PRIMITIVES = {"exp", "log", "log1p", "logistic"}


def _primitive_names(closed_jaxpr):
    """Names of all primitives in a jaxpr, nested calls included."""
    names = set()

    def visit(jaxpr):
        for eqn in jaxpr.eqns:
            names.add(eqn.primitive.name)
            for value in eqn.params.values():
                for sub in value if isinstance(value, (tuple, list)) else (value,):
                    if hasattr(sub, "jaxpr") and hasattr(sub, "consts"):
                        visit(sub.jaxpr)
                    elif hasattr(sub, "eqns"):
                        visit(sub)

    visit(closed_jaxpr.jaxpr)
    return names


def test_zero_temperature_is_the_faithful_path():
    """Identical programs (hence bit-identical values and gradients), with no smooth operator."""
    params = fuzzy_params(k1=1.3, k2=0.7, k3=2.5)
    y = jnp.array([0.5 / 1.3, 0.3])  # e on the PS centre: a kink
    step = lambda c: (lambda p, y: c.step(p, (), y)[1][0])  # noqa: E731
    for transform in (lambda f: f, jax.grad):
        default = jax.make_jaxpr(transform(step(fuzzy())))(params, y)
        zero = jax.make_jaxpr(transform(step(fuzzy(temperature=0.0))))(params, y)
        assert str(zero) == str(default)
        smooth = jax.make_jaxpr(transform(step(fuzzy(temperature=T_GRAD))))(params, y)
        assert not SMOOTH_PRIMITIVES & _primitive_names(zero)
        assert SMOOTH_PRIMITIVES & _primitive_names(smooth)
    surface = jax.make_jaxpr(lambda e: fuzzy_surface(params, e, -0.2, defuzz="singleton"))(0.3)
    surface_0 = jax.make_jaxpr(lambda e: fuzzy_surface(params, e, -0.2, defuzz="singleton", temperature=0))(0.3)
    assert str(surface_0) == str(surface)


def test_smooth_gradient_is_continuous_across_faithful_kinks():
    """Just left and right of a faithful kink the faithful slope jumps by >= 1, the smooth
    gradient changes by O(step / T)."""
    params = fuzzy_params()
    points = np.array(
        [
            [0.0, 0.3],  # angle on the ZE centre
            [0.5, -0.3],  # angle on the PS centre
            [0.2, -0.5],  # velocity on the NS centre
            [-0.3, 0.0],  # velocity on the ZE centre
            [1.0, 0.1],  # angle on the edge of the universe (the input clip)
        ]
    )
    step = KINK_STEP * np.eye(2)[[0, 0, 1, 1, 0]]  # [5, 2] along the kinked coordinate
    # Faithful: one-sided difference quotients (exact slopes: the surface is smooth on each side).
    faithful = _surface_fn(params, 0.0)
    f_left, f_mid, f_right = (np.asarray(faithful(*(points + k * step).T)) for k in (-1, 0, 1))
    assert np.all(np.abs((f_right - f_mid) - (f_mid - f_left)) / KINK_STEP >= FAITHFUL_KINK_JUMP)
    grad = jax.jit(jax.vmap(jax.jacfwd(lambda x: fuzzy_surface(params, x[0], x[1], temperature=T_GRAD))))
    left, right = np.asarray(grad(jnp.asarray(points - step))), np.asarray(grad(jnp.asarray(points + step)))
    assert np.all(np.max(np.abs(right - left), axis=1) <= C_CURVATURE * 2 * KINK_STEP / T_GRAD)


# (theta, theta_dot) with k1 = 2, k2 = 0.5 (exact in binary, so e lands exactly on the kinks):
_KINK_YS = np.array(
    [
        [0.0, 0.6],  # e = 0: ZE centre
        [0.25, -0.4],  # e = 0.5: PS centre
        [0.1, -1.0],  # e_dot = -0.5: NS centre
        [-0.125, 0.0],  # e = -0.25, e_dot = 0: crossing of NS and ZE, ZE centre
        [0.5, 0.3],  # e = 1: edge of the universe
        [0.4, 1.8],  # e = 0.8, e_dot = 0.9: no rule fires
        [0.25, 1.5],  # e = 0.5, e_dot = 0.75: a jump of the faithful surface
    ]
)


def test_smooth_gradients_against_finite_differences():
    """check_grads on the surface summed over the kink points above and random inputs, plus a
    60-step closed-loop rollout (jaxflex plant, 2 modes, 1 ms) from a 0.3 rad hub angle."""
    import jaxflex as jf
    from jaxflex.scenarios import initial_condition

    params = fuzzy_params(k1=2.0, k2=0.5, k3=1.5)._replace(
        torque_centres=jnp.array([-1.0, -0.45, 0.02, 0.55, 1.0])  # uneven: no symmetric cancellation
    )
    assert np.all(np.asarray(params.k1) * _KINK_YS[[0, 1, 4], 0] == [0.0, 0.5, 1.0])
    random_ys = jax.random.uniform(jax.random.key(0), (16, 2), minval=-0.6, maxval=0.6)
    ys = jnp.concatenate([jnp.asarray(_KINK_YS), random_ys])
    controller = fuzzy(temperature=T_GRAD)
    plant = jf.discretize(jf.make_plant(jf.BeamParams(), 2), 1e-3, "rk4")
    scenario = initial_condition(jnp.array([0.3, 1e-3, 0.0, 0.0, 0.0, 0.0]), 60)

    def surface_loss(p):
        u = jax.vmap(lambda y: controller.step(p, (), y)[1])(ys)
        return jnp.sum(u) + jnp.sum(u**2)

    def closed_loop_loss(p):
        traj = jf.rollout(plant, controller, p, scenario)
        return jnp.mean((traj.y[:, 0] / 0.3) ** 2) + jnp.mean(traj.u[:, 0] ** 2)  # O(1)

    tolerances = dict(eps=EPS_FD, atol=ATOL_FD_SMOOTH, rtol=RTOL_FD_SMOOTH)
    # The surface runs op by op: compiling its vmapped forward and reverse programs would take
    # far longer than running them here.
    check_grads(surface_loss, (params,), order=1, modes=["fwd", "rev"], **tolerances)

    # The closed loop: one jitted program gives the loss, its forward-mode derivative along a
    # tangent and its reverse-mode gradient (one compilation rather than one each for the loss,
    # the jvp and the vjp). check_jvp and check_vjp are what check_grads(order=1) runs.
    @jax.jit
    def loop_derivatives(p, tangent):
        value, derivative = jax.jvp(closed_loop_loss, (p,), (tangent,))
        return value, derivative, jax.grad(closed_loop_loss)(p)

    zeros = jax.tree.map(jnp.zeros_like, params)

    def loop_vjp(p):
        value, _, grad = loop_derivatives(p, zeros)
        return value, lambda cotangent: (jax.tree.map(lambda g: g * cotangent, grad),)

    loop_value = lambda p: loop_derivatives(p, zeros)[0]  # noqa: E731
    loop_jvp = lambda primals, tangents: loop_derivatives(primals[0], tangents[0])[:2]  # noqa: E731
    check_jvp(loop_value, loop_jvp, (params,), **tolerances)
    check_vjp(loop_value, loop_vjp, (params,), **tolerances)
    # Every parameter matters (forward mode, one leaf at a time).
    for name in FuzzyParams._fields:
        tangent = zeros._replace(**{name: jnp.ones_like(getattr(params, name))})
        derivs = (jax.jvp(surface_loss, (params,), (tangent,))[1], loop_derivatives(params, tangent)[1])
        assert all(np.isfinite(float(d)) and abs(float(d)) > 1e-4 for d in derivs), (name, derivs)


def test_smooth_ranges_and_symmetry():
    uneven = jnp.array([-1.3, -0.4, 0.1, 0.35, 1.2])
    centre_sets = jnp.stack([jnp.asarray(PAPER_CENTRES), uneven])
    x = jnp.linspace(-2.0, 2.0, 401)
    grid = np.linspace(-1.3, 1.3, 41)  # past the universe; both no-rule corners
    e, ed = (jnp.asarray(a.ravel()) for a in np.meshgrid(grid, grid, indexing="ij"))
    params = fuzzy_params()
    t = 0.1  # smaller T: test_smooth_gradients_finite_everywhere_and_dtype
    mu = jax.vmap(jax.vmap(lambda xi, c: memberships(xi, c, temperature=t), (0, None)), (None, 0))
    mu = np.asarray(jax.jit(mu)(x, centre_sets))  # [2, 401, 5]
    assert np.all((mu >= 0) & (mu <= 1))
    f = np.asarray(_surface_fn(params, t)(jnp.concatenate([e, -e]), jnp.concatenate([ed, -ed])))
    assert np.all(np.abs(f) <= 1.0)
    np.testing.assert_allclose(f[e.size :], -f[: e.size], rtol=0, atol=ATOL_ROUND)  # odd
    assert np.max(np.abs(f)) > 0.5  # not trivially zero
    # Rule tables that name one consequent leave the other output sets at level 0. The smooth
    # min(a, b, 1/2) of the centroid keeps 0 at 0 (a Boltzmann min with 1/2 would not: negative
    # areas, outputs of order 100 at T = 0.3), so the output stays between 0 and that set.
    one_consequent = (
        ((("PS", "PS", "PM"), ("PM", "NM", "PM")), 0.0, 1.0),
        ((("NM", "NM", "NM"), ("NS", "PM", "NM")), -1.0, 0.0),
    )
    for rules, lo, hi in one_consequent:
        g = np.asarray(_surface_fn(params, 0.3, rules=rules)(e, ed))
        assert np.all((g >= lo) & (g <= hi)), (rules, g.min(), g.max())
        assert np.max(np.abs(g)) > 0.5


@pytest.mark.parametrize("dtype, temperature", [(jnp.float64, 0.001), (jnp.float32, T_GRAD)])
def test_smooth_gradients_finite_everywhere_and_dtype(dtype, temperature):
    """Reverse-mode gradients w.r.t. every parameter and both inputs on a grid through both
    no-rule corners and past the universe, where memberships underflow (float64 at a small
    T, float32 at the working T); outputs in the universe, odd; dtypes preserved."""
    params = fuzzy_params(dtype=dtype)
    grid = np.linspace(-1.3, 1.3, 27)  # symmetric: the flat grid reversed is the mirror image
    e, ed = (jnp.asarray(a.ravel(), dtype) for a in np.meshgrid(grid, grid, indexing="ij"))
    surface = lambda p, a, b: fuzzy_surface(p, a, b, temperature=temperature)  # noqa: E731
    value_and_grad = jax.jit(jax.vmap(jax.value_and_grad(surface, argnums=(0, 1, 2)), in_axes=(None, 0, 0)))
    f, grads = value_and_grad(params, e, ed)
    assert f.dtype == dtype
    for leaf in jax.tree.leaves(grads):
        assert leaf.dtype == dtype and np.all(np.isfinite(np.asarray(leaf)))
    f = np.asarray(f)
    assert np.all(np.abs(f) <= 1.0) and np.max(np.abs(f)) > 0.5
    if dtype == jnp.float64:
        np.testing.assert_allclose(f[::-1], -f, rtol=0, atol=ATOL_ROUND)
    else:
        f64 = _surface_fn(fuzzy_params(), temperature)(e.astype(jnp.float64), ed.astype(jnp.float64))
        np.testing.assert_allclose(f, np.asarray(f64), rtol=0, atol=ATOL_F32_SMOOTH)
        _, u = jax.eval_shape(fuzzy(temperature=temperature).step, params, (), jnp.array([0.21, -0.9], dtype))
        assert u.dtype == dtype and u.shape == (1,)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("defuzz", ["centroid", "singleton"])
def test_accepted_temperature_range_is_finite_and_converges_at_its_floor(dtype, defuzz):
    """Across [MIN_TEMPERATURE, MAX_TEMPERATURE] the surface and its gradients (every parameter,
    both inputs) are finite in both dtypes, on a grid past the universe and through the no-rule
    corners; at MIN_TEMPERATURE the smooth centroid is within the documented C_BULK T of the
    faithful surface where rules fire, float32 round-off included (observed 1.16 T).

    The sweep runs op by op: a jitted program per temperature (each is a static constant of
    the controller) made this test 8x slower."""
    params = fuzzy_params(dtype=dtype)
    grid = np.linspace(-1.3, 1.3, 27)
    e, ed = (jnp.asarray(a.ravel(), dtype) for a in np.meshgrid(grid, grid, indexing="ij"))
    for t in np.geomspace(MIN_TEMPERATURE, MAX_TEMPERATURE, 6):
        surface = lambda p, a, b: fuzzy_surface(p, a, b, temperature=float(t), defuzz=defuzz)  # noqa: E731
        f, grads = jax.vmap(jax.value_and_grad(surface, argnums=(0, 1, 2)), in_axes=(None, 0, 0))(params, e, ed)
        for leaf in (f, *jax.tree.leaves(grads)):
            assert np.all(np.isfinite(np.asarray(leaf))), (t, leaf)
    if defuzz == "centroid":
        grid = np.linspace(-1.0, 1.0, 101)
        e, ed = (a.ravel() for a in np.meshgrid(grid, grid, indexing="ij"))
        bulk = (_max_strength_np(e, ed) >= W_BULK) & (np.abs(e) <= 0.9) & (np.abs(ed) <= 0.9)
        faithful = np.asarray(_surface_fn(fuzzy_params(dtype=jnp.float64), 0.0)(e, ed))
        smooth = np.asarray(_surface_fn(params, MIN_TEMPERATURE)(jnp.asarray(e, dtype), jnp.asarray(ed, dtype)))
        assert np.max(np.abs(smooth - faithful)[bulk]) <= C_BULK * MIN_TEMPERATURE


@pytest.mark.parametrize(
    "temperature",
    [-0.01, float("nan"), float("inf"), -float("inf"), "0.1", None, jnp.array(0.02), 1e-50, MIN_TEMPERATURE / 2, 1.01 * MAX_TEMPERATURE, 1e155],
)
def test_temperature_validation(temperature):
    """Out of range: a huge T overflowed (OverflowError from T**2), a tiny one is 0 in float32."""
    match = r"temperature must be 0 \(the faithful controller\) or a Python float in \[1e-05, 1\]"
    with pytest.raises(ValueError, match=match):
        fuzzy(temperature=temperature)
    with pytest.raises(ValueError, match=match):
        fuzzy_surface(fuzzy_params(), 0.0, 0.0, temperature=temperature)
    with pytest.raises(ValueError, match=match):
        memberships(0.0, jnp.asarray(PAPER_CENTRES), temperature=temperature)
    fuzzy(temperature=np.float64(0.02))  # NumPy scalars and ints are accepted
    fuzzy(temperature=0)
    fuzzy(temperature=1)


@pytest.mark.parametrize("field", ["k1", "k2"])
@pytest.mark.parametrize("value", [0.0, -0.3])
def test_input_scalings_must_be_positive(field, value):
    """k1 and k2 scale the measurement into the universe: zero or negative gains (a dead or
    sign-flipped input) are refused by name, like a non-finite one."""
    with pytest.raises(ValueError, match=rf"{field} must be finite and > 0"):
        fuzzy().check(fuzzy_params(**{field: value}))


def test_surface_names_parameters_of_the_wrong_kind():
    """A dict of gains failed inside the surface with an AttributeError."""
    with pytest.raises(ValueError, match=r"params must be a FuzzyParams \(k1, k2, k3, angle_centres, velocity_centres, torque_centres\); got dict"):
        fuzzy_surface({"k1": 1.0}, 0.1, 0.2)


def test_set_names_and_rule_shapes_are_refused_by_name():
    """A single set (no interval to interpolate over: an IndexError in the memberships at
    the first step), repeated names (the rules would read the last of them) and rules of
    more than three names (NumPy's reshape error) are refused by name at construction."""
    for f in (lambda **kw: fuzzy(**kw), lambda **kw: fuzzy_surface(fuzzy_params(centres=(-1.0, 0.0, 1.0)), 0.1, 0.2, **kw)):
        with pytest.raises(ValueError, match=r"set_names must be at least 2 strings; got \('ZE',\)"):
            f(set_names=("ZE",), rules=(("ZE", "ZE", "ZE"),))
        with pytest.raises(ValueError, match=r"set_names must be at least 2 strings"):
            f(set_names=("N", 0, "P"), rules=(("N", "N", "P"),))
        with pytest.raises(ValueError, match=r"set_names must be distinct; got \('N', 'Z', 'N'\)"):
            f(set_names=("N", "Z", "N"), rules=(("N", "Z", "Z"),))
        with pytest.raises(ValueError, match=r"rule 1 must be an \(angle, velocity, torque\) triple of set names; got \('N', 'Z', 'P', 'P'\)"):
            f(set_names=("N", "Z", "P"), rules=(("N", "Z", "P"), ("N", "Z", "P", "P")))
    # the smallest accepted system: two sets, one rule; list rows are triples too
    two = fuzzy_params(centres=(-1.0, 1.0))
    assert float(fuzzy_surface(two, -1.0, -1.0, set_names=("N", "P"), rules=[["N", "N", "P"]])) == pytest.approx(1.0 / 3.0, abs=ATOL_ROUND)


def test_a_measurement_that_is_not_angle_and_velocity_is_refused():
    """The step reads y[0] and y[1]: a y of 3 entries (a state passed for the measurement)
    ran on its first two, silently; one of 1 entry failed with JAX's IndexError."""
    controller, params = fuzzy(), fuzzy_params()
    for shape in ((3,), (1,), (3, 4), (2, 2, 2), ()):
        with pytest.raises(ValueError, match=rf"y must have shape \(2,\) \(theta, theta_dot\), or \(2, B\) for a batch; got {re.escape(str(shape))}"):
            controller.step(params, (), jnp.zeros(shape))
    _, u = controller.step(params, (), jnp.zeros((2, 4)))  # a batch of 4
    assert u.shape == (1, 4)


def test_the_surface_takes_scalars():
    """fuzzy_surface is the surface at one point (vmap it for grids): arrays of inputs are
    refused by name, not broadcast through the scalar chain."""
    params = fuzzy_params()
    for e, e_dot in ((jnp.zeros(3), 0.0), (0.0, jnp.zeros((2, 2))), (jnp.zeros(1), jnp.zeros(1))):
        with pytest.raises(ValueError, match=r"e and e_dot must be scalars \(vmap for grids\); got shapes"):
            fuzzy_surface(params, e, e_dot)
