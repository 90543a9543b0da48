"""Tests of jaxflex.analysis.psd: Welch PSD against scipy.signal.welch, and the dB reduction."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

from jaxflex.analysis import PSDSettings, band_mask, band_peak, get_window, region_reduction_db, vibration_reduction_db, welch

# Same algorithm as scipy in float64 (detrend, window, FFT, scaling); observed worst relative
# error is ~1e-13, so 1e-6 leaves room for other FFT backends while catching any formula slip
# (a wrong window coefficient, scale or one-sided factor is an O(1e-2..1) error).
RTOL_SCIPY = 1e-6
# Bins where the true PSD is ~0 (e.g. DC after detrending) hold pure roundoff on both sides, so
# relative error is meaningless there: allow an absolute floor of 1e-12 of the spectrum's max
# (f64 roundoff of sums of ~1e3 terms is ~1e-13 relative to the largest term).
ATOL_FLOOR_REL = 1e-12
# dB values from synthetic PSDs are exact up to f64 roundoff in a ratio and log10.
ATOL_DB = 1e-9
# jit/vmap vs eager: same f64 operations, possibly fused differently.
RTOL_TRANSFORM = 1e-12

FS = 200.0  # Hz


def _signal(seed, shape):
    """Noise plus a slow ramp plus an offset, so 'constant' and 'linear' detrending differ.

    The noise comes from NumPy's seeded generator: these are fixed test inputs, and each
    jax.random.normal shape would cost an XLA compilation (~0.4 s).
    """
    t = np.arange(shape[0]).reshape((shape[0],) + (1,) * (len(shape) - 1)) / FS  # time first
    return np.random.default_rng(seed).standard_normal(shape) + 0.7 + 3.0 * t


def _assert_matches_scipy(x, **kw):
    f, p = welch(x, FS, **kw)
    f_ref, p_ref = scipy.signal.welch(
        x, FS, scaling="density", return_onesided=True, average="mean", axis=0, **kw
    )
    assert f.shape == f_ref.shape and p.shape == p_ref.shape
    np.testing.assert_allclose(f, f_ref, rtol=RTOL_SCIPY, atol=0)
    np.testing.assert_allclose(p, p_ref, rtol=RTOL_SCIPY, atol=ATOL_FLOOR_REL * np.max(p_ref))
    return f, p


@pytest.mark.parametrize("window", ["hann", "hamming", "blackman", "boxcar"])
def test_window_matches_scipy(window):
    for n in (1, 8, 63):
        np.testing.assert_allclose(
            get_window(window, n, jnp.float64), scipy.signal.get_window(window, n), rtol=1e-12, atol=1e-15
        )


@pytest.mark.parametrize(
    "nperseg,noverlap,window,detrend",
    [
        # Every window with every detrend option, at least once; odd and even nperseg.
        (63, None, "hann", None),  # odd (no Nyquist bin), default half overlap, leftover dropped
        (63, None, "hamming", "constant"),
        (63, None, "blackman", "linear"),
        (63, None, "boxcar", None),
        (256, None, "hann", "constant"),  # scipy's defaults
        (64, 0, "hamming", "linear"),  # no overlap
        (65, 64, "blackman", False),  # maximal overlap, odd
        (101, 17, "boxcar", "linear"),  # odd, small overlap, leftover samples dropped
        (8, 4, "hann", "linear"),  # short segments
        (128, 32, "blackman", "constant"),
        (50, 10, "boxcar", "constant"),
        (1000, 0, "hann", "constant"),  # one segment spanning the whole record
    ],
)
def test_welch_matches_scipy(nperseg, noverlap, window, detrend):
    x = _signal(0, (1000,))
    _assert_matches_scipy(x, window=window, nperseg=nperseg, noverlap=noverlap, detrend=detrend)


@pytest.mark.parametrize("detrend", ["constant", "linear", None])
def test_welch_columns_match_scipy(detrend):
    x = _signal(1, (777, 3))
    _, p = _assert_matches_scipy(x, window="hann", nperseg=128, noverlap=96, detrend=detrend)
    assert p.shape == (65, 3)
    # Column j of a [T, n] input is the PSD of that column alone.
    if detrend == "linear":  # one configuration suffices (each adds a compilation)
        for j in range(3):
            _, pj = welch(x[:, j], FS, window="hann", nperseg=128, noverlap=96, detrend=detrend)
            np.testing.assert_allclose(p[:, j], pj, rtol=RTOL_TRANSFORM)


def test_welch_whole_record_and_settings():
    x = _signal(2, (300,))
    s = PSDSettings(window="hamming", nperseg=75, noverlap=None, detrend="linear")
    f, p = welch(x, FS, settings=s)
    f2, p2 = welch(x, FS, window="hamming", nperseg=75, detrend="linear")
    np.testing.assert_array_equal(p, p2)
    d = s.to_dict()
    assert d["noverlap"] == 37 and d["window"] == "hamming" and d["nperseg"] == 75
    assert d["detrend"] == "linear" and d["scaling"] == "density"
    assert PSDSettings(detrend=False).to_dict()["detrend"] is None
    with pytest.raises(ValueError, match="not both"):
        welch(x, FS, nperseg=64, settings=s)
    with pytest.raises(ValueError, match=r"settings must be a PSDSettings .*; got dict"):
        welch(x, FS, settings={"nperseg": 128})  # failed unpacking the dict's keys
    for dtype, shown in ((jnp.int32, "int32"), ("foo", "'foo'")):  # an int32 window was a float one
        with pytest.raises(ValueError, match=rf"dtype must be a floating dtype \(jnp.float32, jnp.float64\); got {shown}"):
            get_window("hann", 8, dtype)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"window": "kaiser"}, r"window must be one of \('hann', 'hamming', 'blackman', 'boxcar'\); got 'kaiser'"),
        ({"nperseg": 0}, r"nperseg must be an integer >= 1; got 0"),
        ({"nperseg": "256"}, r"nperseg must be an integer >= 1; got '256'"),
        ({"nperseg": 8, "noverlap": 8}, r"noverlap \(None, or below nperseg = 8\) must be an integer in \[0, 7\]; got 8"),
        ({"noverlap": -1}, r"noverlap \(None, or below nperseg = 256\) must be an integer in \[0, 255\]; got -1"),
        ({"detrend": "quadratic"}, r"detrend must be one of 'constant', 'linear', None or False; got 'quadratic'"),
        ({"detrend": 0}, r"detrend must be one of 'constant', 'linear', None or False; got 0"),
    ],
)
def test_psd_settings_refuse_bad_fields_when_built(kwargs, match):
    """PSDSettings kept any value, to fail in welch or be reported as is by to_dict."""
    with pytest.raises(ValueError, match=match):
        PSDSettings(**kwargs)


def test_psd_settings_store_numpy_integers_as_ints():
    s = PSDSettings(nperseg=np.int64(64), noverlap=np.int32(16))
    assert type(s.nperseg) is int and type(s.noverlap) is int and s == PSDSettings(nperseg=64, noverlap=16)
    assert hash(s) == hash(PSDSettings(nperseg=64, noverlap=16))


def test_sinusoid_plus_noise_matches_scipy_and_peaks_at_tone():
    f_tone = 37.5  # Hz; bin 48 of nperseg = 256 at FS = 200
    t = np.arange(4000) / FS
    noise = 0.3 * np.random.default_rng(3).standard_normal(t.shape)
    x = 0.02 * np.sin(2 * np.pi * f_tone * t + 0.3) + 0.001 * noise
    f, p = _assert_matches_scipy(x, window="hann", nperseg=256, noverlap=128, detrend="constant")
    assert int(jnp.argmax(p)) == 48 and float(f[48]) == f_tone


@pytest.mark.parametrize("window", ["hann", "boxcar"])
def test_pure_sinusoid_peak_bin_and_power(window):
    # On a bin centre with boxcar, the density PSD peak is A^2/2 * nperseg / fs (all power in one bin).
    nperseg, k = 128, 19
    f_tone = k * FS / nperseg
    t = np.arange(1024) / FS
    a = 1.5
    f, p = welch(a * np.cos(2 * np.pi * f_tone * t), FS, window=window, nperseg=nperseg)
    assert int(jnp.argmax(p)) == k
    if window == "boxcar":
        np.testing.assert_allclose(p[k], a**2 / 2 * nperseg / FS, rtol=1e-10)
    # Parseval for the density scaling: integral of the PSD equals the mean power A^2/2 (hann:
    # the tone spreads over 3 bins, the sum still holds).
    np.testing.assert_allclose(jnp.sum(p) * (FS / nperseg), a**2 / 2, rtol=1e-10)


def test_vibration_reduction_db_exact_values():
    freqs = np.arange(0.0, 101.0)  # 1 Hz bins
    psd_open = np.full((101,), 1e-6)
    # Mode 1 near 16 Hz: open-loop peak at 17 Hz (inside +-15 %), a bigger bump at 25 Hz outside.
    psd_open[[16, 17, 25]] = [2.0, 4.0, 100.0]
    # Mode 2 near 55 Hz: peak at 50 Hz (inside 55 +- 8.25 Hz).
    psd_open[50] = 3.0
    psd_closed = psd_open / 10.0
    psd_closed[17] = 4.0 / 10**3  # 30 dB at the open-loop peak bin
    psd_closed[16] = 2.0 / 10**9  # closed loop much lower at 16 Hz: must NOT be used
    psd_closed[50] = 3.0 * 10**0.5  # closed loop louder: -5 dB
    psd_closed[14] = 1.0  # the closed loop's own peak in the band: the bin is the OPEN loop's
    db = vibration_reduction_db(freqs, psd_open, psd_closed, jnp.array([16.0, 55.0]))
    np.testing.assert_allclose(db, [30.0, -5.0], rtol=0, atol=ATOL_DB)
    # the band's edges belong to it: |20 - 16| = 0.25 * 16
    edge = np.full((101,), 1e-6)
    edge[20] = 1.0
    assert int(band_peak(freqs, edge, 16.0, rel_band=0.25)[1]) == 20

    f_peak, idx = band_peak(freqs, psd_open, 16.0)
    assert float(f_peak) == 17.0 and int(idx) == 17
    # A narrower band excludes 17 Hz (|17 - 16| > 0.05 * 16), so 16 Hz is taken: 90 dB.
    np.testing.assert_allclose(
        vibration_reduction_db(freqs, psd_open, psd_closed, jnp.array([16.0]), rel_band=0.05), [90.0], atol=ATOL_DB
    )
    # A band with no bins gives NaN, not a silent read of bin 0.
    f_peak, _ = band_peak(jnp.array([0.0, 10.0, 20.0]), jnp.ones(3), 14.0, rel_band=0.1)
    assert np.isnan(f_peak)
    # ... and a gradient of exactly 0 there (as documented), while the other mode's is 10 log10 e / psd
    bandless = jax.grad(lambda closed: jnp.sum(vibration_reduction_db(freqs, psd_open, closed, jnp.array([16.0, 500.0]))))(jnp.asarray(psd_closed))
    expected = np.zeros(101)
    expected[17] = -10 / np.log(10) / psd_closed[17]
    np.testing.assert_allclose(bandless, expected, rtol=1e-12)
    # A band whose PSD is all 0 (a mode not excited) still gives a bin in the band, its lowest
    f_peak, idx = band_peak(jnp.arange(10.0), jnp.zeros(10), 5.0, rel_band=0.3)
    assert float(f_peak) == 4.0 and int(idx) == 4
    with pytest.raises(ValueError, match="mode_freqs_hz"):
        vibration_reduction_db(freqs, psd_open, psd_closed, jnp.array([-1.0]))
    # Bands are checked by name: a negative or NaN band gave NaN or no bins, a string and an
    # array of centres failed deep in JAX.
    for call, match in (
        (lambda: band_mask(freqs, 16.0, -0.1), r"rel_band must be finite and > 0; got -0.1"),
        (lambda: band_mask(freqs, float("nan")), r"f0 must be finite and > 0 \(Hz\); got nan"),
        (lambda: band_peak(freqs, psd_open, jnp.array([16.0, 30.0])), r"f0 must be a scalar \(Hz\); got shape \(2,\)"),
        (lambda: vibration_reduction_db(freqs, psd_open, psd_closed, [16.0], rel_band="0.1"), "rel_band must be a real number; got '0.1'"),
        (lambda: vibration_reduction_db(freqs, psd_open, psd_closed, "16"), "mode_freqs_hz must be a real number or an array of real numbers; got '16'"),
    ):
        with pytest.raises(ValueError, match=match):
            call()


def test_vibration_reduction_db_on_welch_outputs():
    # Open loop: two tones; closed loop: same tones scaled by 1e-2 and 1e-1 in amplitude
    # -> 40 dB and 20 dB in power, whatever the window (the PSD is linear in power).
    t = np.arange(8192) / FS
    tones = [(16.0, 1.0, 1e-2), (55.0, 0.5, 1e-1)]
    x_open = sum(a * np.sin(2 * np.pi * f * t) for f, a, _ in tones)
    x_closed = sum(g * a * np.sin(2 * np.pi * f * t) for f, a, g in tones)
    f, p_open = welch(x_open, FS, nperseg=512)
    _, p_closed = welch(x_closed, FS, nperseg=512)
    db = vibration_reduction_db(f, p_open, p_closed, jnp.array([16.0, 55.0]))
    np.testing.assert_allclose(db, [40.0, 20.0], atol=1e-3)  # leakage of the other tone only


def test_jit_equals_eager():
    x = _signal(4, (600, 2))
    kw = dict(window="hamming", nperseg=100, noverlap=30, detrend="linear")
    modes = jnp.array([20.0, 55.0])

    def analyse(x_open, x_closed):
        f, p_open = welch(x_open, FS, **kw)
        _, p_closed = welch(x_closed, FS, **kw)
        return f, p_open, vibration_reduction_db(f, p_open, p_closed, modes)

    out_jit = jax.jit(analyse)(x[:, 0], x[:, 1])
    with jax.disable_jit():
        out_eager = analyse(x[:, 0], x[:, 1])
    for got, want in zip(out_jit, out_eager):
        np.testing.assert_allclose(got, want, rtol=RTOL_TRANSFORM)
    # [T, n] input under jit as well.
    _, p2 = jax.jit(lambda x: welch(x, FS, **kw))(x)
    np.testing.assert_allclose(p2[:, 0], out_eager[1], rtol=RTOL_TRANSFORM)


def test_vmap_equals_loop_and_grad_finite():
    xs = _signal(5, (500, 4)).T  # [B, T] batch of signals
    xs = jnp.asarray(xs)
    fn = lambda x: welch(x, FS, nperseg=64, detrend="linear")[1]
    batched = jax.vmap(fn)(xs)
    looped = jnp.stack([fn(x) for x in xs])
    np.testing.assert_allclose(batched, looped, rtol=RTOL_TRANSFORM)
    # Differentiable in x and fs.
    g = jax.grad(lambda x, fs: jnp.sum(welch(x, fs, nperseg=64)[1]), argnums=(0, 1))(xs[0], FS)
    assert np.all(np.isfinite(g[0])) and np.any(g[0] != 0) and np.isfinite(g[1]) and g[1] < 0


def test_float32_preserved():
    x = jnp.asarray(_signal(6, (512,)), jnp.float32)
    f, p = welch(x, FS, nperseg=128)
    assert f.dtype == jnp.float32 and p.dtype == jnp.float32
    _, p_ref = scipy.signal.welch(np.asarray(x, np.float64), FS, nperseg=128)
    np.testing.assert_allclose(p, p_ref, rtol=1e-4, atol=1e-6 * p_ref.max())  # f32 roundoff


def test_validation_errors():
    x = jnp.ones(100)
    with pytest.raises(ValueError, match=r"nperseg must satisfy 1 <= nperseg <= T = 100"):
        welch(x, FS, nperseg=101)
    with pytest.raises(ValueError, match=r"nperseg"):
        welch(x, FS, nperseg=0)
    with pytest.raises(ValueError, match=r"nperseg"):
        welch(x, FS, nperseg=32.0)
    with pytest.raises(ValueError, match=r"noverlap must satisfy 0 <= noverlap < nperseg = 32"):
        welch(x, FS, nperseg=32, noverlap=32)
    with pytest.raises(ValueError, match=r"noverlap"):
        welch(x, FS, nperseg=32, noverlap=-1)
    with pytest.raises(ValueError, match=r"window must be one of .*hann.*hamming.*blackman.*boxcar"):
        welch(x, FS, nperseg=32, window="kaiser")
    with pytest.raises(ValueError, match=r"detrend"):
        welch(x, FS, nperseg=32, detrend="quadratic")
    for bad_fs in (0.0, -1.0, np.inf, np.nan):
        with pytest.raises(ValueError, match=r"fs must be finite and > 0"):
            welch(x, bad_fs, nperseg=32)
    for bad_fs in ("1000", True, None):  # float() takes the first two, as 1 kHz and 1 Hz
        with pytest.raises(ValueError, match=r"fs must be a real number; got"):
            welch(x, bad_fs, nperseg=32)
    with pytest.raises(ValueError, match=r"\[T\] or \[T, n\]"):
        welch(jnp.ones((10, 2, 2)), FS, nperseg=4)


def test_psd_figure_shows_every_mode_below_nyquist():
    """The PSD figure once stopped at 150 Hz whatever the arm: a stiff arm's modes at 216 and
    695 Hz were cut off. The axis now reaches 1.5 times the highest mode, within the estimate."""
    import matplotlib.pyplot as plt

    from jaxflex import plotting

    freqs = np.linspace(0, 500, 513)
    psd = np.ones_like(freqs)
    for modes, right in (((13.3, 36.5), 150.0), ((216.0, 695.0), 500.0), ((216.0,), 324.0)):
        fig = plotting.psds(freqs, {"tuned": psd}, modes, "y", "title")
        line = fig.axes[0].get_lines()[0]
        assert np.max(line.get_xdata()) == freqs[freqs <= right].max(), modes
        marked = [ln.get_xdata()[0] for ln in fig.axes[0].get_lines()[1:]]
        assert marked == [f for f in modes if f <= right]
        plt.close(fig)


def test_psd_figure_legend_names_the_modes_and_a_diverged_run():
    """The mode lines were unlabelled, and a diverged run vanished from the figure without a
    word; both are named in the legend now."""
    import matplotlib.pyplot as plt

    from jaxflex import plotting

    freqs = np.linspace(0, 500, 513)
    fig = plotting.psds(freqs, {"dfs": np.ones_like(freqs), "tuned": np.full_like(freqs, np.nan)}, (13.32, 36.47, 400.0), "y", "title", fmax=150.0)
    texts = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    plt.close(fig)
    assert "model modes (13.3, 36.5 Hz)" in texts  # only the modes on the axis (up to 150 Hz)
    assert any(t.endswith("(non-finite, not drawn)") for t in texts)
    assert len(texts) == 3
    # the modes as the title's arm_label writes them: 5.957 Hz read "6.0" under a title's "5.96"
    fig = plotting.psds(freqs, {"dfs": np.ones_like(freqs)}, (5.957, 20.21), "y", plotting.arm_label(0.8, (5.957, 20.21)))
    assert "model modes (5.96, 20.2 Hz)" in [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert fig.axes[0].get_title().endswith("at 5.96, 20.2 Hz")
    plt.close(fig)


def test_welch_and_reduction_gradients_against_scipy_central_differences():
    """Derivatives of the Welch PSD (in a signal parameter and in fs) against central
    differences of scipy.signal.welch, and of the dB reduction in a parameter of the closed
    PSD against central differences of its definition in NumPy (10 log10 of open / closed at
    the open loop's peak bin in each band). h = 1e-5 relative: truncation ~1e-10, round-off ~1e-11, relative."""
    t = np.arange(400) / FS
    noise = _signal(11, (400,))
    kw = dict(nperseg=128, noverlap=64)

    def signal(a, xp):
        return a * noise + a**2 * xp.sin(2 * np.pi * 31.0 * t)

    def ours(a, fs):
        return welch(signal(a, jnp), fs, window="hann", detrend="constant", **kw)[1][5:30]

    def reference(a, fs):
        return scipy.signal.welch(signal(a, np), fs, window="hann", detrend="constant", scaling="density", **kw)[1][5:30]

    a, fs = 1.3, FS
    jac = jax.jit(jax.jacfwd(ours, argnums=(0, 1)))(a, fs)
    for i, (da, dfs) in enumerate(((1e-5 * a, 0.0), (0.0, 1e-5 * fs))):
        fd = (reference(a + da, fs + dfs) - reference(a - da, fs - dfs)) / (2 * (da + dfs))
        assert np.all(np.isfinite(np.asarray(jac[i]))) and np.max(np.abs(fd)) > 0
        np.testing.assert_allclose(np.asarray(jac[i]), fd, rtol=1e-6, atol=1e-8 * np.max(np.abs(fd)))

    freqs, psd_open = (np.asarray(v) for v in welch(noise, FS, nperseg=128))
    modes = np.array([20.0, 55.0])

    def closed(c, xp):
        return psd_open * xp.exp(-c * freqs / 40.0) * (1 + 0.1 * xp.cos(freqs / 7.0))

    def reduction_np(c):
        out = []
        for f0 in modes:
            band = np.abs(freqs - f0) <= 0.15 * f0
            i = np.flatnonzero(band)[np.argmax(psd_open[band])]
            out.append(10 * np.log10(psd_open[i] / closed(c, np)[i]))
        return np.array(out)

    c = 0.7
    got = np.asarray(jax.jacfwd(lambda c: vibration_reduction_db(freqs, psd_open, closed(c, jnp), modes))(c))
    fd = (reduction_np(c + 1e-5) - reduction_np(c - 1e-5)) / 2e-5
    assert np.all(got != 0)
    np.testing.assert_allclose(got, fd, rtol=1e-6)


def test_region_reduction_finds_a_moved_peak_and_tells_a_skirt():
    """A closed loop that moves mode 1's resonance from 13 to 18 Hz: the reduction at the open
    loop's bin (13 Hz) overstates what it removed; over mode 1's region the closed loop's
    highest bin is its new peak. Mode 2's region (from sqrt(13 x 36) = 21.6 Hz) holds only
    the skirt of that peak, highest at the region's first bin, 22 Hz."""
    freqs = np.arange(0.0, 101.0)
    lorentz = lambda f0, width, height: height / (1 + ((freqs - f0) / width) ** 2)
    psd_open = lorentz(13.0, 0.5, 1.0) + lorentz(36.0, 0.5, 0.1) + 1e-9
    psd_closed = lorentz(18.0, 1.0, 1e-4) + 1e-12
    region = region_reduction_db(freqs, psd_open, psd_closed, [13.0, 36.0])
    expected = [10 * np.log10(psd_open[13] / psd_closed[18]), 10 * np.log10(psd_open[36] / psd_closed[22])]
    np.testing.assert_allclose(region.db, expected, rtol=1e-6)
    np.testing.assert_array_equal(region.f_closed_hz, [18.0, 22.0])
    np.testing.assert_array_equal(region.is_peak, [True, False])
    at_bin = vibration_reduction_db(freqs, psd_open, psd_closed, [13.0, 36.0])
    assert at_bin[0] > region.db[0] + 10  # the open loop's bin misses the moved peak
    # the regions' outer edges: f1 / 2 and 2 fn (a closed-loop peak at 5 Hz lies outside mode 1's)
    low = region_reduction_db(freqs, psd_open, lorentz(5.0, 0.5, 1.0) + 1e-12, [13.0, 36.0])
    assert low.f_closed_hz[0] == 7.0 and not low.is_peak[0]
    with pytest.raises(ValueError, match=r"mode_freqs_hz must be strictly increasing \(Hz\)"):
        region_reduction_db(freqs, psd_open, psd_closed, [36.0, 13.0])
    with pytest.raises(ValueError, match="psd_closed must be a power spectral density"):
        region_reduction_db(freqs, psd_open, -psd_closed, [13.0, 36.0])


@pytest.mark.parametrize(
    "modes, peak_hz",
    [
        ([13.0, 36.0], 60.0),  # inside the last region, [21.6, 72): its upper edge is 2 fn, not less
        ([13.0, 36.0], 80.0),  # beyond it: the skirt at the last bin below 72 Hz
        ([13.0, 36.0], 25.0),  # mode 1's skirt rises toward its region's upper edge, 21.6 Hz: not a peak
        ([4.0, 9.0], 6.0),  # an edge exactly on a bin, sqrt(4 x 9) = 6: the bin is the upper region's only
    ],
)
def test_region_reduction_edges_are_half_open_from_f1_over_2_to_2_fn(modes, peak_hz):
    """The regions as documented, read with NumPy: [f1 / 2, sqrt(f1 f2)), ..., [sqrt(fn-1 fn),
    2 fn); in each, the closed loop's highest bin, a peak when it is at least both neighbours."""
    freqs = np.arange(0.0, 101.0)
    psd_open = sum(1.0 / (1 + (freqs - f) ** 2) for f in modes) + 1e-9
    psd_closed = 1e-4 / (1 + ((freqs - peak_hz) / 1.5) ** 2) + 1e-12
    region = region_reduction_db(freqs, psd_open, psd_closed, modes)
    m = np.asarray(modes)
    edges = np.concatenate([m[:1] / 2, np.sqrt(m[:-1] * m[1:]), m[-1:] * 2])
    for i, f0 in enumerate(modes):
        inside = np.flatnonzero((freqs >= edges[i]) & (freqs < edges[i + 1]))
        top = inside[np.argmax(psd_closed[inside])]
        band = np.flatnonzero(np.abs(freqs - f0) <= 0.15 * f0)
        assert region.f_closed_hz[i] == freqs[top]
        assert bool(region.is_peak[i]) == bool(psd_closed[top] >= max(psd_closed[top - 1], psd_closed[top + 1]))
        assert region.db[i] == pytest.approx(10 * np.log10(psd_open[band].max() / psd_closed[top]), rel=1e-6)
    expected = {60.0: ([21.0, 60.0], [False, True]), 80.0: ([21.0, 71.0], [False, False]),
                25.0: ([21.0, 25.0], [False, True]), 6.0: ([5.0, 6.0], [False, True])}[peak_hz]
    np.testing.assert_array_equal(region.f_closed_hz, expected[0])  # the same, written out
    np.testing.assert_array_equal(region.is_peak, expected[1])


def test_region_reduction_of_a_nan_or_zero_spectrum():
    """A NaN closed-loop PSD (a diverged run) gave NaN dB beside a finite frequency and a
    'peak'; an all-zero one gave inf dB at a 'peak'."""
    freqs = np.arange(0.0, 101.0)
    psd_open = 1.0 / (1 + (freqs - 13.0) ** 2) + 1e-9
    nan = region_reduction_db(freqs, psd_open, np.full(freqs.shape, np.nan), [13.0])
    assert np.isnan(nan.db[0]) and np.isnan(nan.f_closed_hz[0]) and not nan.is_peak[0]
    zero = region_reduction_db(freqs, psd_open, np.zeros(freqs.shape), [13.0])
    assert np.isinf(zero.db[0]) and not zero.is_peak[0]


def _trend_noise(n=400, seed=3):
    t = np.arange(n) / FS
    return np.random.default_rng(seed).standard_normal(n) + 0.7 + 3.0 * t


def test_linear_detrend_with_one_sample_segments_matches_scipy():
    """`nperseg` = 1 with linear detrend: each one-sample segment's residual is 0 (scipy
    gives 0 up to roundoff); dividing by <t, t> = 0 gave NaN."""
    x = _trend_noise(50)
    f, p = welch(x, FS, window="hann", nperseg=1, noverlap=0, detrend="linear")
    f_ref, p_ref = scipy.signal.welch(x, FS, window="hann", nperseg=1, noverlap=0, detrend="linear", axis=0)
    np.testing.assert_allclose(f, f_ref)
    assert np.all(np.isfinite(p))
    np.testing.assert_allclose(p, p_ref, atol=1e-20)


def test_integer_signal_is_computed_in_the_default_float():
    """An integer x is computed in JAX's default float (float64 under x64, as these
    tests run), matching scipy to float64 precision, not in float32."""
    x = (np.random.default_rng(4).integers(-1000, 1000, 512)).astype(np.int64)
    f, p = welch(x, FS, nperseg=128)
    assert p.dtype == jnp.result_type(float) == jnp.float64
    _, p_ref = scipy.signal.welch(x.astype(np.float64), FS, nperseg=128, axis=0)
    np.testing.assert_allclose(p, p_ref, rtol=1e-10, atol=1e-12 * p_ref.max())


def test_a_traced_complex_signal_is_refused_by_name():
    """A complex x under jit (the eager real_array check cannot see it) is refused, not
    silently cast to its real part."""
    with pytest.raises(ValueError, match="real signal"):
        jax.jit(lambda x: welch(x, FS, nperseg=8))(jnp.ones(16) + 1j)


@pytest.mark.parametrize("kw", [{"noverlap": 10}, {"detrend": "linear"}, {"window": "boxcar"}])
def test_settings_with_any_changed_keyword_is_refused(kw):
    """`settings=` together with any of the four keywords changed from its default is
    refused (the docstring's contract); a dropped noverlap comparison let noverlap=10 be
    silently ignored."""
    s = PSDSettings(window="hann", nperseg=64, noverlap=None, detrend="constant")
    with pytest.raises(ValueError, match="not both"):
        welch(_trend_noise(), FS, settings=s, **kw)


def test_a_mode_at_zero_hz_is_refused():
    """`mode_freqs_hz` must be > 0: a 0 Hz 'mode' has a zero-width band (only the DC bin) and
    no region; it is refused by name, not read at DC."""
    freqs = np.arange(0.0, 101.0)
    psd = 1.0 / (1 + (freqs - 13.0) ** 2) + 1e-9
    for fn in (vibration_reduction_db, region_reduction_db):
        with pytest.raises(ValueError, match=r"mode_freqs_hz must be finite and > 0"):
            fn(freqs, psd, psd / 2, [0.0, 13.0])


def _region_oracle(freqs, psd_closed, modes):
    """The documented regions and peak test, in NumPy: [f1/2, sqrt(f1 f2)), ..., [.., 2 fn);
    the lowest-index highest bin; a peak when > 0, not the first or last bin of the spectrum,
    and at least both its neighbours."""
    m = np.asarray(modes)
    edges = np.concatenate([m[:1] / 2, np.sqrt(m[:-1] * m[1:]), m[-1:] * 2])
    out = []
    for i in range(len(m)):
        inside = np.flatnonzero((freqs >= edges[i]) & (freqs < edges[i + 1]))
        top = inside[np.argmax(psd_closed[inside])]
        peak = 0 < top < len(freqs) - 1 and psd_closed[top] > 0 and psd_closed[top] >= psd_closed[top - 1] and psd_closed[top] >= psd_closed[top + 1]
        out.append((freqs[top], bool(peak)))
    return out


@pytest.mark.parametrize("case", ["plateau_across_lower_edge", "first_bin", "last_bin"])
def test_region_peak_test_at_plateaus_and_spectrum_ends(case):
    """A highest bin equal to the one below it, just outside the region, is still 'at least
    both neighbours'; the spectrum's first bin is never a peak, nor is its last."""
    modes = [13.0, 36.0]
    if case == "plateau_across_lower_edge":  # mode 2's region starts at sqrt(13 * 36) = 21.6 Hz
        freqs = np.arange(0.0, 101.0)
        psd_closed = np.full(freqs.shape, 1e-9)
        psd_closed[21] = psd_closed[22] = 1e-3
    elif case == "first_bin":  # a spectrum starting inside mode 1's region, falling from its first bin
        freqs = np.arange(10.0, 101.0)
        psd_closed = 1e-3 / (1 + (freqs - 2.0) ** 2) + 1e-12
    else:  # a spectrum ending inside mode 2's region, rising to its last bin
        freqs = np.arange(0.0, 60.0)
        psd_closed = 1e-3 / (1 + ((freqs - 80.0) / 3) ** 2) + 1e-12
    psd_open = sum(1.0 / (1 + (freqs - f) ** 2) for f in modes) + 1e-9
    region = region_reduction_db(freqs, psd_open, psd_closed, modes)
    want = _region_oracle(freqs, psd_closed, modes)
    np.testing.assert_array_equal(region.f_closed_hz, [w[0] for w in want])
    np.testing.assert_array_equal(np.asarray(region.is_peak), [w[1] for w in want])


def test_equal_mode_frequencies_are_refused():
    """Mode frequencies must be strictly increasing: two equal modes (an empty region between them) are refused."""
    freqs = np.arange(0.0, 101.0)
    psd = 1.0 / (1 + (freqs - 13.0) ** 2) + 1e-9
    with pytest.raises(ValueError, match="strictly increasing"):
        region_reduction_db(freqs, psd, psd / 2, [13.0, 13.0])


def test_empty_bins_are_refused_by_name():
    """An empty freqs/psd is refused by name as 'a non-empty 1-D array'."""
    with pytest.raises(ValueError, match="non-empty 1-D array"):
        band_mask(np.array([]), 10.0)
    with pytest.raises(ValueError, match="non-empty 1-D array"):
        band_peak(np.array([]), np.array([]), 10.0)


def test_band_peak_refuses_psd_of_another_length():
    """A psd whose length is not freqs' is refused by name (a length-1 psd broadcast
    silently and gave the first in-band bin)."""
    freqs = np.arange(0.0, 50.0)
    for psd in (np.ones(1), np.ones(49)):
        with pytest.raises(ValueError, match=r"freqs and psd must both have shape \[F\]"):
            band_peak(freqs, psd, 10.0)


def test_to_dict_nfft_is_the_fft_length_welch_uses():
    """To_dict's nfft is the FFT length behind welch's frequency grid: F = nfft // 2 + 1
    bins spaced fs / nfft (as scipy.signal.welch with that nfft gives them)."""
    for nperseg in (64, 75):
        s = PSDSettings(nperseg=nperseg)
        d = s.to_dict()
        f, _ = welch(_trend_noise(), FS, settings=s)
        f_ref, _ = scipy.signal.welch(_trend_noise(), FS, nperseg=nperseg, nfft=d["nfft"])
        np.testing.assert_allclose(f, f_ref, rtol=1e-12)
