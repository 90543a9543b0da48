"""Pade delay: coefficients against python-control, poles against exact rational arithmetic,
the realisation's transfer function, phase accuracy, exact sampling against scipy, and the
conditioning against python-control's companion realisation."""

from fractions import Fraction
import math

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import jaxflex as jf
from jaxflex import pade
from jaxflex.controllers import DFSParams, dfs

TAU = 0.005  # the paper's delay (s)
DT = 1e-3  # the paper's sample time (s)
RTOL_COEF = 1e-10  # the brief's bar; both sides are float64 roundings of the same integers
RTOL_POLE = 1e-14  # poles correct to float64 round-off (a few ulps of a Newton step)
RTOL_TF = 1e-11  # state-space solve vs polynomial evaluation with coefficients up to 1e15 (N = 12)
ATOL_GRAMIAN = 1e-12  # Lyapunov solves on matrices of norm <= 5.4 N, float64
RTOL_SAMPLED = 1e-12  # two float64 expm of the same block matrix


def _exact_newton_step(order, z):
    """|p(z) / p'(z)| / |z| for the exact integer denominator, in Fraction arithmetic: the
    relative distance from z to the nearest root, to first order (independent of pade.py)."""
    n = order
    a = [Fraction(math.factorial(2 * n - k), math.factorial(k) * math.factorial(n - k)) for k in range(n + 1)]
    zr, zi = Fraction(z.real), Fraction(z.imag)
    pr = pi_ = qr = qi = Fraction(0)
    for k in range(n, -1, -1):  # Horner for p and p' together
        qr, qi = qr * zr - qi * zi + pr, qr * zi + qi * zr + pi_
        pr, pi_ = pr * zr - pi_ * zi + a[k], pr * zi + pi_ * zr
    q2 = qr * qr + qi * qi
    ratio = complex(float((pr * qr + pi_ * qi) / q2), float((pi_ * qr - pr * qi) / q2))
    return abs(ratio) / abs(z)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6])
def test_coefficients_match_python_control(n):
    num, den = pade.pade_coefficients(n)
    num_c, den_c = (np.asarray(c, float) for c in control.pade(1.0, n))
    num_c, den_c = num_c / den_c[0], den_c / den_c[0]  # normalise: monic denominator
    np.testing.assert_allclose(den / den[0], den_c, rtol=RTOL_COEF)
    np.testing.assert_allclose(num / den[0], num_c, rtol=RTOL_COEF)
    assert den[0] == 1.0 and num[0] == (-1.0) ** n


def test_poles_known_values():
    """N = 1: D(s) = s + 2. N = 2: s^2 + 6 s + 12, poles 3 +- j sqrt(3). N = 3:
    s^3 + 12 s^2 + 60 s + 120, real root from Cardano's formula."""
    np.testing.assert_allclose(pade._poles(1), [2.0], rtol=RTOL_POLE)
    p2 = np.sort_complex(pade._poles(2))
    np.testing.assert_allclose(p2, [3 - 1j * np.sqrt(3), 3 + 1j * np.sqrt(3)], rtol=RTOL_POLE)
    # D(-p) = 0: p^3 - 12 p^2 + 60 p - 120 = 0; with p = y + 4 the depressed cubic
    # y^3 + 12 y - 8 = 0 has the real root y = cbrt(4 + sqrt(80)) + cbrt(4 - sqrt(80)).
    y = np.cbrt(4 + np.sqrt(80)) + np.cbrt(4 - np.sqrt(80))
    real3 = pade._poles(3)[0]
    np.testing.assert_allclose(real3, y + 4, rtol=RTOL_POLE)
    assert abs(np.imag(real3)) == 0.0


@pytest.mark.parametrize("n", [1, 4, 5, 7, 8, 12, 20, 30, 31])
def test_poles_are_exact_to_float64(n):
    poles = pade._poles(n)
    assert poles.shape == (n,) and np.all(poles.real > 0)  # stable: roots of D in the open LHP
    assert max(_exact_newton_step(n, complex(-p)) for p in poles) < RTOL_POLE
    assert np.sum(poles.imag == 0) == n % 2  # one real pole iff N odd, the rest in pairs


def test_companion_eigenvalues_lose_accuracy_at_high_order():
    """Why pade.py refines the roots: np.roots of the same polynomial is off by > 1e-8 at N = 20."""
    _, den = pade.pade_coefficients(20)
    assert max(_exact_newton_step(20, complex(r)) for r in np.roots(den)) > 1e-8


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 12])
def test_state_space_transfer_function_equals_num_over_den(n):
    ss = pade.pade_state_space(TAU, n)
    A, B, C, D = (np.asarray(m) for m in ss)
    assert A.shape == (n, n) and B.shape == (n, 1) and C.shape == (1, n) and D.shape == (1, 1)
    num, den = pade.pade_coefficients(n)
    for x in (0.3j, 2j, 1 + 1j, -0.5 + 3j, 10j, 4.0):  # s tau
        s = x / TAU
        h_ss = (C @ np.linalg.solve(s * np.eye(n) - A, B) + D)[0, 0]
        np.testing.assert_allclose(h_ss, np.polyval(num, x) / np.polyval(den, x), rtol=RTOL_TF)


@pytest.mark.parametrize("n", [1, 2, 7, 12, 20])
def test_realisation_is_balanced_and_all_pass(n):
    """Gramians equal to the identity (the conditioning argument) and |H(j w)| = 1."""
    A, B, C, D = (np.asarray(m) for m in pade.pade_state_space(1.0, n))
    P = scipy.linalg.solve_continuous_lyapunov(A, -B @ B.T)
    Q = scipy.linalg.solve_continuous_lyapunov(A.T, -C.T @ C)
    np.testing.assert_allclose(P, np.eye(n), atol=ATOL_GRAMIAN * n)
    np.testing.assert_allclose(Q, np.eye(n), atol=ATOL_GRAMIAN * n)
    for w in (1e-3, 1.0, 30.0, 1e3):
        h = (C @ np.linalg.solve(1j * w * np.eye(n) - A, B) + D)[0, 0]
        np.testing.assert_allclose(abs(h), 1.0, rtol=1e-13)


def _phase_error(n, w_tau):
    A, B, C, D = (np.asarray(m) for m in pade.pade_state_space(TAU, n))
    w = w_tau / TAU
    h = (C @ np.linalg.solve(1j * w * np.eye(n) - A, B) + D)[0, 0]
    return np.angle(h * np.exp(1j * w_tau))  # arg H(j w) + w tau


@pytest.mark.parametrize("n", [1, 2, 3])
def test_low_frequency_phase_error_is_the_pade_remainder(n):
    """Phase error (N!)^2 / ((2N)! (2N + 1)!) (w tau)^(2N + 1), positive (H lags a little
    less than the delay), up to relative O((w tau)^2) = 1e-2 at w tau = 0.1."""
    c = math.factorial(n) ** 2 / (math.factorial(2 * n) * math.factorial(2 * n + 1))
    np.testing.assert_allclose(_phase_error(n, 0.1), c * 0.1 ** (2 * n + 1), rtol=2e-2)


@pytest.mark.parametrize("n, w_tau_max", [(4, 4.2), (8, 10.5), (12, 17.4)])
def test_phase_stays_within_10_mrad_up_to_the_documented_band(n, w_tau_max):
    errors = [abs(_phase_error(n, x)) for x in np.linspace(0.01, w_tau_max, 400)]
    assert max(errors) < 1e-2
    assert abs(_phase_error(n, 1.1 * w_tau_max)) > 1e-2  # and the band is not much wider


N_SAMPLED = 7  # one order for the expm-based tests: jax's expm compiles once per matrix size


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_discretize_matches_scipy_cont2discrete(hold):
    n = N_SAMPLED
    ss = pade.pade_state_space(TAU, n)
    got = pade.discretize_pade(ss, DT, hold)
    Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete(tuple(np.asarray(m) for m in ss), DT, method=hold)
    for a, b in zip(got, (Ad, Bd, Cd, Dd)):
        np.testing.assert_allclose(np.asarray(a), b, rtol=RTOL_SAMPLED, atol=RTOL_SAMPLED)
    if hold == "foh":  # the default, as sampled_delay's and dfs's (it was "zoh", which does not converge to the delay)
        for a, b in zip(pade.discretize_pade(ss, DT), got):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # and the sampled poles are exactly exp(-p_i dt / tau)
    np.testing.assert_allclose(
        np.sort(np.abs(np.linalg.eigvals(np.asarray(got.Ad)))), np.sort(np.exp(-pade._poles(n).real * DT / TAU)), rtol=RTOL_SAMPLED
    )


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_sampled_delay_starts_in_steady_state(hold):
    """History before t = 0 equals u0: with the input held at u0 the output is u0 and the
    state does not move."""
    u0 = jnp.asarray([0.7])
    filt, xi = pade.sampled_delay(TAU, N_SAMPLED, DT, u0, hold)
    if hold == "foh":  # the documented default (every caller in jaxflex passes its hold)
        jax.tree.map(np.testing.assert_array_equal, pade.sampled_delay(TAU, N_SAMPLED, DT, u0), (filt, xi))
    for _ in range(20):
        np.testing.assert_allclose(np.asarray(filt.C @ xi + filt.D @ u0), [0.7], rtol=1e-13)
        xi_next = filt.Ad @ xi + filt.Bd @ u0
        np.testing.assert_allclose(np.asarray(xi_next), np.asarray(xi), rtol=1e-12, atol=1e-14)
        xi = xi_next
    if hold == "zoh":  # the brief's A xi = -B u0
        ss = pade.pade_state_space(TAU, N_SAMPLED)
        np.testing.assert_allclose(np.asarray(ss.A @ xi), np.asarray(-ss.B @ u0), atol=1e-10)


def _sampled_response_error(n, hold, freq_hz):
    """|H_d(e^{j w dt}) - z^-5|: the sampled filter against the exact 5-sample delay.

    Sampled with scipy (equal to ``discretize_pade``, tested above) to keep this sweep over
    orders free of one expm compilation per order."""
    ss = tuple(np.asarray(m) for m in pade.pade_state_space(TAU, n))
    Ad, Bd, C, D, _ = scipy.signal.cont2discrete(ss, DT, method=hold)
    z = np.exp(2j * np.pi * freq_hz * DT)
    return abs((C @ np.linalg.solve(z * np.eye(n) - Ad, Bd) + D)[0, 0] - z**-5)


def test_sampled_filter_converges_with_foh_but_not_with_zoh():
    """At the first mode (~14 Hz): with "foh" the error falls with N to a plateau of ~1e-3
    (the interpolant's images at w tau = 31 need N > 16); with "zoh" the feedthrough of
    each held jump keeps it at several percent whatever N."""
    foh = {n: _sampled_response_error(n, "foh", 14.0) for n in (1, 2, 4, 8, 12, 20, 40)}
    zoh = {n: _sampled_response_error(n, "zoh", 14.0) for n in (1, 2, 4, 8, 12, 20, 40)}
    assert foh[1] > 10 * foh[2]
    assert max(foh[n] for n in (4, 8, 12)) < 1e-3 and foh[40] < 0.5 * foh[12]
    assert min(zoh.values()) > 2e-2


def test_python_control_companion_realisation_is_badly_conditioned():
    """control.tf2ss(control.pade(5 ms, N)): an accurate transfer function in float64, but a
    companion A with entries ~1e27, which JAX's expm (16 squarings at most) turns into NaN at
    N = 8 (from N = 3 on). The cascade has cond(A) < 1e3 and exactly sampled poles
    (test_discretize_matches_scipy_cont2discrete).

    scipy's expm is not asserted on: scipy 1.17 samples the N = 8 companion form with 3e-5
    relative error in the poles, while scipy 1.18 (on the H100 machine) gets it to 3e-14. A test
    of another library's accuracy would fail when that library improves."""
    for n in (8, 12):
        sys = control.tf2ss(control.tf(*control.pade(TAU, n)))
        A, B, C, D = (np.asarray(m, float) for m in (sys.A, sys.B, sys.C, sys.D))
        ours = pade.pade_state_space(TAU, n)
        assert np.linalg.cond(A) > 1e20 and np.linalg.cond(np.asarray(ours.A)) < 1e3
        if n == 8:  # the expm compiles once per size; this size only
            block = np.zeros((n + 1, n + 1))
            block[:n, :n], block[:n, n:] = A * DT, B * DT
            assert not np.all(np.isfinite(np.asarray(jax.scipy.linalg.expm(jnp.asarray(block)))))
            for w in (10.0, 1e3):  # the continuous transfer function itself is fine in float64
                h_c = (C @ np.linalg.solve(1j * w * np.eye(n) - A, B) + D)[0, 0]
                h_o = (np.asarray(ours.C) @ np.linalg.solve(1j * w * np.eye(n) - np.asarray(ours.A), np.asarray(ours.B)) + np.asarray(ours.D))[0, 0]
                np.testing.assert_allclose(h_c, h_o, rtol=1e-12)


def test_bad_arguments():
    for bad in (0, -1, 2.0, True, None, 101, 1000):
        with pytest.raises(ValueError, match="^order must be an integer in \\[1, 100\\]"):
            pade.pade_state_space(TAU, bad)
    with pytest.raises(ValueError, match="hold must be one of"):
        pade.discretize_pade(pade.pade_state_space(TAU, 2), DT, "cubic")
    with pytest.raises(ValueError, match="dt must be"):
        pade.discretize_pade(pade.pade_state_space(TAU, 2), 0.0)
    with pytest.raises(ValueError, match="tau_s must be a scalar"):
        pade.pade_state_space(jnp.ones(2), 2)
    # named, where they failed inside JAX or with an AttributeError
    with pytest.raises(ValueError, match="tau_s must be a real number; got '0.005'"):
        pade.pade_state_space("0.005", 2)
    with pytest.raises(ValueError, match=r"ss must be a PadeSS \(build one with pade_state_space\(tau_s, order\)\); got dict"):
        pade.discretize_pade({"A": 1.0}, DT)
    for u0 in (jnp.zeros(3), jnp.zeros(()), jnp.zeros((2, 4))):
        with pytest.raises(ValueError, match=r"u0 must have shape \(1,\), or \(1, B\) for a batch"):
            pade.sampled_delay(TAU, 2, DT, u0)
    assert pade.sampled_delay(TAU, 2, DT, jnp.zeros((1, 4)))[1].shape == (2, 4)


def test_delays_far_below_the_sample_time_stay_finite_and_bad_delays_are_refused():
    """tau = 1e-7 s at N = 8 needs more than expm's default 16 squarings (NaN before); the
    loop then behaves as with no delay at all, which is what such a delay is."""
    plant = jf.discretize(jf.make_plant(jf.BeamParams(), 2), DT, "rk4")
    scenario = jf.paper_scenario(plant, 0.3)
    buffered = jf.rollout(plant, dfs(DT, interpolation="linear"), DFSParams(55.0, 1e-7), scenario, output="metrics")
    for order in (4, 8):
        m = jf.rollout(plant, dfs(DT, approximation="pade", pade_order=order), DFSParams(55.0, 1e-7), scenario, output="metrics")
        assert np.isfinite(float(m.tip_ise)) and not bool(m.diverged)
        np.testing.assert_allclose(float(m.tip_ise), float(buffered.tip_ise), rtol=1e-9)
    for bad in (0.0, -0.005, float("nan")):
        with pytest.raises(ValueError, match="tau_s must be a finite delay > 0"):
            pade.pade_state_space(bad, 4)


def test_sampled_frequency_response_gradient_in_tau_against_python_control():
    """d/dtau of the zoh-sampled filter's frequency response ``C (zI - Ad)^-1 Bd + D`` at
    ``z = e^{j w dt}`` (coordinate-free, so comparable across realisations) against central
    differences of python-control's own Pade approximant (``control.pade``, companion form,
    well conditioned at N = 3) sampled by scipy's ``cont2discrete``: an oracle independent of
    pade.py. h = 1e-4 tau: truncation ~1e-8, round-off ~1e-12 relative, well below 1e-6.
    ("foh" is checked in tau through the closed loop, tests/test_dfs_delay.py; "zoh" was not.
    One hold: the expm's forward-mode program takes seconds to compile.)"""
    order, tau, hold = 3, 0.0053, "zoh"
    ws = np.array([20.0, 90.0, 300.0, 1200.0])  # rad/s: w tau from 0.1 to 6.4
    z = np.exp(1j * ws * DT)[:, None, None]

    def response(filt, xp):
        Ad, Bd, C, D = filt
        stack = lambda m: xp.broadcast_to(m[None], (z.shape[0],) + m.shape)  # noqa: E731  (no rank promotion)
        h = (stack(C) @ xp.linalg.solve(z * stack(xp.eye(Ad.shape[0])) - stack(Ad), stack(Bd)) + stack(D))[:, 0, 0]
        return xp.concatenate([xp.real(h), xp.imag(h)])

    def ours(t):
        return response(pade.discretize_pade(pade.pade_state_space(t, order), DT, hold), jnp)

    def reference(t):
        sys = control.tf2ss(*control.pade(t, order))
        Ad, Bd, C, D, _ = scipy.signal.cont2discrete((sys.A, sys.B, sys.C, sys.D), DT, method=hold)
        return response((Ad, Bd, C, D), np)

    value_and_derivative = jax.jit(lambda t: jax.jvp(ours, (t,), (jnp.ones_like(t),)))  # one compilation
    value, grad = (np.asarray(a) for a in value_and_derivative(jnp.asarray(tau)))
    np.testing.assert_allclose(value, reference(tau), rtol=1e-9, atol=1e-12)
    h = 1e-4 * tau
    fd = (reference(tau + h) - reference(tau - h)) / (2 * h)
    assert np.all(np.isfinite(grad)) and np.max(np.abs(grad)) > 1.0
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * np.max(np.abs(fd)))
