"""Tests of jaxflex.analysis.metrics against analytic signals and NumPy references."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.analysis import (
    SignalMetrics,
    control_effort,
    diverged,
    iae,
    ise,
    peaks,
    run_diverged,
    samples_at,
    settling_time,
    signal_metrics,
)

DT = 1e-3  # s
# Sums of ~1e3 f64 terms, computed in a different order than NumPy.
RTOL_SUM = 1e-12
# The final value s_f is the mean of the last 10 % of a record that has decayed by e^-18 or more,
# so it differs from the true offset by < 2e-8 of the amplitude; this moves the band crossing by
# far less than a sample unless it falls within ~1e-6 s of a sample instant (not the case below).
TOL_CROSSING = 1e-9  # s


def _settling_reference(s, dt, band=0.02, final_fraction=0.1):
    """Plain-Python reading of the documented definition, scanning back from the end."""
    s = np.asarray(s, np.float64)
    n_final = max(1, int(round(final_fraction * len(s))))
    s_f = np.mean(s[-n_final:])
    dev = np.abs(s - s_f)
    thr = band * dev.max()
    if dev[-1] > thr:
        return math.inf
    k = len(s) - 1
    while k >= 0 and dev[k] <= thr:
        k -= 1
    return (k + 1) * dt


@pytest.mark.parametrize("offset,amp", [(0.0, 1.0), (0.35, -0.02), (-5.0, 2.0)])
def test_settling_time_exponential_about_offset(offset, amp):
    # s = c + A exp(-t / T0): |s - c| <= band |A| from t = T0 ln(1/band) on, so the settling time is
    # the first sample at or after that instant.
    t0 = 0.05
    t = np.arange(2000) * DT  # 2 s = 40 T0
    s = offset + amp * np.exp(-t / t0)
    for band in (0.02, 0.05):
        t_cross = t0 * math.log(1.0 / band)
        expected = math.ceil(t_cross / DT - 1e-9) * DT
        got = float(settling_time(s, DT, band=band))
        assert abs(got - expected) < TOL_CROSSING, (got, expected)
        assert t_cross - TOL_CROSSING <= got < t_cross + DT
        assert got == pytest.approx(_settling_reference(s, DT, band=band), abs=1e-15)


def test_settling_time_damped_cosine_about_offset():
    # s = c + A e^{-a t} cos(w t): the envelope reaches band*A at T_env = ln(1/band)/a; the last
    # excursion outside the band is within half a period before T_env.
    a, w, c, amp = 6.0, 2 * np.pi * 16.0, 0.01, 0.03
    t = np.arange(3000) * DT
    s = c + amp * np.exp(-a * t) * np.cos(w * t)
    got = float(settling_time(s, DT))
    t_env = math.log(1 / 0.02) / a
    assert t_env - np.pi / w <= got <= t_env + DT
    assert got == pytest.approx(_settling_reference(s, DT), abs=1e-15)
    # Measuring the band from 0 instead of the final value would settle far earlier: guard it.
    got_shifted = float(settling_time(s + 1.0, DT))
    assert got_shifted == pytest.approx(got, abs=1e-15)


def test_settling_time_never_settles_and_always_inside():
    t = np.arange(1000) * DT
    growing = np.exp(t)  # last sample is the peak deviation
    assert math.isinf(float(settling_time(growing, DT)))
    tone = np.sin(2 * np.pi * 5.0 * t + 1.0)  # undamped; last sample far outside 2 %
    assert math.isinf(float(settling_time(tone, DT)))
    assert float(settling_time(np.full(1000, 0.7), DT)) == 0.0
    assert float(settling_time(tone, DT, band=1.0)) == 0.0  # the band covers the peak deviation
    impulse = np.zeros(1000)
    impulse[0] = 1.0
    assert float(settling_time(impulse, DT)) == DT  # only sample 0 is outside
    # a diverged record has no settling time (it read 0 for an all-NaN signal)
    for bad in (np.nan, np.inf):
        assert math.isnan(float(settling_time(np.full(1000, bad), DT)))
        assert math.isnan(float(settling_time(np.where(t > 0.5, bad, tone), DT)))
    both = np.asarray(settling_time(np.stack([impulse, np.full(1000, np.nan)], axis=1), DT))
    assert both[0] == DT and math.isnan(both[1])


def test_settling_time_columns_and_validation():
    t = np.arange(1500) * DT
    s = np.stack([0.2 + np.exp(-t / 0.03), np.sin(40 * t), np.full_like(t, 3.0)], axis=1)  # [T, 3]
    got = np.asarray(settling_time(s, DT))
    assert got.shape == (3,)
    for j in range(3):
        assert got[j] == pytest.approx(_settling_reference(s[:, j], DT), abs=1e-15) or (
            math.isinf(got[j]) and math.isinf(_settling_reference(s[:, j], DT))
        )
    with pytest.raises(ValueError, match="final_fraction"):
        settling_time(s, DT, final_fraction=0.0)
    with pytest.raises(ValueError, match=r"final_fraction must be a static Python float in \(0, 1\]; got True"):
        settling_time(s, DT, final_fraction=True)  # taken as 1
    with pytest.raises(ValueError, match="band must be a real number; got '0.02'"):
        settling_time(s, DT, band="0.02")  # taken as 0.02
    with pytest.raises(ValueError, match="band must be finite and > 0; got nan"):
        settling_time(s, DT, band=float("nan"))
    with pytest.raises(ValueError, match="dt must be finite and > 0"):
        settling_time(s, -DT)
    for bad in ("1e-3", None, True):  # a string or a bool is not a sample time, though float() takes it
        with pytest.raises(ValueError, match=r"dt must be a real number; got"):
            settling_time(s, bad)
        with pytest.raises(ValueError, match=r"dt must be a real number; got"):
            ise(s, bad)
    with pytest.raises(ValueError, match="band"):
        settling_time(s, DT, band=0.0)


def test_peaks_ise_iae_effort_against_numpy():
    rng = np.random.default_rng(0)
    s = rng.standard_normal((800, 2))
    lo, hi = peaks(s)
    np.testing.assert_array_equal(lo, s.min(axis=0))
    np.testing.assert_array_equal(hi, s.max(axis=0))
    np.testing.assert_allclose(ise(s, DT), np.sum(s**2, axis=0) * DT, rtol=RTOL_SUM)
    np.testing.assert_allclose(iae(s, DT), np.sum(np.abs(s), axis=0) * DT, rtol=RTOL_SUM)
    np.testing.assert_allclose(control_effort(s[:, 0], DT), np.sum(s[:, 0] ** 2) * DT, rtol=RTOL_SUM)
    # Analytic: ISE of a constant c over T samples is c^2 T dt.
    np.testing.assert_allclose(ise(np.full(500, 0.3), 0.01), 0.09 * 5.0, rtol=RTOL_SUM)
    m = signal_metrics(s[:, 1], DT)
    assert isinstance(m, SignalMetrics)
    np.testing.assert_allclose(m.iae, np.sum(np.abs(s[:, 1])) * DT, rtol=RTOL_SUM)
    assert float(m.min) == s[:, 1].min() and float(m.max) == s[:, 1].max()


def test_diverged():
    x = np.zeros((50, 3))
    assert not bool(diverged(x))
    for bad in (np.nan, np.inf, -np.inf, 2e6, -2e6):
        y = x.copy()
        y[17, 1] = bad
        assert bool(diverged(y)), bad
    y = x.copy()
    y[3, 0] = 5.0
    assert bool(diverged(y, threshold=4.0)) and not bool(diverged(y, threshold=5.0))
    assert bool(jax.jit(diverged)(jnp.array([0.0, jnp.nan])))
    assert not bool(diverged(y, threshold=np.inf)) and bool(jax.jit(diverged)(y, 4.0))  # traced: not checked
    for bad in (-1.0, 0.0, np.nan, "1e6", [1.0, 2.0]):  # a bound <= 0 called every run diverged
        with pytest.raises(ValueError, match="threshold must be a (real )?number"):
            diverged(x, threshold=bad)
    for bad in ("abc", [True, False]):  # JAX's TypeError for the string, named nothing
        with pytest.raises(ValueError, match="x must be a real number or an array of real numbers"):
            diverged(bad)


def test_run_diverged_counts_a_tip_beyond_the_arm():
    # blown up, beyond the 0.9 m arm, at its length (not beyond), and neither; batched and traced
    blew_up = np.array([True, False, False, False])
    peak = np.array([1e-3, 2.0, 0.9, 0.5])
    np.testing.assert_array_equal(run_diverged(blew_up, peak, 0.9), [True, True, False, False])
    np.testing.assert_array_equal(jax.jit(run_diverged)(blew_up, peak, 0.9), [True, True, False, False])
    assert bool(run_diverged(True, np.nan, 0.9)) and not bool(run_diverged(False, np.nan, 0.9))  # NaN counts through blew_up
    for bad, shown in ((0.0, "0.0"), (-0.9, "-0.9"), (np.nan, "nan"), (np.inf, "inf")):
        with pytest.raises(ValueError, match=rf"^length_m must be finite and > 0 \(m\); got {shown}$"):
            run_diverged(blew_up, peak, bad)
    with pytest.raises(ValueError, match=r"^length_m must be a scalar \(m\); got shape \(2,\)$"):
        run_diverged(blew_up, peak, [0.9, 1.0])


def test_reproduce_run_metrics_use_the_same_rule():
    """reproduce's results.json and montecarlo's summary.json call the same runs diverged: a
    tip grown to 2 m on the paper's 0.9 m arm (to either side), every state below 1e6."""
    from types import SimpleNamespace

    from jaxflex.report import _run_metrics

    t = np.arange(3000) * DT  # the paper's 3 s horizon, which holds results.json's sample times
    grow = np.exp(3 * (t - t[-1]))
    tips = [2.0 * grow * np.sin(2 * np.pi * 13 * t), 0.5 * grow * np.sin(2 * np.pi * 13 * t),
            -2.0 * grow * np.abs(np.sin(2 * np.pi * 13 * t)),  # on one side only: its max is 0, its |tip| 2 m
            2.0 * grow * np.abs(np.sin(2 * np.pi * 13 * t))]
    for tip in tips:
        expected = bool(np.max(np.abs(tip)) > 0.9)
        x = np.stack([0 * t, tip / 2, 0 * t, 0 * t], axis=1)  # q1 = tip / 2: no state near 1e6
        traj = SimpleNamespace(x=jnp.asarray(x), z=jnp.stack([jnp.zeros(t.size), jnp.asarray(tip)], axis=1), u=jnp.zeros((t.size, 1)))
        assert _run_metrics(traj, DT)["diverged"] is expected


def test_samples_at():
    s = np.arange(101.0) * 2.0  # s[k] = 2k at t = k dt
    dt = 0.01
    np.testing.assert_array_equal(samples_at(s, dt, (0.0, 0.25, 0.3, 0.504, 0.506, 1.0)), [0, 50, 60, 100, 102, 200])
    s2 = np.stack([s, -s], axis=1)
    np.testing.assert_array_equal(samples_at(s2, dt, (0.1,)), [[20.0, -20.0]])
    within = r"times_s must lie in the record \[0, 1\] s to within half a sample, \[-0.005, 1.005\) s"
    np.testing.assert_array_equal(samples_at(s, dt, (-0.0049, 1.0049)), [0, 200])
    with pytest.raises(ValueError, match=within + r" .*got \[1.0051\]"):
        samples_at(s, dt, (1.0051,))
    with pytest.raises(ValueError, match=within + r" .*got \[-0.0051\]"):
        samples_at(s, dt, (-0.0051,))
    for bad in ("0.5", ["0.5"], [True]):  # a string was read character by character
        with pytest.raises(ValueError, match=r"times_s must be a static sequence of floats \(s\)"):
            samples_at(s, dt, bad)
    # Traced dt: same values, NaN (not an error) outside the record.
    got = jax.jit(lambda s, dt: samples_at(s, dt, (0.25, 2.0)))(s, dt)
    np.testing.assert_array_equal(got[:1], [50.0])
    assert np.isnan(got[1])
    # the traced bounds are the concrete ones, half a sample beyond each end
    got = np.asarray(jax.jit(lambda s, dt: samples_at(s, dt, (1.0049, 1.0051, -0.0049, -0.0051)))(s, dt))
    np.testing.assert_array_equal(got[[0, 2]], [200.0, 0.0])
    assert np.isnan(got[1]) and np.isnan(got[3])


def test_float32_preserved():
    t = np.arange(1000, dtype=np.float32) * np.float32(DT)
    s = jnp.asarray(0.1 + np.exp(-t / 0.05), jnp.float32)
    m = signal_metrics(s, jnp.float64(DT))  # a float64 dt must not promote the results
    for leaf in m:
        assert leaf.dtype == jnp.float32
    assert samples_at(s, DT, (0.1,)).dtype == jnp.float32
    assert control_effort(s, DT).dtype == jnp.float32
    # Same settling time as f64 up to one sample (f32 roundoff near the crossing).
    assert abs(float(m.settling_time_s) - 0.05 * math.log(50)) < DT + 1e-6


def test_vmap_and_jit_equal_loop():
    t = np.arange(1200) * DT
    taus = np.array([0.02, 0.05, 0.1, 0.15])
    batch = jnp.asarray(0.3 + np.exp(-t[None, :] / taus[:, None]) * np.cos(30 * t[None, :]))  # [B, T]
    fn = lambda s: signal_metrics(s, DT)
    batched = jax.jit(jax.vmap(fn))(batch)
    for b in range(batch.shape[0]):
        single = fn(batch[b])
        for got, want in zip(batched, single):
            np.testing.assert_allclose(got[b], want, rtol=RTOL_SUM)
    np.testing.assert_array_equal(jax.vmap(diverged)(batch.at[2, 5].set(jnp.nan)), [False, False, True, False])


@pytest.mark.parametrize(
    "s, dt, kwargs, expected",
    [
        # the final value is the mean of the last round(0.2 * 10) = 2 samples, 8.5: the band of
        # 0.5 * 8.5 holds 5..9, and sample 4 (4.5 off) is the last outside
        (np.arange(10.0), 1.0, dict(band=0.5, final_fraction=0.2), 5.0),
        # round(0.1 * 15) = 2 samples (not 1): s_f = 0.5, and the last sample is 0.5 off, as
        # far as any (with one sample, s_f = 1 and the run would settle at 14 s)
        (np.concatenate([np.zeros(14), [1.0]]), 1.0, dict(final_fraction=0.1), math.inf),
        # the last sample itself outside the band: not settled
        (np.concatenate([[100.0], np.zeros(94), [0.0, 0.0, -5.0, 0.0, 5.0]]), 1e-3, dict(final_fraction=0.03), math.inf),
    ],
)
def test_settling_time_final_window_and_last_sample(s, dt, kwargs, expected):
    assert float(settling_time(s, dt, **kwargs)) == expected
    assert _settling_reference(s, dt, **kwargs) == expected


def test_samples_at_rounds_half_up():
    """The documented index is floor(t / dt + 0.5): exact halves go up (NumPy's round would
    send 0.5 and 2.5 down, to the even index)."""
    s = np.arange(10.0) * 3.0
    np.testing.assert_array_equal(samples_at(s, 1.0, (0.5, 1.5, 2.5, 8.5)), [3.0, 6.0, 9.0, 27.0])
    np.testing.assert_array_equal(jax.jit(lambda s, dt: samples_at(s, dt, (0.5, 2.5)))(s, 1.0), [3.0, 9.0])


def test_signal_metrics_passes_band_and_final_fraction_to_the_settling_time():
    s = np.arange(10.0)
    for kwargs in (dict(band=0.5, final_fraction=1.0), dict(band=0.5, final_fraction=0.1), dict(band=0.3, final_fraction=0.2)):
        expected = _settling_reference(s, 1.0, **kwargs)
        assert float(signal_metrics(s, 1.0, **kwargs).settling_time_s) == expected
    assert _settling_reference(s, 1.0, band=0.5, final_fraction=1.0) == math.inf  # s_f = 4.5: the last sample is outside


def test_a_signal_that_is_not_numbers_is_refused_by_name():
    """A string (or a bool array) went into jnp.asarray and failed with JAX's TypeError
    ('is not a valid JAX array type'), which names no parameter."""
    from jaxflex.analysis import signal_metrics, welch

    for f in (lambda s: signal_metrics(s, 1e-3), lambda s: settling_time(s, 1e-3), lambda s: ise(s, 1e-3)):
        with pytest.raises(ValueError, match=r"s must be a real number or an array of real numbers; got 'abc'"):
            f("abc")
    with pytest.raises(ValueError, match=r"x must be a real number or an array of real numbers; got 'abc'"):
        welch("abc", 1000.0)
    with pytest.raises(ValueError, match=r"x must be a real number or an array of real numbers"):
        welch(np.ones(300, bool), 1000.0)
    np.testing.assert_allclose(ise([1, 2], 1e-3), 5e-3)  # integers are numbers
    # read in JAX's default float (float64 here): 2**24 + 1 has no float32
    big = np.array([16777217, 3, -5], np.int64)
    assert iae(big, 1.0).dtype == jnp.result_type(float) == jnp.float64
    assert float(iae(big, 1.0)) == 16777217 + 3 + 5


def test_an_empty_record_is_refused_by_name():
    """A record of no samples has no peak, final value or settling time: each metric refuses
    it by name (the integrals read 0 and the peaks failed in JAX's reduction)."""
    match = r"s must have shape \[T\] or \[T, n\] with T >= 1 \(time first\); got shape \(0,?( 2)?\)"
    for empty in (np.zeros(0), np.zeros((0, 2))):
        for f in (peaks, lambda s: ise(s, DT), lambda s: iae(s, DT), lambda s: control_effort(s, DT), lambda s: settling_time(s, DT), lambda s: signal_metrics(s, DT), lambda s: samples_at(s, DT, (0.0,))):
            with pytest.raises(ValueError, match=match):
                f(empty)


def test_a_traced_dt_must_be_a_scalar():
    """Under jit dt is not checked for its value, but its shape is: a [n] dt against a [T, n]
    signal broadcast into per-column sample times (the integrals came out scaled column by
    column, with no error)."""
    s = np.ones((10, 2))
    dts = jnp.array([1e-3, 2e-3])
    for f in (ise, iae, control_effort, settling_time, lambda s, dt: samples_at(s, dt, (0.0,))):
        with pytest.raises(ValueError, match=r"dt must be a scalar \(s\); got shape \(2,\)"):
            jax.jit(f)(s, dts)
    np.testing.assert_allclose(jax.jit(ise)(s, jnp.asarray(1e-3)), [10e-3, 10e-3], rtol=RTOL_SUM)  # a traced scalar runs
