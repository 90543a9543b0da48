"""DFS stability analysis: critical delays, the generator's rightmost root, the sampled loop,
the (k, tau) chart and ``jaxflex.stability_report``, each against an independent oracle
(direct determinants, jaxflex's own rollout, the other two methods)."""

import json
import math

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pytest

from jaxflex import beam, pade, plotting, stability_report
from jaxflex.analysis import stability as st
from jaxflex.controllers import DFSParams, dfs
from jaxflex.plant import discretize, make_plant
from jaxflex.rollout import rollout
from jaxflex.scenarios import initial_condition, paper_scenario

RTOL_DELTA = 1e-9  # |Delta(jw, tau_m)| / |P(jw)|: crossings polished to ~1e-15 relative; det itself ~1e-14
RTOL_POLY = 1e-9  # P, Q from eigenvalues / transmission zeros against LU determinants (~1e-14 seen)
RTOL_STEP = 1e-12  # one sample of the augmented matrix against one rollout step: same float64 products
RTOL_DEFLATE = 1e-9  # deflated spectrum against the full one (eigenvalue conditioning, 46 x 46)
SMALL_EIG = 0.05  # well above eps^(1/5) ~ 7e-4, well below every other eigenvalue modulus (> 0.5)
RTOL_GRAD = 1e-6  # jax.grad of the spectral radius against a central difference (h = 1e-4 N*m/rad)
SIM_MARGIN = 2e-3  # |radius - 1| of the points classified by simulation: >= 20x growth/decay over a window
SIM_WINDOW = 1500  # samples per window of the growth test
SIM_FLOOR = 1e-9  # decayed to round-off: the settled hub angle (structural mode) leaks ~1e-13 into q through Ad's rounding
TAU_MARGIN = 0.02  # chart points within 2 % of a critical delay are not compared (marginal)
SAMPLED_RATE_RTOL = 0.02  # log(radius)/dt against Re(rightmost root) at dt = 0.1 ms (O(dt) discretisation error)
PAPER_K, PAPER_TAU = 55.0, 0.005


@pytest.fixture(scope="module")
def plant():
    return make_plant(n_modes=2)


@pytest.fixture(scope="module")
def crit(plant):
    return {k: st.critical_delays(plant, k, 0.04) for k in (20.0, PAPER_K, 120.0, -55.0)}


# ---------------------------------------------------------------------------------------------
# 1. P, Q and the critical delays


def test_p_plus_q_is_open_loop_and_delta_is_affine_in_z(plant):
    rng = np.random.default_rng(0)
    s = rng.normal(scale=150.0, size=8) + 1j * rng.normal(scale=300.0, size=8)
    A, b, c = st.loop_vectors(plant)
    for k in (PAPER_K, -20.0, 200.0):
        polys = st.characteristic_polynomials(plant, k)
        p_val, q_val = np.polyval(polys.P, s), np.polyval(polys.Q, s)
        det_open = np.linalg.det(s[:, None, None] * np.eye(6) - A)
        det_closed = np.linalg.det(s[:, None, None] * np.eye(6) - A + k * np.outer(b, c))
        np.testing.assert_allclose(np.polyval(polys.P + polys.Q, s), det_open, rtol=RTOL_POLY)  # z = 1
        np.testing.assert_allclose(p_val, det_closed, rtol=RTOL_POLY)  # z = 0
        for tau in (0.005, 0.0123):
            z = np.exp(-s * tau)
            direct = st.delta(plant, k, tau, s)
            scale = np.abs(p_val) + np.abs(q_val * z)
            assert np.all(np.abs(direct - (p_val + q_val * z)) <= RTOL_POLY * scale)


def test_each_critical_delay_zeroes_delta(plant, crit):
    n_checked = 0
    for k, result in crit.items():
        polys = st.characteristic_polynomials(plant, k)
        assert len(result.crossings) >= 3
        for cr in result.crossings:
            s = 1j * cr.omega
            p_val = abs(np.polyval(polys.P, s))
            assert abs(abs(np.polyval(polys.Q, s)) - p_val) <= RTOL_DELTA * p_val  # |P| = |Q|
            for tau in cr.tau_s:
                assert abs(st.delta(plant, k, tau, s)) <= RTOL_DELTA * p_val, (k, cr.freq_hz, tau)
                n_checked += 1
            # tau_m are beta / w + 2 pi m / w
            np.testing.assert_allclose(np.diff(cr.tau_s), 2 * np.pi / cr.omega, rtol=1e-12)
    assert n_checked >= 8


def test_direction_signs_agree_with_cooke_and_with_the_roots(plant, crit):
    """Re ds/dtau (implicit function theorem) has the sign of F'(w) at every tau_m, and the
    root near jw really moves to that side: checked with the generator's roots at tau_m +- 1 %."""
    for k, result in crit.items():
        for cr in result.crossings:
            assert cr.direction == ("destabilising" if cr.dF_dw > 0 else "stabilising")
            assert np.all(np.sign(cr.re_dsdtau) == np.sign(cr.dF_dw))
            for tau in cr.tau_s[:1]:
                for factor, side in ((0.99, -1), (1.01, 1)):
                    roots = np.asarray(st.characteristic_roots(plant, k, tau * factor))
                    near = roots[np.argmin(np.abs(roots - 1j * cr.omega))]
                    assert abs(near.imag - cr.omega) < 0.02 * cr.omega
                    assert np.sign(near.real) == side * np.sign(cr.re_dsdtau[0]), (k, cr.freq_hz, factor, near)


def test_first_destabilising_delay_is_where_the_rightmost_root_crosses(plant):
    first = st.first_destabilising_delay(PAPER_K, 2)
    assert 0.005 < first < 0.01  # the paper's 5 ms is inside the stable range
    for k in (20.0, PAPER_K, 120.0):
        tau = st.first_destabilising_delay(k, 2, plant=plant)
        below = complex(st.rightmost_root(plant, k, 0.99 * tau))
        above = complex(st.rightmost_root(plant, k, 1.01 * tau))
        assert below.real < 0 < above.real, (k, tau, below, above)
        omega = [cr.omega for cr in st.critical_delays(plant, k, 2 * tau).crossings if np.any(np.isclose(cr.tau_s, tau, rtol=1e-12))]
        assert abs(above.imag - omega[0]) < 0.01 * omega[0]


def test_continuous_chart_matches_the_stability_switches(plant):
    """Where the rightmost root is in the left half plane is where the crossings count 0 roots
    in the right half plane (stability switches, including re-stabilisation at small k)."""
    k_values = np.linspace(2.0, 150.0, 12)
    tau = np.arange(1, 41) * 1e-3
    real = np.asarray(st.rightmost_real_grid(plant, k_values, tau))
    compared = 0
    for j, k in enumerate(k_values):
        result = st.critical_delays(plant, k, 0.05)
        crit_taus = np.concatenate([cr.tau_s for cr in result.crossings] + [np.zeros(0)])
        count = st.unstable_root_count(result, tau)
        away = np.all(np.abs(tau[:, None] - crit_taus[None, :]) > TAU_MARGIN * tau[:, None], axis=1)
        np.testing.assert_array_equal((real[:, j] < 0)[away], (count == 0)[away], err_msg=f"k = {k}")
        compared += int(away.sum())
    assert compared > 400


def test_wrong_sign_gain_has_a_real_crossing_through_zero(plant, crit):
    """k < 0: the rigid-body root passes through s = 0 at tau_0 = -a'(0) / (k N(0)); the
    deflation keeps that second root at 0 (a tolerance around 0 would drop it)."""
    result = crit[-55.0]
    zero = result.zero_crossing
    polys = st.characteristic_polynomials(plant, -55.0)
    assert zero is not None and zero.direction == "destabilising"
    np.testing.assert_allclose(zero.tau_s, -polys.a[-2] / (-55.0 * polys.N[-1]), rtol=1e-14)
    for factor, sign in ((0.9, -1), (1.1, 1)):
        roots = np.asarray(st.characteristic_roots(plant, -55.0, zero.tau_s * factor))
        real = roots[np.abs(roots.imag) < 1e-9]
        assert np.sign(real[np.argmin(np.abs(real))].real) == sign
    roots = np.asarray(st.characteristic_roots(plant, -55.0, zero.tau_s))
    assert np.min(np.abs(roots)) < 1e-6
    # the counted switches: one root (not a pair) enters through 0, as the roots themselves say
    for factor in (0.5, 0.9, 1.1, 2.0):
        roots = np.asarray(st.characteristic_roots(plant, -55.0, zero.tau_s * factor))
        assert int(st.unstable_root_count(result, zero.tau_s * factor)) == int(np.sum(roots.real > 1e-6)), factor
    assert crit[PAPER_K].zero_crossing is None  # k > 0: the root at 0 stays simple


def test_the_first_destabilising_delay_can_be_the_real_crossing_through_zero(plant):
    """k = -0.5: no imaginary-axis crossing destabilises the loop, the real root through s = 0
    does (the docstring: "an imaginary-axis crossing or the real crossing through 0"); the
    rightmost root is real and changes sign there."""
    first = st.first_destabilising_delay(-0.5, 2, plant=plant)
    assert math.isfinite(first)
    below, above = (complex(st.rightmost_root(plant, -0.5, factor * first, 32)) for factor in (0.99, 1.01))
    assert below.real < 0 < above.real and abs(above.imag) < 1e-9


def _g(plant, s):
    """G(s) = c (sI - A)^{-1} b of each s, by NumPy solves."""
    A, b, c = (np.asarray(m, float) for m in (plant.A, plant.B[:, 0], plant.C[0]))
    s = np.atleast_1d(s).astype(complex)
    x = np.linalg.solve(s[:, None, None] * np.eye(A.shape[0]) - A, np.broadcast_to(b.astype(complex), (s.size, b.size))[..., None])
    return x[..., 0] @ c


@pytest.mark.parametrize("k", [PAPER_K, -55.0, -0.5])
def test_the_crossings_are_the_sign_changes_of_one_plus_two_k_re_g(plant, k):
    """|P(jw)| = |Q(jw)| where 1 + 2 k Re G(jw) = 0 (P = a + k N, Q = -k N, G = N / a):
    every sign change of it on a scan of 400,001 frequencies from 0.01 to 1e5 rad/s, and
    nothing else (at k = -0.5 the polynomial in w^2 has complex roots, near 83 and 228 rad/s,
    which are no crossings)."""
    w = np.geomspace(1e-2, 1e5, 400_001)
    h = 1 + 2 * k * _g(plant, 1j * w).real
    changes = np.nonzero(np.sign(h[:-1]) != np.sign(h[1:]))[0]
    found = np.asarray(st.crossing_frequencies(plant, k))
    assert found.size == changes.size, (found, w[changes])
    assert np.all((w[changes] <= found * (1 + 1e-9)) & (found <= w[changes + 1] * (1 + 1e-9)))


def test_df_dw_is_the_derivative_of_f(plant, crit):
    """dF/dw of F(w) = |P(jw)|^2 - |Q(jw)|^2 (its sign gives each crossing's direction), against
    a central difference of F built from NumPy determinants."""
    A, b, c = (np.asarray(m, float) for m in (plant.A, plant.B[:, 0], plant.C[0]))

    def F(k, w):
        P = np.linalg.det(1j * w * np.eye(A.shape[0]) - A + k * np.outer(b, c))
        return abs(P) ** 2 - abs(np.linalg.det(1j * w * np.eye(A.shape[0]) - A) - P) ** 2

    for k, result in crit.items():
        for crossing in result.crossings:
            h = 1e-5 * crossing.omega
            np.testing.assert_allclose(crossing.dF_dw, (F(k, crossing.omega + h) - F(k, crossing.omega - h)) / (2 * h), rtol=1e-4, err_msg=f"k = {k}")


def test_more_than_a_million_critical_delays_of_a_crossing_are_refused(plant):
    """The documented cap: the top crossing at k = 55 repeats every 2 pi / w; 2e4 s of delay
    would hold about 1.4e6 of them."""
    top = float(np.max(st.crossing_frequencies(plant, PAPER_K)))
    assert 1.1e6 < 2e4 * top / (2 * np.pi) < 1e7
    with pytest.raises(ValueError, match=r"k = 55: the loop crosses the imaginary axis at 68.91 Hz, every 0.0145 s of delay, which is 1.38e\+06 critical delays up to 20000 s \(at most 1e\+06 are listed\)"):
        st.critical_delays(plant, PAPER_K, 2e4)


# ---------------------------------------------------------------------------------------------
# 2. Rightmost root of the delay equation


@pytest.mark.parametrize("k, tau", [(PAPER_K, 0.03), (120.0, 0.02), (20.0, 0.04)])
def test_rightmost_root_converges_with_chebyshev_points(plant, k, tau):
    roots = [complex(st.rightmost_root(plant, k, tau, m)) for m in (8, 12, 16, 24, 32)]
    diffs = np.abs(np.diff(roots))
    floor = 1e-9 * abs(roots[-1])  # round-off level of the eigenvalues
    for prev, nxt in zip(diffs[:-1], diffs[1:]):
        assert nxt < 0.2 * prev or nxt < floor, diffs  # geometric (spectral) convergence
    assert diffs[-1] < floor
    assert roots[-1].imag > 0 and roots[-1].real > 0  # of the unstable pair, the Im > 0 root


def _characteristic_residual(plant, k, tau, s):
    """|1 + k G(s) (1 - e^{-s tau})|, G = c (sI - A)^{-1} b, in NumPy: zero at a root of
    det(sI - A + k b c (1 - e^{-s tau})) away from the poles of G."""
    A, b, c = (np.asarray(m, complex) for m in (plant.A, plant.B[:, :1], plant.C[:1]))
    g = (c @ np.linalg.solve(s * np.eye(A.shape[0]) - A, b))[0, 0]
    return abs(1 + k * g * (1 - np.exp(-s * tau)))


def test_rightmost_root_converged_doubles_until_settled():
    """A 0.3 m arm (53 and 190 Hz) at tau = 0.16 s, 30 periods of mode 2: 32 intervals leave the
    rightmost root off the characteristic equation (Re 8.8 /s against 11.25); the doubled one
    solves it, and a cap below the needed intervals is reported unconverged."""
    stiff = make_plant(beam.BeamParams(length_m=0.3), 2)
    k, tau = 55.0, 0.16
    coarse = complex(st.rightmost_root(stiff, k, tau, 32))
    found = st.rightmost_root_converged(stiff, k, tau, 32)
    assert found.converged and found.n_cheb >= 64 and found.change <= st.ROOT_RTOL * (1 + abs(found.root))
    assert found.root == complex(st.rightmost_root(stiff, k, tau, found.n_cheb))
    assert _characteristic_residual(stiff, k, tau, found.root) < 1e-8
    assert _characteristic_residual(stiff, k, tau, coarse) > 1e-3 and abs(found.root.real - coarse.real) > 1.0
    capped = st.rightmost_root_converged(stiff, k, tau, 8, max_n_cheb=16)
    assert (capped.n_cheb, capped.converged) == (16, False) and capped.change > st.ROOT_RTOL * (1 + abs(capped.root))
    with pytest.raises(ValueError, match=r"max_n_cheb must be an integer >= 64 \(Chebyshev intervals, twice n_cheb at least\); got 40"):
        st.rightmost_root_converged(stiff, k, tau, 32, max_n_cheb=40)


def test_rightmost_root_converged_stops_at_the_first_change_within_root_rtol(plant):
    """The documented doubling, followed here from 8 intervals: stop at the first doubling whose
    root moved by at most ROOT_RTOL (1e-8) x (1 + |root|). At k = 20, tau = 10 ms, 8 -> 16 moves
    it by about 3e-7 relative, 16 -> 32 by round-off: 32."""
    assert st.ROOT_RTOL == 1e-8
    k, tau = 20.0, 0.01
    m, previous = 8, complex(st.rightmost_root(plant, k, tau, 8))
    while True:
        m, root = 2 * m, complex(st.rightmost_root(plant, k, tau, 2 * m))
        if abs(root - previous) <= 1e-8 * (1 + abs(root)):
            break
        previous = root
    found = st.rightmost_root_converged(plant, k, tau, 8)
    assert found.converged and found.n_cheb == m == 32
    np.testing.assert_allclose(found.change, abs(root - previous), rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("k, tau", [(PAPER_K, 0.005), (PAPER_K, 0.02)])
def test_rightmost_real_grid_is_the_real_part_of_the_rightmost_root(plant, k, tau):
    """A real rightmost root (-9.34 /s at the paper's point) and an unstable pair (20 ms)."""
    roots = np.asarray(st.characteristic_roots(plant, k, tau, 32))
    np.testing.assert_allclose(np.asarray(st.rightmost_real_grid(plant, [k], [tau], 32))[0, 0], roots.real.max(), rtol=1e-9)


def test_sampled_rate_approaches_the_continuous_rightmost_root(plant):
    """log(radius)/dt -> Re(rightmost root) as dt -> 0 (ZOH and sampling add O(dt))."""
    for k, tau in ((PAPER_K, 0.005), (120.0, 0.004)):
        real = complex(st.rightmost_root(plant, k, tau)).real
        assert real < 0
        errors = []
        for dt in (1e-3, 2.5e-4, 1e-4):
            radius = float(st.spectral_radius(discretize(plant, dt, "zoh"), k, st.delay_steps_of(tau, dt)))
            errors.append(abs(math.log(radius) / dt - real))
        assert all(b < a for a, b in zip(errors[:-1], errors[1:])), errors
        assert errors[-1] < SAMPLED_RATE_RTOL * abs(real)


# ---------------------------------------------------------------------------------------------
# 3. The sampled loop


@pytest.mark.parametrize("method, d", [("zoh", 5), ("rk4", 3), ("zoh", 1)])
def test_sampled_matrix_reproduces_the_rollout(plant, method, d):
    dt = 1e-3
    dplant = discretize(plant, dt, method)
    x0 = jax.random.normal(jax.random.key(0), (6,)) * jnp.asarray([1e-2, 1e-3, 1e-4, 1e-1, 1e-2, 1e-3])
    steps = 200
    traj = rollout(dplant, dfs(dt, capacity=8), DFSParams(PAPER_K, d * dt), initial_condition(x0, steps))
    x = np.asarray(traj.x)
    theta = x[:, 0]
    hist = np.stack([theta[np.maximum(t - np.arange(1, d + 1), 0)] for t in range(steps)])
    xi = np.concatenate([x, hist], axis=1)  # [T, n_x + d]: [x_k, theta_{k-1}..theta_{k-d}], theta_{<0} = theta_0
    mat = np.asarray(st.sampled_loop_matrix(dplant, PAPER_K, d))
    pred = xi[:-1] @ mat.T
    np.testing.assert_allclose(pred, xi[1:], rtol=RTOL_STEP, atol=RTOL_STEP * np.abs(xi).max())
    u = -PAPER_K * (theta - hist[:, -1])
    np.testing.assert_allclose(np.asarray(traj.u)[:, 0], u, rtol=RTOL_STEP, atol=RTOL_STEP * np.abs(u).max())
    # and propagated from xi_0 = [x0, theta0 ... theta0] over the whole horizon
    prop = [xi[0]]
    for _ in range(steps - 1):
        prop.append(mat @ prop[-1])
    np.testing.assert_allclose(np.asarray(prop), xi, rtol=0, atol=1e-10 * np.abs(xi).max())


@pytest.mark.parametrize("order, hold", [(1, "foh"), (4, "zoh"), (8, "foh")])
def test_pade_matrix_reproduces_the_rollout_and_deflates_the_structural_eigenvalue(plant, order, hold):
    """The loop tune penalises and reports with delay = "pade" (it used the buffer's, a
    different loop: at k = 150, tau = 5 ms the order-1 loop decays where the buffer's grows)."""
    dplant = discretize(plant, 1e-3, "rk4")
    x0 = jax.random.normal(jax.random.key(0), (6,)) * jnp.asarray([1e-2, 1e-3, 1e-4, 1e-1, 1e-2, 1e-3])
    steps, k, tau = 300, 150.0, 0.0045
    traj = rollout(dplant, dfs(1e-3, approximation="pade", pade_order=order, pade_hold=hold), DFSParams(k, tau), initial_condition(x0, steps))
    mat = np.asarray(st.pade_loop_matrix(dplant, k, tau, order, hold))
    state = np.concatenate([x0, np.asarray(pade.sampled_delay(tau, order, 1e-3, x0[:1], hold)[1])])  # the filter starts at theta_0's steady state
    prop = [state]
    for _ in range(steps - 1):
        prop.append(mat @ prop[-1])
    x = np.asarray(traj.x)
    np.testing.assert_allclose(np.asarray(prop)[:, :6], x, rtol=0, atol=1e-10 * np.abs(x).max())
    # the deflated spectrum is the full one without one eigenvalue 1 (a constant hub angle)
    full, deflated = np.linalg.eigvals(mat), np.linalg.eigvals(np.asarray(st.deflated_pade_loop_matrix(dplant, k, tau, order, hold)))
    rest = np.delete(full, np.argmin(np.abs(full - 1)))
    assert np.min(np.abs(full - 1)) < 1e-12 and deflated.shape == rest.shape
    np.testing.assert_allclose(np.sort_complex(deflated), np.sort_complex(rest), rtol=0, atol=RTOL_DEFLATE)
    radius = np.max(np.abs(deflated))
    assert (radius < 1) == (order == 1) and float(st.spectral_radius(dplant, k, tau / 1e-3, 8)) > 1  # the buffer's grows at every order


def test_pade_and_cubic_matrices_refuse_bad_input(plant):
    dplant = discretize(plant, 1e-3, "rk4")
    for call, said in (
        (lambda: st.pade_loop_matrix(plant, 55.0, 0.005, 2), r"plant must be a DiscretePlant \(build one with jaxflex.discretize"),
        (lambda: st.deflated_pade_loop_matrix(plant, 55.0, 0.005, 2), r"plant must be a DiscretePlant"),
        (lambda: st.deflated_pade_loop_matrix(dplant, float("nan"), 0.005, 2), r"k must be finite; got nan"),
        (lambda: st.pade_loop_matrix(dplant, 55.0, 0.0, 2), r"tau_s must be a finite delay > 0 \(s\); got 0.0"),
        (lambda: st.pade_loop_matrix(dplant, 55.0, float("nan"), 2), r"tau_s must be a finite delay > 0"),
        (lambda: st.pade_loop_matrix(dplant, 55.0, 0.005, 0), r"^order must be an integer in \[1, 100\]; got 0"),
        (lambda: st.pade_loop_matrix(dplant, 55.0, 0.005, 2, "xyz"), r"hold must be one of \('foh', 'zoh'\); got 'xyz'"),
        (lambda: st.deflated_loop_matrix(dplant, 55.0, 4.3, 8, "quadratic"), r"interpolation must be 'linear' or 'cubic'; got 'quadratic'"),
        (lambda: st.deflated_loop_matrix(dplant, 55.0, 9.5, 8, "cubic"), r"delay_steps must be a number of samples in \[1, n_hist = 8\] \(fractional: read between samples by interpolation\); got 9.5"),
    ):
        with pytest.raises(ValueError, match=said):
            call()


@pytest.mark.parametrize("d", [4.3, 1.6, 7.5, 5.0])
def test_cubic_matrix_reproduces_the_rollout_and_deflates_the_structural_eigenvalue(plant, d):
    """The loop tune penalises and reports with delay = "cubic" (it used the linear read's,
    the same loop at whole samples only): 4-point Lagrange on lags floor(d) - 1 .. floor(d) + 2,
    clamped into the buffer of 9 samples at d = 1.6 (lags 0..3) and d = 7.5 (lags 5..8)."""
    dplant = discretize(plant, 1e-3, "zoh")
    x0 = jax.random.normal(jax.random.key(1), (6,)) * jnp.asarray([1e-2, 1e-3, 1e-4, 1e-1, 1e-2, 1e-3])
    steps, n_hist = 200, 8
    traj = rollout(dplant, dfs(1e-3, capacity=n_hist, interpolation="cubic"), DFSParams(PAPER_K, d * 1e-3), initial_condition(x0, steps))
    x = np.asarray(traj.x)
    theta = x[:, 0]
    hist = np.stack([theta[np.maximum(t - np.arange(1, n_hist + 1), 0)] for t in range(steps)])
    mat = np.asarray(st.sampled_loop_matrix(dplant, PAPER_K, d, n_hist, interpolation="cubic"))
    prop = [np.concatenate([x[0], hist[0]])]
    for _ in range(steps - 1):
        prop.append(mat @ prop[-1])
    np.testing.assert_allclose(np.asarray(prop)[:, :6], x, rtol=0, atol=1e-10 * np.abs(x).max())
    full = np.linalg.eigvals(mat)
    deflated = np.linalg.eigvals(np.asarray(st.deflated_loop_matrix(dplant, PAPER_K, d, n_hist, interpolation="cubic")))
    rest = np.delete(full, np.argmin(np.abs(full - 1)))
    assert np.min(np.abs(full - 1)) < 1e-12
    big = deflated[np.abs(deflated) > SMALL_EIG]  # the unread slots' zeros scatter, as in the linear read's test
    assert big.shape[0] == np.sum(np.abs(rest) > SMALL_EIG)
    for lam in big:
        assert np.min(np.abs(rest - lam)) < RTOL_DEFLATE
    linear = float(st.spectral_radius(dplant, PAPER_K, d, n_hist))
    cubic = np.max(np.abs(deflated))
    assert (cubic == pytest.approx(linear, rel=1e-12)) == (d == 5.0)  # the same loop at whole samples only


@pytest.mark.parametrize("k", [0.0, 1e-3, PAPER_K, -55.0])
def test_deflation_removes_exactly_the_structural_eigenvalue(plant, k):
    dplant = discretize(plant, 1e-3, "zoh")
    d = 5
    mat = np.asarray(st.sampled_loop_matrix(dplant, k, d))
    v = st.structural_directions(dplant)
    r = np.concatenate([v, np.ones((d, 1)) * (np.asarray(dplant.C[:1]) @ v)])
    assert np.max(np.abs(mat @ r - r)) < 1e-13  # [v, c v, ..., c v] is an eigenvector for eigenvalue 1 at every k
    full = np.linalg.eigvals(mat)
    deflated = np.asarray(st.sampled_eigenvalues(dplant, k, d))
    i_one = np.argmin(np.abs(full - 1))
    rest = np.delete(full, i_one)
    assert deflated.shape == rest.shape
    # At k = 0 the history is a nilpotent Jordan block of size d: its computed eigenvalues
    # scatter by ~eps^(1/d) around 0 in both computations, so only |lambda| > SMALL_EIG are matched.
    big = deflated[np.abs(deflated) > SMALL_EIG]
    assert big.shape[0] == np.sum(np.abs(rest) > SMALL_EIG)
    for lam in big:  # multiset equality up to eigenvalue conditioning
        j = np.argmin(np.abs(rest - lam))
        assert abs(rest[j] - lam) < RTOL_DEFLATE
        rest = np.delete(rest, j)
    if k == 0.0:  # open loop: the largest non-structural |exp(lambda dt)| of the plant
        lam = np.linalg.eigvals(np.asarray(plant.A))
        lam = lam[np.argsort(np.abs(lam))][1:]
        np.testing.assert_allclose(float(st.spectral_radius(dplant, k, d)), np.max(np.abs(np.exp(lam * 1e-3))), rtol=1e-12)


def test_spectral_radius_jit_vmap_grad(plant):
    dplant = discretize(plant, 1e-3, "zoh")
    ks = jnp.asarray([10.0, PAPER_K, 90.0])
    eager = np.asarray([float(st.spectral_radius(dplant, k, 5)) for k in ks])
    radius = jax.jit(jax.vmap(lambda k: st.spectral_radius(dplant, k, 5)))
    np.testing.assert_allclose(np.asarray(radius(ks)), eager, rtol=1e-12)
    grid = np.asarray(st.sampled_radius_grid(dplant, np.asarray(ks), np.asarray([2, 5, 9])))
    np.testing.assert_allclose(grid[1], eager, rtol=1e-12)  # padded history, traced delay
    np.testing.assert_allclose(grid[2, 1], float(st.spectral_radius(dplant, PAPER_K, 9)), rtol=1e-12)
    g = float(jax.grad(lambda k: st.spectral_radius(dplant, k, 5))(PAPER_K))
    h = 1e-4
    plus, minus = np.asarray(radius(jnp.asarray([PAPER_K + h, PAPER_K - h, PAPER_K])))[:2]
    fd = (plus - minus) / (2 * h)
    assert g != 0.0 and math.isfinite(g)
    np.testing.assert_allclose(g, fd, rtol=RTOL_GRAD)


def test_spectral_radius_of_a_fractional_delay(plant):
    """With n_hist given, a fractional delay (concrete or traced) is the linearly interpolated
    loop, not cut to whole samples; its radius is differentiable in the delay."""
    dplant = discretize(plant, 1e-3, "zoh")
    n_hist = 8

    def oracle(d):  # NumPy: the full loop's spectrum less the eigenvalue nearest 1
        full = np.linalg.eigvals(np.asarray(st.sampled_loop_matrix(dplant, PAPER_K, d, n_hist)))
        return np.abs(np.delete(full, np.argmin(np.abs(full - 1)))).max()

    ds = [5.0, 5.3, 5.9, 6.0]
    expected = np.asarray([oracle(d) for d in ds])
    assert len(set(np.round(expected, 9))) == 4  # a whole-sample cut would repeat 5's radius
    traced = jax.jit(jax.vmap(lambda d: st.spectral_radius(dplant, PAPER_K, d, n_hist)))
    np.testing.assert_allclose(np.asarray(traced(jnp.asarray(ds))), expected, rtol=1e-12)
    np.testing.assert_allclose([float(st.spectral_radius(dplant, PAPER_K, d, n_hist)) for d in ds], expected, rtol=1e-12)
    g = float(jax.grad(lambda d: st.spectral_radius(dplant, PAPER_K, d, n_hist))(5.3))
    h = 1e-5
    np.testing.assert_allclose(g, (oracle(5.3 + h) - oracle(5.3 - h)) / (2 * h), rtol=RTOL_GRAD)
    with pytest.raises(ValueError, match=r"delay_steps must be a number of samples in \[1, n_hist = 8\] .*got 8.5"):
        st.spectral_radius(dplant, PAPER_K, 8.5, n_hist)
    with pytest.raises(ValueError, match=r"^delay_steps must be an integer in \[1, 2048\] \(samples\); got 5.3; a fractional delay needs n_hist, the history length \(an integer >= the delay\)$"):
        st.spectral_radius(dplant, PAPER_K, 5.3)  # no n_hist: whole samples only, and the refusal says where a fractional delay goes
    for whole in (0.005 / 0.001, 0.003 / 0.001, np.float32(7.0)):  # tau_s / dt, 5.0 and 2.9999999999999996: that many samples
        np.testing.assert_array_equal(st.sampled_loop_matrix(dplant, PAPER_K, whole), st.sampled_loop_matrix(dplant, PAPER_K, round(float(whole))))
        assert float(st.spectral_radius(dplant, PAPER_K, whole)) == float(st.spectral_radius(dplant, PAPER_K, round(float(whole))))
    with pytest.raises(ValueError, match=r"^delay_steps must be an integer in \[1, 2048\] \(samples\); got 0$"):
        st.spectral_radius(dplant, PAPER_K, 0)
    for bad in (0.0, -2.0, 1e-7):  # quoted as given, not as rounded ('got 0' for 1e-7)
        with pytest.raises(ValueError, match=rf"^delay_steps must be an integer in \[1, 2048\] \(samples\); got {bad!r}$"):
            st.spectral_radius(dplant, PAPER_K, bad)
    # the grids read tau / dt alike (they refused 3.0, and an int32 cast would have cut 2.9999999999999996 to 2)
    np.testing.assert_array_equal(st.sampled_radius_grid(dplant, [PAPER_K], [0.003 / 0.001, 5.0]), st.sampled_radius_grid(dplant, [PAPER_K], [3, 5]))
    with pytest.raises(ValueError, match=r"^delay_steps must be an integer in \[1, 2048\] \(samples\); got 2.5$"):
        st.sampled_radius_grid(dplant, [PAPER_K], [2.5])


def test_chart_agrees_with_simulation(plant):
    """Points near the sampled stability boundary (|radius - 1| in [2e-3, 5e-2]), both sides:
    the jaxflex rollout (ZOH plant, dfs controller) grows from one late window to the next
    exactly where the radius exceeds 1. theta is left out: its constant (structural) part
    neither grows nor decays."""
    dt = 1e-3
    k_values = np.linspace(5.0, 150.0, 12)
    delays = np.arange(1, 41)
    chart = st.stability_chart(plant, k_values, delays, dt, "zoh", continuous=False)
    radius = chart.spectral_radius
    near = (np.abs(radius - 1) >= SIM_MARGIN) & (np.abs(radius - 1) <= 5e-2)
    i_tau, i_k = np.nonzero(near)
    assert np.sum(radius[near] < 1) >= 20 and np.sum(radius[near] > 1) >= 20
    dplant = discretize(plant, dt, "zoh")
    controller = dfs(dt, capacity=int(delays.max()))
    x0 = jnp.asarray([1e-2, 1e-3, 1e-4, 1e-1, 1e-2, 1e-3])
    scenario = initial_condition(x0, 4 * SIM_WINDOW)

    @jax.jit
    @jax.vmap
    def growth(k, tau):
        flex = rollout(dplant, controller, DFSParams(k, tau), scenario).x[:, 1:]
        late = jnp.max(jnp.abs(flex[-SIM_WINDOW:]))
        prev = jnp.max(jnp.abs(flex[-2 * SIM_WINDOW : -SIM_WINDOW]))
        return late / prev, late / jnp.max(jnp.abs(flex))

    ratio, level = (np.asarray(a) for a in growth(jnp.asarray(k_values[i_k]), jnp.asarray(chart.tau_s[i_tau])))
    at_floor = level < SIM_FLOOR
    growing = (ratio > 1) & ~at_floor
    np.testing.assert_array_equal(growing, radius[near] > 1)
    assert not np.any(at_floor & (radius[near] > 1))
    # the growth per window follows the radius (loose: transients of the other eigenvalues)
    ok = ~at_floor
    np.testing.assert_allclose(np.log(ratio[ok]), SIM_WINDOW * np.log(radius[near][ok]), rtol=0.3)


# ---------------------------------------------------------------------------------------------
# 4. Validation, plot and report


def test_validation_errors(plant):
    dplant = discretize(plant, 1e-3, "zoh")
    for bad in (math.nan, math.inf):
        with pytest.raises(ValueError, match="k must be finite"):
            st.critical_delays(plant, bad)
        with pytest.raises(ValueError, match="k must be finite"):
            st.spectral_radius(dplant, bad, 5)
        with pytest.raises(ValueError, match="k must be finite"):
            stability_report.run("/nonexistent-not-written", k=bad)
    for bad in (0.0, -0.005, math.nan):
        with pytest.raises(ValueError, match="tau_s must be finite and > 0"):
            st.rightmost_root(plant, PAPER_K, bad)
        with pytest.raises(ValueError, match="tau_s must be finite and > 0"):
            stability_report.run("/nonexistent-not-written", tau_s=bad)
    with pytest.raises(ValueError, match="tau_s must be a whole number"):
        st.delay_steps_of(0.0055, 1e-3)
    with pytest.raises(ValueError, match="tau_s must be a whole number"):
        stability_report.run("/nonexistent-not-written", tau_s=0.0055)
    with pytest.raises(ValueError, match="must be an integer in \\[1, 2048\\]"):
        st.spectral_radius(dplant, PAPER_K, 0)
    with pytest.raises(ValueError, match="delay_steps must be an integer in \\[1, 2048\\]"):
        st.sampled_loop_matrix(dplant, PAPER_K, 2.5)
    for bad in (0, -1, 1.5):
        with pytest.raises(ValueError, match="n_modes must be an integer in \\[1, 100\\]"):
            st.first_destabilising_delay(PAPER_K, bad)
        with pytest.raises(ValueError, match="n_modes must be an integer in \\[1, 100\\]"):
            stability_report.run("/nonexistent-not-written", n_modes=bad)
    with pytest.raises(ValueError, match="n_cheb must be an integer >= 2"):
        st.rightmost_root(plant, PAPER_K, 0.005, 1)


def test_the_matrices_check_their_gain_and_delay(plant):
    """deflated_loop_matrix and generator_matrix took any delay: a delay longer than the
    history dropped the delayed term (a loop with spectral radius 1.055 looked stable, 0.995),
    and tau = 0 gave an inf/NaN generator. Traced values still pass (vmap over delays)."""
    dplant = discretize(plant, 1e-3, "zoh")
    with pytest.raises(ValueError, match=r"delay_steps must be a number of samples in \[1, n_hist = 5\]"):
        st.deflated_loop_matrix(dplant, PAPER_K, 10.0, 5)
    with pytest.raises(ValueError, match=r"delay_steps must be a number of samples in \[1, n_hist = 5\].*got nan"):
        st.deflated_loop_matrix(dplant, PAPER_K, float("nan"), 5)
    with pytest.raises(ValueError, match="k must be finite"):
        st.deflated_loop_matrix(dplant, float("inf"), 5, 5)
    for matrix in (st.deflated_loop_matrix, st.sampled_loop_matrix, st.spectral_radius):  # less than one sample
        with pytest.raises(ValueError, match=r"delay_steps must be a number of samples in \[1, n_hist = 4\] .*; got 0.5"):
            matrix(dplant, PAPER_K, 0.5, 4)
    for tau in (0.0, -0.005, float("nan")):
        with pytest.raises(ValueError, match="tau_s must be finite and > 0"):
            st.generator_matrix(plant, PAPER_K, tau)
    with pytest.raises(ValueError, match="k must be finite"):
        st.generator_matrix(plant, float("nan"), 0.005)
    radii = jax.vmap(lambda d: jnp.max(jnp.abs(jnp.linalg.eigvals(st.deflated_loop_matrix(dplant, PAPER_K, d, 12)))))(jnp.asarray([5.0, 10.0]))
    np.testing.assert_allclose(radii, [float(st.spectral_radius(dplant, PAPER_K, d)) for d in (5, 10)], rtol=1e-9)
    assert radii[1] > 1  # the 10-sample loop is unstable when its history holds the delay


def test_grids_and_root_counts_name_bad_values(plant):
    """unstable_root_count took NaN delays (the open-loop count) and strings, and the grids
    failed in NumPy on an empty delay list or a gain that is not a number."""
    result = st.critical_delays(plant, PAPER_K)
    dplant = discretize(plant, 1e-3, "zoh")
    for call, match in (
        (lambda: st.unstable_root_count(result, [float("nan")]), r"tau_s must be in \(0, tau_max_s = 0.05\] s"),
        (lambda: st.unstable_root_count(result, "0.01"), "tau_s must be a real number or an array of real numbers; got '0.01'"),
        (lambda: st.unstable_root_count(result, []), "tau_s must hold at least one delay"),
        (lambda: st.sampled_radius_grid(dplant, [PAPER_K], []), r"k_values and delay_steps must be non-empty 1-D arrays \(the grid's axes\); got shapes \(1,\), \(0,\)"),
        (lambda: st.stability_chart(plant, ["a"], [5]), r"k_values must be a real number or an array of real numbers; got \['a'\]"),
        # each delay of a count in (0, tau_max_s]: below it no switch is counted, beyond it one may be missed
        (lambda: st.unstable_root_count(result, [0.0]), r"tau_s must be in \(0, tau_max_s = 0.05\] s; got range \[0, 0\]"),
        (lambda: st.unstable_root_count(result, [-0.01]), r"tau_s must be in \(0, tau_max_s = 0.05\] s"),
        (lambda: st.unstable_root_count(result, [0.06]), r"tau_s must be in \(0, tau_max_s = 0.05\] s; got range \[0.06, 0.06\]"),
        (lambda: st.rightmost_real_grid(plant, [PAPER_K], [0.0]), r"tau_s must be finite and > 0; got 0.0"),
        (lambda: st.rightmost_real_grid(plant, [PAPER_K], [-0.005]), r"tau_s must be finite and > 0; got -0.005"),
        (lambda: st.sampled_radius_grid(dplant, [PAPER_K, float("nan")], [5]), "k must be finite; got nan"),
        (lambda: st.sampled_radius_grid(dplant, [PAPER_K, float("inf")], [5]), "k must be finite; got inf"),
    ):
        with pytest.raises(ValueError, match=match):
            call()
    assert st.unstable_root_count(result, [0.004]).tolist() == [0]


def test_each_analysis_refuses_the_other_kind_of_plant(plant):
    """A sampled plant given to the continuous-time analyses was read as if ``Ad`` were ``A``:
    critical_delays, crossing_frequencies, characteristic_polynomials, delta and
    first_destabilising_delay returned numbers (a first destabilising delay of 150 s for the
    paper's arm at k = 10), the rest an AttributeError. Each names the plant it needs."""
    dplant = discretize(plant, 1e-3, "zoh")
    continuous = [
        lambda p: st.characteristic_polynomials(p, 10.0),
        lambda p: st.delta(p, 10.0, 0.01, 1j),
        lambda p: st.crossing_frequencies(p, 10.0),
        lambda p: st.crossing_frequencies(p, 0.0),
        lambda p: st.critical_delays(p, 10.0),
        lambda p: st.first_destabilising_delay(10.0, plant=p),
        lambda p: st.generator_matrix(p, 10.0, 0.01, 4),
        lambda p: st.characteristic_roots(p, 10.0, 0.01, 4),
        lambda p: st.rightmost_root(p, 10.0, 0.01, 4),
        lambda p: st.rightmost_real_grid(p, [10.0], [0.01], 4),
        lambda p: st.stability_chart(p, [10.0], [5]),
    ]
    sampled = [
        lambda p: st.sampled_loop_matrix(p, 10.0, 5),
        lambda p: st.deflated_loop_matrix(p, 10.0, 5, 5),
        lambda p: st.sampled_eigenvalues(p, 10.0, 5),
        lambda p: st.spectral_radius(p, 10.0, 5),
        lambda p: st.sampled_radius_grid(p, [10.0], [5]),
    ]
    for call in continuous:
        with pytest.raises(ValueError, match=r"plant must be a LinearPlant \(build one with make_plant\(...\); a DiscretePlant is already sampled\); got DiscretePlant"):
            call(dplant)
        with pytest.raises(ValueError, match=r"plant must be a LinearPlant .*; got the function make_plant itself: call it to build one"):
            call(make_plant)
    for call in sampled:
        with pytest.raises(ValueError, match=r"plant must be a DiscretePlant \(build one with jaxflex.discretize\(plant, dt, method\)\); got LinearPlant"):
            call(plant)
    for call in (st.loop_vectors, st.structural_directions, paper_scenario):
        with pytest.raises(ValueError, match=r"plant must be a LinearPlant or DiscretePlant \(build one with make_plant\(...\), and sample it with discretize\(...\) if needed\); got dict"):
            call({"A": plant.A})


def test_plot_stability_chart():
    k = np.linspace(0, 100, 5)
    tau = np.arange(1, 5) * 1e-3
    radius = 0.9 + 0.05 * np.add.outer(np.arange(4), np.arange(5)) / 2
    fig = plotting.stability_chart(k, tau, radius, radius - 1.05, np.full(5, 0.003), point=(55.0, 0.005))
    assert len(fig.axes) == 1
    plt.close(fig)
    fig = plotting.stability_chart(k, tau, radius)
    plt.close(fig)
    assert not plt.get_fignums()


def test_report_writes_chart_and_json(tmp_path):
    result = stability_report.run(tmp_path, n_k=6, tau_max_s=0.012, n_cheb=24)
    assert (tmp_path / "stability_chart.png").stat().st_size > 1000
    on_disk = json.loads((tmp_path / "stability.json").read_text())
    assert on_disk == result
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]
    assert result["k"] == PAPER_K and result["tau_s"] == PAPER_TAU and result["n_modes"] == 2 and result["dt"] == 1e-3
    for cr in result["crossings"]:
        assert set(cr) >= {"freq_hz", "tau_s", "direction"} and cr["direction"] in ("destabilising", "stabilising")
    first = st.first_destabilising_delay(PAPER_K, 2)
    np.testing.assert_allclose(result["first_destabilising_delay_s"], first, rtol=1e-12)
    assert any(first in cr["tau_s"] for cr in result["crossings"])
    dplant = discretize(make_plant(n_modes=2), 1e-3, "zoh")
    np.testing.assert_allclose(result["spectral_radius"], float(st.spectral_radius(dplant, PAPER_K, 5)), rtol=1e-12)
    assert result["stable_sampled"] and result["stable_continuous"]
    root = result["rightmost_root"]
    assert root["real"] < 0 and root["converged"] and root["n_cheb"] == 2 * 24 and root["change_from_half_n_cheb"] < 1e-8
    assert complex(root["real"], root["imag"]) == complex(st.rightmost_root(make_plant(n_modes=2), PAPER_K, PAPER_TAU, root["n_cheb"]))
    v = result["first_destabilising_validation"]
    assert v["rightmost_real_below"] < 0 < v["rightmost_real_above"]
    # the 2-mode model's first destabilising delay (a crossing above its top mode) beside 6 modes'
    more = result["first_destabilising_delay_more_modes"]
    assert more == {"n_modes": 2 + stability_report.MORE_MODES, "s": st.first_destabilising_delay(PAPER_K, 2 + stability_report.MORE_MODES), "error": None}
    assert more["s"] < 0.9 * first
    assert result["excluded_structural"]["multiplicity"] == 1
    # the sampled loop's own first destabilising delay, in whole samples: 6 ms is stable and
    # 7 ms is not, below the continuous loop's 7.315 ms
    assert float(st.spectral_radius(dplant, PAPER_K, 6)) < 1 <= float(st.spectral_radius(dplant, PAPER_K, 7))
    assert result["first_destabilising_delay_sampled_s"] == pytest.approx(7e-3, rel=1e-12) and 7e-3 < first
    assert result["first_destabilising_delay_sampled_tau_max_s"] == pytest.approx(0.012, rel=1e-12)


def test_report_searches_beyond_its_chart_for_the_larger_models_first_delay(tmp_path):
    """k = 10: the first destabilising delay (about 12 ms) lies beyond an 8 ms chart; the
    more-modes figure is still the larger model's own, not 'none up to the chart's range'."""
    result = stability_report.run(tmp_path, k=10.0, n_k=3, tau_max_s=0.008, n_cheb=16)
    more, expected = result["first_destabilising_delay_more_modes"], st.first_destabilising_delay(10.0, 2 + stability_report.MORE_MODES)
    assert expected > 0.008 and more["n_modes"] == 2 + stability_report.MORE_MODES and more["s"] == pytest.approx(expected, rel=1e-12)


def test_the_charts_first_destabilising_delay_is_not_cut_at_its_range(plant):
    """A chart of 1-3 ms at k = 55 still gives the first destabilising delay above it (7.3 ms),
    where the continuous loop's rightmost root changes sign."""
    first = float(st.stability_chart(plant, [PAPER_K], [1, 2, 3], 1e-3, continuous=False).first_destabilising_delay_s[0])
    assert math.isfinite(first) and first > 0.003
    below, above = (complex(st.rightmost_root(plant, PAPER_K, factor * first, 48)).real for factor in (0.99, 1.01))
    assert below < 0 < above


def test_an_interrupted_report_leaves_the_earlier_pair_of_files(tmp_path, monkeypatch):
    """The chart and the JSON replace an earlier run's together: Ctrl-C while the JSON is
    written leaves the earlier chart too (it was replaced first, beside the earlier JSON)."""
    stability_report.run(tmp_path, k=20.0, n_k=2, tau_max_s=0.006, n_cheb=8)
    before = {name: (tmp_path / name).read_bytes() for name in ("stability_chart.png", "stability.json")}

    def interrupted(path, data):
        raise KeyboardInterrupt

    monkeypatch.setattr(stability_report.fileio, "write_json", interrupted)
    with pytest.raises(KeyboardInterrupt):
        stability_report.run(tmp_path, k=80.0, n_k=2, tau_max_s=0.006, n_cheb=8)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_report_refuses_a_chart_range_it_cannot_hold(tmp_path):
    """`jaxflex stability --tau 1` once ran out of memory after 40 s (8 s of delay samples per
    chart matrix); now it is refused at once, naming the range and the largest tau."""
    with pytest.raises(ValueError, match=r"tau_max_s = 0.24 s is 240 samples of dt = 0.001 s; at most 160 are supported: pass tau_max_s \(jaxflex stability --tau-max\) from tau_s to 0.16 s, or leave it out \(its default: the largest of 8 tau_s, 40 ms and 20 samples, at most 160 samples\)"):
        stability_report.run(tmp_path, tau_s=0.03, tau_max_s=0.24)
    # a delay no range can hold (5 ms typed as 5) is refused as such: the range's message sent
    # it to --tau-max, whose own check then asked for a range up to 5 s
    for tau, samples in ((1.0, 1000), (5.0, 5000), (0.161, 161)):
        with pytest.raises(ValueError, match=rf"^tau_s must be at most 160 samples of dt = 0.001 s, 0.16 s, for the chart to hold it; got {tau:g} s, {samples} samples \(tau_s is in seconds, 5 ms is 0.005; or a larger dt\)$"):
            stability_report.run(tmp_path, tau_s=tau, tau_max_s=None if tau < 1 else 0.16)
    with pytest.raises(ValueError, match="tau_max_s = 0.5 s is 500 samples"):
        stability_report.run(tmp_path, tau_max_s=0.5)
    # a chart that would not hold the point analysed (its star off the top)
    with pytest.raises(ValueError, match=r"tau_max_s must be at least the delay analysed, tau_s = 0.005 s, so that the chart holds that point; got 0.004 s"):
        stability_report.run(tmp_path, tau_max_s=0.004)
    assert not list(tmp_path.iterdir())
    stability_report.run(tmp_path / "edge", tau_s=0.16, tau_max_s=0.16, n_k=2, n_tau=2, n_cheb=8)  # 160 samples: charted
    # the default range stops at the chart's limit: 8 tau of 21-160 samples was refused, a range
    # the user had not typed (`jaxflex stability --tau 0.021`)
    for tau, top in ((0.021, 0.16), (0.16, 0.16), (0.004, 0.04), (0.01, 0.08)):
        chart = stability_report.run(tmp_path / f"default{tau}", tau_s=tau, n_k=2, n_tau=2, n_cheb=8)["chart"]
        assert chart["tau_range_s"][1] == pytest.approx(top, rel=1e-12), tau


def test_cli_names_tau_beyond_the_chart_by_its_option(tmp_path, capsys):
    """The tau refusal names --tau, typed or its default (it named the library's tau_s when
    only --dt was typed, and 5 ms at dt = 1e-5 s is 500 samples)."""
    from jaxflex import cli

    assert cli.main(["stability", "--tau", "5", "--out", str(tmp_path / "a")]) == 2
    assert "error: --tau must be at most 160 samples of dt = 0.001 s, 0.16 s, for the chart to hold it; got 5 s, 5000 samples" in capsys.readouterr().err
    assert cli.main(["stability", "--dt", "1e-5", "--out", str(tmp_path / "b")]) == 2
    assert "error: --tau (default 0.005 s) must be at most 160 samples of dt = 1e-05 s, 0.0016 s, for the chart to hold it; got 0.005 s, 500 samples" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in "ab")


def test_cli_tau_max_sets_the_chart_range(tmp_path, monkeypatch):
    """`--tau-max` reaches the chart (by default 1-40 ms for any delay up to 5 ms: a 1 ms delay
    sat at a fortieth of its height)."""
    from jaxflex import cli

    seen = {}

    def run(out_dir, **kwargs):
        seen.update(kwargs)
        raise ValueError("stop")

    monkeypatch.setattr(stability_report, "run", run)
    assert cli.main(["stability", "--tau", "0.001", "--tau-max", "0.008", "--out", str(tmp_path / "o")]) == 2
    assert seen["tau_s"] == 0.001 and seen["tau_max_s"] == 0.008
    assert cli.main(["stability", "--out", str(tmp_path / "o")]) == 2
    assert seen["tau_max_s"] is None  # the report's default range


def test_default_chart_range_fits_the_limit_at_a_fine_sample_time(tmp_path):
    """The default range's 40 ms floor is 400 samples at dt = 0.1 ms: it is capped at the
    chart's 160 samples, so a small delay is charted rather than refused."""
    result = stability_report.run(tmp_path, tau_s=5e-4, dt=1e-4, n_k=3, n_cheb=8)
    np.testing.assert_allclose(result["chart"]["tau_range_s"][1], 160 * 1e-4, rtol=1e-12)


def test_report_analyses_the_given_arm(tmp_path, monkeypatch, capsys):
    """``beam_params`` is the arm analysed (its sampled-loop radius, recorded in the JSON), and
    ``jaxflex stability --config`` reads only the file's [beam] table."""
    from jaxflex import cli
    from jaxflex.beam import BeamParams
    from jaxflex.plant import discretize, make_plant

    arm = BeamParams(length_m=0.6, payload_mass_kg=0.05)
    titles = []
    chart = plotting.stability_chart
    monkeypatch.setattr(plotting, "stability_chart", lambda *a, **kw: titles.append(kw["title"]) or chart(*a, **kw))
    result = stability_report.run(tmp_path / "arm", n_k=2, tau_max_s=0.006, n_cheb=8, beam_params=arm)
    f1, f2 = beam.natural_frequencies_hz(arm, 2)
    assert titles == [f"DFS stability: 0.6 m arm, 2 modes at {f1:.3g}, {f2:.3g} Hz, sampled at 1 ms (zoh)"]  # the chart names its arm
    expected = float(st.spectral_radius(discretize(make_plant(arm, 2), 1e-3, "zoh"), 55.0, 5))
    paper = float(st.spectral_radius(discretize(make_plant(BeamParams(), 2), 1e-3, "zoh"), 55.0, 5))
    np.testing.assert_allclose(result["spectral_radius"], expected, rtol=1e-12)
    assert abs(expected - paper) > 1e-4 and result["beam"]["length_m"] == 0.6

    seen = {}

    def fake_run(out, **kwargs):
        seen.update(kwargs)
        return {"spectral_radius": 0.5, "spectral_radius_rk4": 3531649110.40803719, "stable_sampled": True, "first_destabilising_delay_s": 0.0123,
                "first_destabilising_delay_sampled_s": None, "first_destabilising_delay_sampled_tau_max_s": 0.04, "stable_continuous": stable,
                "crossings": [{"freq_hz": 68.91, "tau_s": [0.0123, 0.1]}], "first_destabilising_delay_more_modes": {"n_modes": 6, "s": first_more, "error": more_error},
                "rightmost_root": {"real": -9.33536 if stable else 28.2199, "imag": imag, "n_cheb": 1024, "change_from_half_n_cheb": 0.0123, "converged": converged}}

    stable, imag, converged, first_more, more_error = True, 0.0, True, 0.01225, None

    monkeypatch.setattr(stability_report, "run", fake_run)
    config = tmp_path / "tune.toml"
    config.write_text('steps = 5\n[beam]\nlength_m = 0.6\npayload_mass_kg = 0.05\n')
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    assert seen["beam_params"] == arm and (seen["n_modes"], seen["dt"]) == (2, 1e-3)
    assert (seen["k"], seen["tau_s"]) == (55.0, 0.005)  # the paper's point by default
    # the loop tune and montecarlo simulate by default (RK4) is printed beside the ZOH one, a
    # large radius in 4 digits (a 4 m thick arm's printed as 3531649110.40803719)
    out, err = capsys.readouterr()
    assert f"the arm of {config}, k = 55, tau = 0.005 s, 2 modes, dt = 0.001 s: sampled-loop spectral radius 0.50000000 (stable; sampled by RK4, the default of tune and montecarlo: 3.532e+09, UNSTABLE), first destabilising delay 0.0123 s (continuous loop; sampled loop: none up to 0.04 s), continuous loop's rightmost root -9.335 /s (stable)" in out
    assert "Chebyshev" not in err and "6 modes" not in err  # 0.4 % from the 6-mode model's: no note
    # a root that did not settle is said to be unsettled, with its change
    stable, imag, converged, first_more = False, -289.84, False, 0.0107
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    out, err = capsys.readouterr()
    top = beam.natural_frequencies_hz(arm, 2)[-1]
    assert f"note: with 6 modes the continuous loop's first destabilising delay is 0.0107 s against 0.0123 s with 2 (its crossing is at 68.91 Hz, above the model's top mode, {top:.4g} Hz): it moves with the modes the model leaves out; --modes 6 analyses the larger model" in err
    assert top < 68.91
    assert "continuous loop's rightmost root 28.22 ± 289.8j /s (UNSTABLE)" in out
    assert "note: the continuous loop's rightmost root moved by 0.0123 rad/s between 512 and 1024 Chebyshev intervals, the most tried: its real part, and stable_continuous in stability.json, are not settled" in err
    # a larger model that could not be analysed is said so, and a first delay that appears or
    # goes with the modes is a change (the delay 'none' where the other is a number)
    more_error = "n_modes = 6: the coefficients overflow float64"
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    assert "note: the first destabilising delay was not rechecked with 6 modes: n_modes = 6: the coefficients overflow float64" in capsys.readouterr().err
    more_error, first_more = None, None
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    assert "first destabilising delay is none against 0.0123 s with 2 (its crossing is at 68.91 Hz, above" in capsys.readouterr().err
    assert cli._moved(None, None) is False and cli._moved(None, 0.01) is True and cli._moved(0.01, 0.01009) is False and cli._moved(0.01, 0.0102) is True
    stable, imag, converged, first_more = True, 0.0, True, 0.01225
    # a config that sets its method is named beside the RK4 radius, which read as the run's own
    for method, whose in (("zoh", f"which {config} does not use"), ("rk4", f"the method of {config}")):
        config.write_text(f'method = "{method}"\n[beam]\nlength_m = 0.6\npayload_mass_kg = 0.05\n')
        assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
        assert f"(stable; sampled by RK4, {whose}: 3.532e+09, UNSTABLE)" in capsys.readouterr().out
    # the tuned arm's model and sample time come from the config, unless the flags say otherwise
    config.write_text('n_modes = 3\n[scenarios]\ndt = 5e-4\n[beam]\nlength_m = 0.6\npayload_mass_kg = 0.05\n')
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    assert (seen["n_modes"], seen["dt"]) == (3, 5e-4)
    assert cli.main(["stability", "--config", str(config), "--modes", "2", "--dt", "0.002", "--tau", "0.004", "--out", str(tmp_path / "o")]) == 0
    assert (seen["n_modes"], seen["dt"], seen["tau_s"]) == (2, 0.002, 0.004)
    # the default delay, the paper's 5 ms, is 2.5 samples there: said so, naming --tau
    capsys.readouterr()
    assert cli.main(["stability", "--config", str(config), "--dt", "0.002", "--out", str(tmp_path / "o")]) == 2
    assert "--tau: its default, the paper's 0.005 s, is 2.5 samples of dt = 0.002 s; pass --tau" in capsys.readouterr().err
    # the model is named before the run (a unit slip in [beam] shows there), with the modes above Nyquist
    freqs = np.asarray(beam.natural_frequencies_hz(arm, 2))
    capsys.readouterr()
    assert cli.main(["stability", "--config", str(config), "--modes", "2", "--dt", "0.02", "--tau", "0.02", "--out", str(tmp_path / "o")]) == 0
    assert (
        f"model: 2 mode(s) at {freqs[0]:.4g}, {freqs[1]:.4g} Hz with damping ratios 0.01, 0.01 in flexible modes 1-2 (damping_ratio = 0.01 of the 2-mode model), sampled every 0.02 s (Nyquist 25 Hz); 1 mode(s) above Nyquist alias in what the controller measures"
        in capsys.readouterr().err
    )
    assert 13 < freqs[0] < 25 < freqs[1]
    assert cli.main(["stability", "--config", str(config), "--dt", "0", "--out", str(tmp_path / "o")]) == 2
    assert "dt must be a finite scalar > 0" in capsys.readouterr().err
    # dt and tau in ms typed as seconds: the first mode above Nyquist is refused, by source (it ran
    # for 20 s and charted delays to 40000 ms)
    assert cli.main(["stability", "--config", str(config), "--modes", "2", "--dt", "1", "--tau", "5", "--out", str(tmp_path / "o")]) == 2
    assert f"--dt must be below {0.5 / freqs[0]:.3g} s, for the arm's first flexible mode, {freqs[0]:.4g} Hz, to lie below the Nyquist frequency 0.5 / dt" in capsys.readouterr().err
    config.write_text("[scenarios]\ndt = 0.04\n")  # the paper's arm: 13.32 Hz above Nyquist, 12.5 Hz
    assert cli.main(["stability", "--config", str(config), "--tau", "0.08", "--out", str(tmp_path / "o")]) == 2
    assert f"[scenarios] dt of {config} must be below 0.0375 s" in capsys.readouterr().err
    config.write_text("[beam]\ndamping_ratio = 1\n")  # 1 % typed as 1: said beside the ratios
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    assert "(damping_ratio = 1 of the 2-mode model), sampled every 0.001 s (Nyquist 500 Hz); a damping_ratio of 1 damps the modes critically (1 % is 0.01)\n" in capsys.readouterr().err
    for ratio, how in (("0.6", "heavily"), ("2", "past critically (overdamped)")):
        config.write_text(f"[beam]\ndamping_ratio = {ratio}\n")
        assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
        assert f"; a damping_ratio of {ratio} damps the modes {how} (1 % is 0.01)\n" in capsys.readouterr().err
    config.write_text("[beam]\nlength = 0.6\n")
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    # a misspelt key or table is refused, not read as "use the paper's arm" (it was, silently)
    for text, name in (("[Beam]\nlength_m = 0.6\n", "'Beam'"), ("n_mode = 3\n", "'n_mode'"), ("[scenarios]\ndT = 0.002\n", "'dT'")):
        config.write_text(text)
        capsys.readouterr()
        assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
        assert name in capsys.readouterr().err
    # a montecarlo config serves too, and without [beam] the paper's arm is named
    config.write_text('chunk = 8\npercentiles = [5, 95]\n')
    assert cli.main(["stability", "--config", str(config), "--out", str(tmp_path / "o")]) == 0
    assert seen["beam_params"] == BeamParams() and "the paper's arm, k = 55" in capsys.readouterr().out


def test_huge_gain_is_refused_by_name_not_by_memory():
    """k = 1e30 once asked NumPy for 2.3 PiB of critical delays (and k = 1e9 ran for 10 minutes,
    one Python call per delay). The delays of a crossing are now computed in one vector call,
    and a crossing with more than a million of them is refused naming k and the count."""
    plant = make_plant(n_modes=2)
    with pytest.raises(ValueError, match=r"k = 1e\+30: the loop crosses the imaginary axis at .* Hz, every .* s of delay, which is .* critical delays up to 1 s \(at most 1e\+06"):
        st.first_destabilising_delay(1e30, plant=plant)
    # the vector call gives the delays and directions of the per-delay loop it replaced
    crit = st.critical_delays(plant, 500.0, 0.5)
    A, b, c = st.loop_vectors(plant)
    for crossing in crit.crossings:
        looped = [np.real(st._dsdtau(A, b, c, 500.0, t, 1j * crossing.omega)[0]) for t in crossing.tau_s]
        np.testing.assert_allclose(crossing.re_dsdtau, looped, rtol=1e-12)


def test_a_plant_whose_polynomial_overflows_is_refused_by_name():
    """At 18 modes the characteristic polynomial's coefficients overflow float64; the analysis
    said only 'Array must not contain infs or NaNs' (NumPy's root finder). 17 modes still work."""
    with pytest.raises(ValueError, match=r"n_modes = 18: the coefficients of this plant's characteristic polynomial overflow float64"):
        st.crossing_frequencies(make_plant(n_modes=18), 55.0)
    assert st.crossing_frequencies(make_plant(n_modes=17), 55.0).size > 0


def _root_near(plant, k, tau, s0, deflate=False):
    """The root of Delta(s, tau) (of Delta / s with ``deflate``, past the structural root at 0)
    nearest ``s0``, by Newton's method with a central-difference derivative."""
    f = (lambda s: st.delta(plant, k, tau, s) / s) if deflate else (lambda s: st.delta(plant, k, tau, s))
    s = complex(s0)
    for _ in range(50):
        h = 1e-7 * max(1.0, abs(s))
        step = f(s) / ((f(s + h) - f(s - h)) / (2 * h))
        s -= step
        if abs(step) < 1e-13 * max(1.0, abs(s)):
            break
    return s


def test_root_velocities_match_finite_differences_of_the_roots(plant, crit):
    """Re ds/dtau at each crossing, and ds/dtau of the real crossing through 0, are numbers
    in the stability report: their magnitudes, not only their signs, against the roots of
    Delta moved by a central difference in tau."""
    checked = 0
    for k, result in crit.items():
        for cr in (cr for cr in result.crossings if cr.tau_s.size):
            tau = cr.tau_s[0]
            h = 1e-5 * tau
            up, down = (_root_near(plant, k, tau + d, 1j * cr.omega) for d in (h, -h))
            np.testing.assert_allclose(cr.re_dsdtau[0], ((up - down) / (2 * h)).real, rtol=1e-4, err_msg=f"k = {k}, {cr.freq_hz} Hz")
            checked += 1
    assert checked >= 4
    zero = crit[-55.0].zero_crossing
    h = 1e-3 * zero.tau_s  # Delta / s loses digits near 0 (4e-7 at tau_0): a wider step keeps the roots above that
    up, down = (_root_near(plant, -55.0, zero.tau_s + d, 1e-9, deflate=True) for d in (h, -h))
    np.testing.assert_allclose(zero.dsdtau, ((up - down) / (2 * h)).real, rtol=1e-4)


# ---------------------------------------------------------------------------------------------
# The report's derived numbers and default chart grid, against independent rules


def _numpy_loop_radius(dplant, k, d):
    """Spectral radius of the sampled DFS loop built here in NumPy: xi = [x, theta_{k-1..k-d}],
    u = -k (c x - theta_{k-d}); the structural eigenvalue nearest 1 is removed."""
    Ad, Bd, c = (np.asarray(a, np.float64) for a in (dplant.Ad, dplant.Bd, dplant.C[:1]))
    n = Ad.shape[0]
    m = np.zeros((n + d, n + d))
    m[:n, :n] = Ad - k * Bd @ c
    m[:n, n + d - 1] = k * Bd[:, 0]  # theta_{k-d} is the last history slot
    m[n, :n] = c[0]  # theta_k enters the history
    for i in range(1, d):
        m[n + i, n + i - 1] = 1.0  # the history shifts by one sample
    eig = np.linalg.eigvals(m)
    return float(np.max(np.abs(np.delete(eig, np.argmin(np.abs(eig - 1))))))


@pytest.fixture(scope="module")
def coarse_report(tmp_path_factory):
    """One report at dt = 4 ms (RK4 and ZOH loops differ visibly there), default chart range."""
    return stability_report.run(tmp_path_factory.mktemp("coarse"), tau_s=0.008, dt=0.004, n_k=2, n_tau=2, n_cheb=16)


def test_report_default_chart_grid(coarse_report):
    """Default k range [0, 3 k] = [0, 165]; default tau top max(8 tau, 40 ms, 20 dt) = 20 * 4 ms = 0.08 s."""
    chart = coarse_report["chart"]
    assert chart["k_range"] == [0.0, 3 * PAPER_K]
    np.testing.assert_allclose(chart["tau_range_s"], [0.004, 20 * 0.004], rtol=1e-12)


def test_report_other_method_radius_is_the_rk4_loop(coarse_report):
    """spectral_radius_rk4 (method zoh reports RK4 alongside) is the RK4-sampled loop's radius,
    and spectral_radius the ZOH one's, each rebuilt in NumPy (d = 2 samples)."""
    plant = make_plant(n_modes=2)
    rk4 = _numpy_loop_radius(discretize(plant, 0.004, "rk4"), PAPER_K, 2)
    zoh = _numpy_loop_radius(discretize(plant, 0.004, "zoh"), PAPER_K, 2)
    assert abs(rk4 - zoh) > 1e-3  # the check below can tell the two apart
    np.testing.assert_allclose(coarse_report["spectral_radius_rk4"], rk4, rtol=1e-10)
    np.testing.assert_allclose(coarse_report["spectral_radius"], zoh, rtol=1e-10)


def test_report_rightmost_frequency_is_imag_over_two_pi(coarse_report):
    root = coarse_report["rightmost_root"]
    assert abs(root["imag"]) > 1.0  # an oscillating root, so the frequency is not trivially 0
    assert root["freq_hz"] == pytest.approx(abs(root["imag"]) / (2 * np.pi), rel=1e-12)


def test_report_validation_brackets_the_first_delay_by_one_percent(coarse_report):
    first = st.first_destabilising_delay(PAPER_K, 2)
    v = coarse_report["first_destabilising_validation"]
    assert v["tau_below_s"] == pytest.approx(0.99 * first, rel=1e-12)
    assert v["tau_above_s"] == pytest.approx(1.01 * first, rel=1e-12)


def test_report_stable_fractions_count_the_grid(coarse_report):
    """Chart grid k in {0, 165}, tau in {4, 80} ms. Sampled: NumPy loop radii < 1. Continuous:
    at k = 0 the open loop's non-structural roots; at k = 165 the crossing count (stability switches)."""
    plant = make_plant(n_modes=2)
    dplant = discretize(plant, 0.004, "zoh")
    sampled = [_numpy_loop_radius(dplant, k, d) < 1 for k in (0.0, 3 * PAPER_K) for d in (1, 20)]
    lam = np.linalg.eigvals(np.asarray(plant.A))
    open_stable = bool(np.all(np.delete(lam, np.argmin(np.abs(lam))).real < 0))
    counts = st.unstable_root_count(st.critical_delays(plant, 3 * PAPER_K, 0.1), np.array([0.004, 0.08]))
    continuous = [open_stable, open_stable] + [bool(c == 0) for c in counts]
    assert np.mean(sampled) != np.mean(continuous)  # the two fractions can be told apart
    assert coarse_report["chart"]["stable_fraction_sampled"] == pytest.approx(np.mean(sampled), abs=1e-12)
    assert coarse_report["chart"]["stable_fraction_continuous"] == pytest.approx(np.mean(continuous), abs=1e-12)


def test_report_chart_rows_are_whole_samples_capped_at_80(tmp_path):
    """tau_max_s = 0.087 at dt = 1 ms is 87 samples (0.087 / 0.001 rounds to 86.999...): the
    chart tops out at 0.087 s, and its rows are capped at 80."""
    result = stability_report.run(tmp_path, tau_max_s=0.087, n_k=2, n_cheb=16)
    assert result["chart"]["n_tau"] == 80
    np.testing.assert_allclose(result["chart"]["tau_range_s"], [0.001, 0.087], rtol=1e-12)


def test_cli_reads_a_negative_number_in_exponent_form_as_a_value(tmp_path, capsys):
    """``--k -1e3`` stopped in argparse ("argument --k: expected one argument"): -1e3 was taken
    for an option. A negative gain is analysed (the loop is unstable); a negative frequency is
    refused by the command, by name."""
    from jaxflex import cli

    assert cli._parser().parse_args(["stability", "--k", "-1e3"]).k == -1000.0
    assert cli._parser().parse_args(["calibrate", "--freqs", "-1e1", "2.5E+2"]).freqs == [-10.0, 250.0]
    assert cli.main(["calibrate", "--freqs", "-1e1", "--out", str(tmp_path / "cal")]) == 2
    assert "freqs" in capsys.readouterr().err


@pytest.mark.parametrize("k, tau", [(55.0, 0.02), (120.0, 0.012), (30.0, 0.0053)])
def test_rightmost_root_gradient_matches_central_differences(plant, k, tau):
    """The rightmost root is differentiable in k and tau (traced through the generator's
    eigenvalues): forward-mode derivatives of its real and imaginary parts against central
    differences. The first two are complex pairs (one unstable), the last a real root; all are
    simple. n_cheb = 24 (converged to ~1e-9 here; one compilation). h = 1e-5 relative:
    truncation ~1e-10, round-off of the eigenvalues ~1e-14 / 1e-5, relative."""
    root = jax.jit(lambda kt: st.rightmost_root(plant, kt[0], kt[1], 24))
    x = jnp.asarray([k, tau])
    jac = jax.jit(jax.jacfwd(lambda kt: jnp.stack([jnp.real(root(kt)), jnp.imag(root(kt))])))(x)
    for i in range(2):
        h = 1e-5 * float(x[i])
        e = jnp.zeros(2).at[i].set(h)
        up, down = complex(root(x + e)), complex(root(x - e))
        fd = (up - down) / (2 * h)
        assert np.isfinite(float(jac[0, i])) and float(jac[0, i]) != 0.0
        np.testing.assert_allclose(float(jac[0, i]), fd.real, rtol=1e-6)
        np.testing.assert_allclose(float(jac[1, i]), fd.imag, rtol=1e-6, atol=1e-6 * abs(fd.real))



class _Validated(Exception):
    """Raised where stability_report.run starts its analysis: its options were accepted."""


@pytest.fixture
def validated_only(monkeypatch):
    def stop(*args, **kwargs):
        raise _Validated

    monkeypatch.setattr(stability_report, "make_plant", stop)


def test_a_chart_range_of_exactly_two_samples_is_accepted(tmp_path, validated_only):
    """tau_max_s must span 'at least 2 samples': 2 ms at 1 ms does."""
    with pytest.raises(_Validated):
        stability_report.run(tmp_path, tau_s=0.001, tau_max_s=0.002, dt=1e-3)


def test_the_default_gain_range_of_a_negative_gain_spans_it(tmp_path, validated_only, monkeypatch):
    """k = -10: the chart's gains run over [3 k, 0] = [-30, 0], as [0, 3 k] does for k > 0."""
    calls, real = [], np.linspace
    monkeypatch.setattr(stability_report.np, "linspace", lambda *a, **k: (calls.append(a[:2]), real(*a, **k))[1])
    with pytest.raises(_Validated):
        stability_report.run(tmp_path, k=-10.0, dt=1e-3)
    monkeypatch.undo()
    assert (-30.0, 0.0) in [tuple(float(v) for v in c) for c in calls]


def test_stability_json_replaces_the_earlier_one_after_the_chart(tmp_path, monkeypatch):
    """stability.json, the file a reader waits for, is moved into place last, whatever order
    the staging folder lists its files in."""
    import os

    from jaxflex import fileio

    renamed, real_replace, real_listdir = [], os.replace, os.listdir
    monkeypatch.setattr(fileio.os, "replace", lambda src, dst: (renamed.append(os.path.basename(dst)), real_replace(src, dst))[1])
    monkeypatch.setattr(fileio.os, "listdir", lambda p: sorted(real_listdir(p), key=lambda n: n != stability_report.JSON_FILE))  # the JSON listed first
    stability_report.run(tmp_path, k=20.0, n_k=2, tau_max_s=0.006, n_cheb=8)
    assert renamed[-1] == stability_report.JSON_FILE and stability_report.CHART_FILE in renamed
