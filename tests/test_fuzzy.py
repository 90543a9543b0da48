"""PD-type fuzzy controller: the closed-form Mamdani centroid against scikit-fuzzy and a
brute-force numeric centroid, odd symmetry, the singleton defuzzifier, the controller under
jit/vmap, gradients against finite differences, validation and dtype preservation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import skfuzzy
from jax.test_util import check_grads

from jaxflex.controllers.fuzzy import (
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
    params = fuzzy_params()
    c = np.asarray(PAPER_CENTRES)
    consequent_centres = np.array([c[SET_NAMES.index(t)] for _, _, t in PAPER_RULES])
    rng = np.random.default_rng(3)
    n_fired = 0
    for e, ed in rng.uniform(-1.0, 1.0, size=(200, 2)):
        w = _rule_strengths_np(e, ed, PAPER_RULES, c, c)
        expected = np.sum(w * consequent_centres) / np.sum(w) if np.sum(w) > 0 else 0.0
        n_fired += np.sum(w) > 0
        ours = float(fuzzy_surface(params, e, ed, defuzz="singleton"))
        np.testing.assert_allclose(ours, expected, rtol=0, atol=ATOL_ROUND)
    assert 100 < n_fired < 200
    # A hand-checked point: e = -0.25 is half NS, half ZE; e_dot = 0 is ZE. Rules 2 (NS,ZE->PS)
    # and 6 (ZE,ZE->ZE) fire at 0.5 each: (0.5 * 0.5 + 0.5 * 0) / 1 = 0.25.
    assert float(fuzzy_surface(params, -0.25, 0.0, defuzz="singleton")) == pytest.approx(0.25, abs=ATOL_ROUND)


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
    grads = jax.jit(jax.grad(loss))(params)
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


# -- 7. validation -----------------------------------------------------------------------------


def test_validation():
    with pytest.raises(ValueError, match=r"rule 1 names unknown set 'XX'.*accepted names.*NM"):
        fuzzy(rules=(("NM", "ZE", "PM"), ("XX", "ZE", "PS")))
    with pytest.raises(ValueError, match=r"rule 0 must be an \(angle, velocity, torque\) triple"):
        fuzzy(rules=(("NM", "ZE"),))
    with pytest.raises(ValueError, match=r"rule 0 must be"):
        fuzzy(rules=("NMZEPM",))
    with pytest.raises(ValueError, match=r"rule 2 names unknown set"):
        fuzzy_surface(fuzzy_params(), 0.0, 0.0, rules=PAPER_RULES[:2] + (("ZE", "ZE", "BIG"),))
    with pytest.raises(NotImplementedError, match="defuzz"):
        fuzzy(defuzz="bisector")
    with pytest.raises(NotImplementedError, match="defuzz"):
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
    assert isinstance(params32, FuzzyParams)
