"""tuning.identify and `jaxflex calibrate --record`: the arm's modes from a free-vibration record.

Oracles: scipy's eigenvalues of the continuous plant (the free decay is sampled from
``expm(A t)``, not from jaxflex's rollout), damped sinusoids written in closed form, and the
arm that made the record (recovered by the calibration).
"""

import json
import os
import re

import jax
import numpy as np
import pytest
import scipy.linalg

from jaxflex import cli
from jaxflex.beam import BeamParams
from jaxflex.plant import discretize, make_plant
from tuning.identify import identify_modes, read_record

PAPER = BeamParams()
DT = 1e-3


def _modes_of(arm: BeamParams, n_modes: int) -> tuple[np.ndarray, np.ndarray]:
    """The flexible modes' undamped frequencies (Hz) and damping ratios from the eigenvalues."""
    lam = scipy.linalg.eigvals(np.asarray(make_plant(arm, n_modes).A))
    lam = lam[lam.imag > 1e-9]
    lam = lam[np.argsort(np.abs(lam))]
    return np.abs(lam) / (2 * np.pi), -lam.real / np.abs(lam)


def _free_decay(arm: BeamParams, n_modes: int, steps: int, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``t`` and ``[hub angle, tip deflection]`` from ``x0``, sampled exactly (``expm``)."""
    plant = make_plant(arm, n_modes)
    step = scipy.linalg.expm(np.asarray(plant.A) * DT)
    xs = [np.asarray(x0, np.float64)]
    for _ in range(steps - 1):
        xs.append(step @ xs[-1])
    outputs = np.stack([np.asarray(plant.C)[0], np.asarray(plant.Cz)[1]])
    return DT * np.arange(steps), np.stack(xs) @ outputs.T


def _x0(n_modes: int) -> np.ndarray:
    """A hub kick and a bent link: every mode moves, and the hub drifts (the rigid mode)."""
    x0 = np.zeros(2 * (n_modes + 1))
    x0[1:n_modes + 1] = 0.01 / np.arange(1, n_modes + 1)
    x0[n_modes + 1] = 0.2
    return x0


@pytest.mark.parametrize("channels", [[0], [1], [0, 1]], ids=["hub angle", "tip", "both"])
def test_modes_of_a_free_decay_are_the_plants_eigenvalues(channels):
    t, y = _free_decay(PAPER, 2, 3000, _x0(2))
    modes = identify_modes(t, y[:, channels], 2)
    freqs, damping = _modes_of(PAPER, 2)
    np.testing.assert_allclose(modes.frequencies_hz, freqs, rtol=1e-10)
    np.testing.assert_allclose(modes.damping, damping, rtol=1e-9)
    assert modes.residual < 1e-9 and modes.dt == pytest.approx(DT, rel=1e-12)
    np.testing.assert_allclose(modes.reconstruction, y[:, channels], atol=1e-9 * np.max(np.abs(y)))


def test_the_factorisations_run_on_one_blas_thread(monkeypatch):
    """NumPy's default BLAS threads made a 100,000-sample record take 11 to 80 s to identify on
    a 2-core machine, against 3 s on one: every least-squares fit and factorisation runs inside
    a one-thread limit, and the caller's setting is back afterwards."""
    from threadpoolctl import threadpool_info

    def blas_threads() -> set[int]:
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}

    seen = []
    for name in ("qr", "svd", "lstsq"):  # polyfit calls np.linalg.lstsq too
        original = getattr(np.linalg, name)

        def recording(*args, _original=original, **kwargs):
            seen.append(blas_threads())
            return _original(*args, **kwargs)

        monkeypatch.setattr(np.linalg, name, recording)
    before = blas_threads()
    t, y = _free_decay(PAPER, 2, 3000, _x0(2))
    identify_modes(t, y, 2)
    assert len(seen) >= 4 and all(threads == {1} for threads in seen)
    assert blas_threads() == before


def test_a_component_that_alternates_sign_each_sample_is_no_mode():
    """A real negative pole, (-0.995)^k (a mode aliased onto the Nyquist frequency, or a sensor
    that flips sign each sample), is not a mode: asked for 2, only the 10 Hz one is found, and
    alone it is exact (undamped 10 sqrt(1 + 0.02^2) Hz for a decay rate of 0.02 x 2 pi 10 1/s)."""
    t = np.arange(3000) * DT
    y = np.exp(-0.02 * 2 * np.pi * 10 * t) * np.cos(2 * np.pi * 10 * t) + 0.5 * (-0.995) ** np.arange(t.size)
    with pytest.raises(ValueError, match=r"found 1 mode\(s\) above the noise in the window \(10 Hz\)"):
        identify_modes(t, y, 2)
    modes = identify_modes(t, y, 1)
    np.testing.assert_allclose(modes.frequencies_hz, [10 * np.sqrt(1 + 0.02**2)], rtol=1e-6)
    np.testing.assert_allclose(modes.damping, [0.02 / np.sqrt(1 + 0.02**2)], rtol=1e-5)


def test_closed_form_sinusoids_offset_and_ramp():
    t = np.arange(2500) * 2e-3 + 7.0  # the record's clock need not start at 0
    freqs, damping = np.array([3.0, 11.0, 47.0]), np.array([0.05, 0.002, 0.2])
    wn = 2 * np.pi * freqs
    wd = wn * np.sqrt(1 - damping**2)
    tt = t - t[0]
    y = 0.3 + 0.01 * tt + sum(a * np.exp(-z * w * tt) * np.cos(v * tt + p) for a, z, w, v, p in zip([1.0, 0.2, 0.5], damping, wn, wd, [0.3, 1.0, -2.0]))
    modes = identify_modes(t, y, 3)
    np.testing.assert_allclose(modes.frequencies_hz, freqs, rtol=1e-10)
    np.testing.assert_allclose(modes.damping, damping, rtol=1e-9)
    # each mode's RMS over the window in the channel, against the closed form's
    rms = [np.sqrt(np.mean((a * np.exp(-z * w * tt) * np.cos(v * tt + p)) ** 2)) for a, z, w, v, p in zip([1.0, 0.2, 0.5], damping, wn, wd, [0.3, 1.0, -2.0])]
    np.testing.assert_allclose(modes.rms[:, 0], rms, rtol=1e-8)
    assert modes.start_s == t[0] and modes.end_s == t[-1]


def test_the_lowest_modes_above_the_noise_are_kept():
    tt = np.arange(3000) * DT
    weak, strong_low, strong_high = (a * np.exp(-0.5 * tt) * np.sin(2 * np.pi * f * tt) for a, f in ((1e-3, 5.0), (1.0, 20.0), (0.5, 90.0)))
    clean = weak + strong_low + strong_high
    hz = np.hypot([5.0, 20.0, 90.0], 0.5 / (2 * np.pi))
    np.testing.assert_allclose(identify_modes(tt, clean, 2).frequencies_hz, hz[:2], rtol=1e-9)  # the weak mode is no noise
    noisy = clean + 1e-2 * np.random.default_rng(0).standard_normal(3000)  # 7x the weak mode's RMS
    np.testing.assert_allclose(identify_modes(tt, noisy, 2).frequencies_hz, hz[1:], rtol=1e-4)
    with pytest.raises(ValueError, match=r"found 2 mode\(s\) above the noise in the window \(20 Hz, 90 Hz\), not the 3 asked for"):
        identify_modes(tt, noisy, 3)


def test_higher_modes_in_the_record_leave_the_lower_ones_right():
    # The arm has more modes than are asked for: modes 1 and 2 of the 8-mode arm, not mode 3
    # (the strongest after mode 1 in the tip), and its damping ratios to 1 %.
    t, y = _free_decay(PAPER, 8, 3000, _x0(8))
    freqs, damping = _modes_of(PAPER, 8)
    for channels in ([0], [1], [0, 1]):
        modes = identify_modes(t, y[:, channels], 2)
        np.testing.assert_allclose(modes.frequencies_hz, freqs[:2], rtol=1e-4)
        np.testing.assert_allclose(modes.damping, damping[:2], rtol=1e-2)


def test_offset_and_drift_do_not_hide_what_the_model_leaves():
    t, y = _free_decay(PAPER, 8, 3000, _x0(8))
    tip = y[:, 1]
    base = identify_modes(t, tip, 1)
    shifted = identify_modes(t, tip + 1e3 * np.std(tip) + 10 * np.std(tip) * t, 1)
    # modes 6-8 are left, beyond the 1 + 4 fitted (with no offset or drift, the 2 poles kept
    # for them fit a sixth mode): a thousandfold offset does not make that look like nothing
    assert base.residual > 1e-3
    assert base.residual / 3 < shifted.residual < 3 * base.residual
    np.testing.assert_allclose(shifted.frequencies_hz, base.frequencies_hz, rtol=1e-5)


def test_channels_are_weighed_alike_whatever_their_units():
    # Mode 2 is only in the second channel, in units 1e6 times smaller: unscaled, the first
    # channel's SVD directions would leave it out.
    tt = np.arange(2000) * DT
    first = 1e3 * np.exp(-1.0 * tt) * np.sin(2 * np.pi * 10 * tt)
    second = 1e-3 * np.exp(-2.0 * tt) * np.sin(2 * np.pi * 33 * tt)
    noise = np.random.default_rng(0).standard_normal((2000, 2)) * [1e-3 * 1e3, 0.0]
    modes = identify_modes(tt, np.stack([first, second], 1) + noise, 2)
    np.testing.assert_allclose(modes.frequencies_hz, np.hypot([10.0, 33.0], np.array([1.0, 2.0]) / (2 * np.pi)), rtol=1e-5)


def test_noise_moves_the_modes_little():
    # 1 % sensor noise on the tip: frequencies to 1e-4 and damping ratios to 5 % (measured
    # 1e-5 and 4e-4 with this seed); the residual is the noise.
    t, y = _free_decay(PAPER, 2, 3000, _x0(2))
    tip = y[:, 1] + 0.01 * np.std(y[:, 1]) * np.random.default_rng(0).standard_normal(3000)
    modes = identify_modes(t, tip, 2)
    freqs, damping = _modes_of(PAPER, 2)
    np.testing.assert_allclose(modes.frequencies_hz, freqs, rtol=1e-4)
    np.testing.assert_allclose(modes.damping, damping, rtol=5e-2)
    assert 0.005 < modes.residual < 0.02


def test_sample_times_may_be_rounded_but_not_irregular():
    dt = 1 / 5120
    tt = np.arange(5000) * dt
    y = np.exp(-tt) * np.sin(2 * np.pi * 30 * tt)
    hz = [np.hypot(30.0, 1 / (2 * np.pi))]
    # written to 4 decimals, the times are up to 0.26 of a sample off the grid
    assert np.max(np.abs(np.round(tt, 4) - tt)) > 0.25 * dt
    # dt from the grid that fits them best: 2.5e-8 off (from the first and last times alone, 3.4e-5)
    np.testing.assert_allclose(identify_modes(np.round(tt, 4), y, 1).frequencies_hz, hz, rtol=1e-7)
    for off, accepted in ((0.45, True), (0.55, False)):
        late = tt.copy()
        late[2500] += off * dt
        if accepted:
            np.testing.assert_allclose(identify_modes(late, y, 1).frequencies_hz, hz, rtol=1e-9)
        else:
            with pytest.raises(ValueError, match="t must be uniformly sampled"):
                identify_modes(late, y, 1)


def test_a_growing_mode_over_a_long_window_is_refused_without_overflow():
    tt = np.arange(20_000) * 1e-3  # 20 s: the mode grows by e^800, its z^t would overflow
    y = np.exp(40 * (tt - 20)) * np.sin(2 * np.pi * 20 * tt)
    with np.errstate(over="raise", invalid="raise"):
        with pytest.raises(ValueError, match="at 20.99 Hz do not decay"):
            identify_modes(tt, y, 1)


def test_window_leaves_out_the_excitation():
    # a forced part (a square wave) before the free decay: with the window, the decay alone
    tt = np.arange(3000) * DT
    decay = np.exp(-0.8 * (tt - 0.5)) * np.sin(2 * np.pi * 12 * (tt - 0.5))
    y = np.where(tt < 0.5, np.sign(np.sin(2 * np.pi * 4 * tt)), decay)
    modes = identify_modes(tt, y, 1, start_s=0.5)
    np.testing.assert_allclose(modes.frequencies_hz, [np.hypot(12.0, 0.8 / (2 * np.pi))], rtol=1e-10)
    assert modes.start_s == pytest.approx(0.5) and modes.reconstruction.shape == (2500, 1)
    with pytest.raises(ValueError, match="above the noise"):  # the whole record is no free decay
        identify_modes(tt, y, 1)


@pytest.mark.parametrize(
    "t, y, kwargs, match",
    [
        (np.arange(100) * DT, np.zeros(100), dict(n_modes=0), "n_modes must be an integer in"),
        (np.arange(100) * DT, np.ones(99), {}, "same N"),
        (np.arange(100) * DT, np.r_[np.nan, np.ones(99)], {}, "must be finite"),
        (np.arange(40) * DT, np.ones(40), {}, "holds 40 samples; 2 modes need at least 45"),
        (np.arange(100) * DT, np.ones(100), dict(start_s=1.0), r"start_s must be within the record, from its first sample at 0 s to before its last at 0.099 s \(t's clock\); got 1 s"),
        (np.arange(100) * DT, np.ones(100), dict(start_s=-0.001), r"start_s must be within the record, from its first sample at 0 s to before its last at 0.099 s \(t's clock\); got -0.001 s"),
        (np.arange(100) * DT, np.ones(100), dict(end_s=-0.5), r"end_s must be after the record's first sample, at 0 s \(t's clock\); got -0.5 s"),
        (np.arange(100) * DT, np.ones(100), dict(start_s=0.05, end_s=0.01), "end_s must be after start_s"),
        (np.arange(100) * DT, np.ones(100), dict(start_s=float("nan")), "start_s must be a finite time"),
        (np.arange(100) * DT, np.ones(100), dict(end_s="1"), "end_s must be a finite time"),
        (np.r_[np.arange(50), np.arange(50, 100) * 1.5] * DT, np.ones(100), {}, "uniformly sampled"),
        (np.arange(100)[::-1] * DT, np.ones(100), {}, "t must be strictly ascending"),
        (np.arange(100) * DT, np.c_[np.sin(np.arange(100)), 3 + np.arange(100)], {}, r"channel\(s\) \[2\] of y are constant or a straight line"),
        (np.arange(300) * DT, np.exp(-np.arange(300) * DT), {}, r"found 0 mode\(s\) above the noise"),
        # a component gone within two samples (damping ratio 0.99) is no mode: it was taken as
        # mode 2 (and a pole fitted to round-off, gone as fast, on some LAPACK builds)
        (np.arange(300) * DT, np.exp(-np.arange(300) * DT) + 0.5 * np.exp(-2000 * np.arange(300) * DT) * np.cos(2 * np.pi * 40 * np.arange(300) * DT)
         + 0.2 * np.exp(-2 * np.arange(300) * DT) * np.sin(2 * np.pi * 15 * np.arange(300) * DT), {}, r"found 1 mode\(s\) above the noise in the window \(15 Hz\)"),
        (np.arange(300) * DT, np.exp(np.arange(300) * DT) * np.sin(2 * np.pi * 20 * np.arange(300) * DT), dict(n_modes=1), "at 20 Hz do not decay"),
        ("abc", np.ones(3), {}, "t must be a real number or an array"),
    ],
)
def test_refusals(t, y, kwargs, match):
    with pytest.raises(ValueError, match=match):
        identify_modes(t, y, **kwargs)


def test_read_record(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("# tap test\ntime_s, tip_m ,strain\n0.0,1,2  # first\n\n0.001,3,4\n")
    t, y, names = read_record(path)
    np.testing.assert_array_equal(t, [0.0, 0.001])
    np.testing.assert_array_equal(y, [[1, 2], [3, 4]])
    assert names == ["tip_m", "strain"]
    path.write_text("0.0,1\n0.001,3\n")
    assert read_record(path)[2] == ["channel 1"]
    for text, match in [
        ("t,a\n0,1\n1,2,3\n", r"line 3 of .*: 3 columns, not 2 as the header line 1 has \(its names may hold no comma: quotes are not read\)$"),
        ('"time, s","tip, mm"\n0,1\n', r"line 2 of .*: 2 columns, not 4 as the header line 1 has"),  # it blamed the data line alone
        ("0,1\n1,2,3\n", r"line 2 of .*: 3 columns, not 2$"),
        ("0,001;1,2\n0,002;1,3\n", r"line 2 of .*: '002;1' is not a finite number \(the file must be comma-separated with '.' for decimals: a ';'-separated export"),
        ("t,a\n0,x\n", "line 2 of .*: 'x' is not a finite number"),
        ("t,a\n0,nan\n", "line 2 of .*: 'nan' is not a finite number"),
        ("t,a\n", "holds no rows of numbers"),
        ("0\n1\n", "a time column .* and at least one channel"),
        ("# nothing\n", "holds no rows"),
    ]:
        path.write_text(text)
        with pytest.raises(ValueError, match=match):
            read_record(path, "--record")
    with pytest.raises(ValueError, match="^path: cannot read"):  # from Python, the argument; the CLI's option is tested in test_cli
        read_record(tmp_path / "missing.csv")


def _write_record(path, t, y, header="time_s,hub_angle_rad,tip_m") -> None:
    np.savetxt(path, np.column_stack([t, y]), delimiter=",", header=header, comments="")


def test_cli_calibrates_the_arm_that_made_the_record(tmp_path, capsys):
    true = PAPER._replace(youngs_modulus_pa=71e9 * 1.1, hub_inertia_kg_m2=5.8598e-4 * 0.9, rayleigh_alpha=0.3, rayleigh_beta=2e-5)
    t, y = _free_decay(true, 2, 3000, _x0(2))
    _write_record(tmp_path / "tap.csv", t, y)
    out = tmp_path / "cal"
    assert cli.main(["calibrate", "--record", str(tmp_path / "tap.csv"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 channel(s), 2.999 s from 0 s at dt = 0.001 s" in printed
    assert sorted(os.listdir(out)) == ["calibrated.toml", "calibration.json", "calibration.png", "identification.png"]
    summary = json.loads((out / "calibration.json").read_text())
    for name in ("youngs_modulus_pa", "hub_inertia_kg_m2", "rayleigh_alpha", "rayleigh_beta"):
        np.testing.assert_allclose(summary["beam"][name], getattr(true, name), rtol=1e-8, err_msg=name)
    np.testing.assert_allclose(summary["identified"]["frequencies_hz"], _modes_of(true, 2)[0], rtol=1e-10)
    assert summary["identified"]["record"] == str(tmp_path / "tap.csv")
    # a later run from frequencies leaves no identification figure of this one behind
    assert cli.main(["calibrate", "--freqs", "13", "36", "--out", str(out)]) == 0
    assert "identification.png" not in os.listdir(out)


def test_cli_record_errors_name_options(tmp_path, capsys):
    tt = np.arange(200) * DT
    _write_record(tmp_path / "r.csv", tt, np.exp(-tt) * np.sin(2 * np.pi * 30 * tt), "t,a")
    record = str(tmp_path / "r.csv")
    for argv, message in [
        (["--record", record, "--damping", "0.01"], "error: --damping: with --record the damping ratios come from the record"),
        (["--freqs", "13", "--start", "0.1"], "error: --start, --end and --record-modes apply to --record only"),
        (["--record", record, "--start", "0.19"], "error: --record .*r.csv: the window 0.19-0.199 s holds 10 samples"),
        (["--record", record, "--start", "5"], r"error: --start must be within the record, from its first sample at 0 s to before its last at 0.199 s \(t's clock\); got 5 s"),
        (["--record", record, "--start", "0.15", "--end", "0.1"], r"error: --end must be after --start; got --start = 0.15 s, --end = 0.1 s"),
        (["--record", record, "--record-modes", "3"], "error: --record .*: found 1 mode\\(s\\) above the noise in the window \\(30 Hz\\), not the 3"),
        (["--record", str(tmp_path / "none.csv")], "error: --record: cannot read"),
    ]:
        assert cli.main(["calibrate", *argv, "--out", str(tmp_path / "out")]) == 2
        assert re.search(message, capsys.readouterr().err), argv
    assert not os.path.exists(tmp_path / "out")
    with pytest.raises(SystemExit):  # argparse: one or the other
        cli.main(["calibrate", "--freqs", "13", "--record", record])


def test_figures_draw_the_damping_and_the_record(tmp_path):
    from jaxflex import plotting

    fig = plotting.calibration(np.array([13.0, 36.0]), np.array([12.0, 35.0]), np.array([13.0, 36.0]), "t", np.array([0.012]), np.array([0.012, 0.02]))
    damping_panel = fig.axes[2]
    np.testing.assert_allclose(damping_panel.lines[0].get_ydata(), [1.2])
    np.testing.assert_allclose(damping_panel.lines[1].get_ydata(), [1.2, 2.0])
    plotting.plt.close(fig)
    assert len(plotting.calibration(np.array([13.0]), np.array([12.0]), np.array([13.0]), "t").axes) == 2  # no ratios, no panel
    t, y = _free_decay(PAPER, 2, 600, _x0(2))
    modes = identify_modes(t, y, 2, start_s=0.1)
    fig = plotting.identification(t, y, modes.start_s + modes.dt * np.arange(500), modes.reconstruction, ["hub", "tip"], "t")
    assert [ax.get_ylabel() for ax in fig.axes] == ["hub", "tip"]
    for ax, channel in zip(fig.axes, y.T):
        np.testing.assert_array_equal(ax.lines[0].get_ydata(), channel)  # the whole record
        np.testing.assert_allclose(ax.lines[1].get_ydata(), channel[100:], atol=1e-9 * np.max(np.abs(channel)))  # the model, from --start
    plotting.plt.close("all")


def test_cli_notes_a_record_the_modes_do_not_explain_and_one_sampled_too_fast(tmp_path, capsys):
    tt = np.arange(3000) * DT
    decay = np.exp(-0.1 * tt) * np.sin(2 * np.pi * 12 * tt)
    _write_record(tmp_path / "r.csv", tt, decay + 0.15 * np.random.default_rng(0).standard_normal(3000), "t,a")
    assert cli.main(["calibrate", "--record", str(tmp_path / "r.csv"), "--record-modes", "1", "--out", str(tmp_path / "a")]) == 0
    assert "unexplained: check that the window starts after the excitation" in capsys.readouterr().err
    fast = np.arange(30000) * 1e-5  # 400 lags span 4 ms, a twentieth of a period
    _write_record(tmp_path / "f.csv", fast, np.exp(-0.1 * fast) * np.sin(2 * np.pi * 12 * fast), "t,a")
    assert cli.main(["calibrate", "--record", str(tmp_path / "f.csv"), "--record-modes", "1", "--out", str(tmp_path / "b")]) == 0
    assert "sampled so fast" in capsys.readouterr().err


def test_cli_names_a_constant_channel_by_its_column(tmp_path, capsys):
    """It said "channel(s) [2, 3] of y", which the file's header names otherwise."""
    tt = np.arange(2000) * DT
    _write_record(tmp_path / "r.csv", tt, np.c_[np.exp(-tt) * np.sin(2 * np.pi * 13 * tt), 0 * tt, 1 + 0 * tt], "t,tip,zero,one")
    assert cli.main(["calibrate", "--record", str(tmp_path / "r.csv"), "--out", str(tmp_path / "a")]) == 2
    assert capsys.readouterr().err.endswith(f"error: --record {tmp_path / 'r.csv'}: channel(s) 'zero', 'one' are constant or a straight line throughout the window\n")


def test_cli_notes_a_window_too_short_for_mode_1_as_short_not_as_sampled_too_fast(tmp_path, capsys):
    tt = np.arange(3000) * DT
    _write_record(tmp_path / "r.csv", tt, np.exp(-0.1 * tt) * np.sin(2 * np.pi * 12 * tt), "t,a")
    # 0.2 s at 1 kHz (201 samples): the lags span 67 ms, less than a period (83 ms); decimating would shorten them further
    assert cli.main(["calibrate", "--record", str(tmp_path / "r.csv"), "--record-modes", "1", "--end", "0.2", "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "less than a period of mode 1" in err and "so short" in err and "--end" in err
    assert "sampled so fast" not in err


def test_read_record_takes_spreadsheet_exports(tmp_path):
    """A trailing comma on every line (an empty last cell) is no column, and a UTF-8
    byte-order mark is no part of the first cell: both as a spreadsheet writes a CSV."""
    path = tmp_path / "r.csv"
    path.write_text("time_s,tip_m,\n0.0,1.5,\n0.001,2.5,\n")
    t, y, names = read_record(path)
    np.testing.assert_array_equal(t, [0.0, 0.001])
    np.testing.assert_array_equal(y, [[1.5], [2.5]])
    assert names == ["tip_m"]
    path.write_bytes(b"\xef\xbb\xbf0.0,1.5\n0.001,2.5\n")  # no header: the first row is numbers
    t, y, names = read_record(path)
    np.testing.assert_array_equal(t, [0.0, 0.001])
    assert names == ["channel 1"] and y.shape == (2, 1)


def test_a_swing_of_less_than_a_cycle_is_no_mode():
    """A slow swing (0.2 Hz: 0.6 of a cycle in the 3 s window, undamped) cannot be told from a
    drift; set aside, the lowest mode is the 20 Hz one."""
    tt = np.arange(3000) * DT
    y = 2.0 * np.sin(2 * np.pi * 0.2 * tt + 0.4) + np.exp(-1.0 * tt) * np.sin(2 * np.pi * 20 * tt)
    modes = identify_modes(tt, y, 1)
    wn = np.hypot(2 * np.pi * 20, 1.0)
    np.testing.assert_allclose(modes.frequencies_hz, [wn / (2 * np.pi)], rtol=1e-9)
    np.testing.assert_allclose(modes.damping, [1.0 / wn], rtol=1e-7)


def test_lag_span_is_that_of_the_lags_fitted():
    """The lags run over a third of the window, at most MAX_ROWS of them: 1000 samples span
    1000 // 3 = 333 lags (0.333 s), 3000 samples MAX_ROWS (0.4 s); the command's notes on a
    short window and on fast sampling tell the two apart by this count."""
    from tuning.identify import MAX_ROWS

    tt = np.arange(3000) * DT
    y = np.exp(-1.0 * tt) * np.sin(2 * np.pi * 20 * tt)
    assert identify_modes(tt, y, 1).lag_span_s == pytest.approx(MAX_ROWS * DT, rel=1e-9)
    assert identify_modes(tt[:1000], y[:1000], 1).lag_span_s == pytest.approx(333 * DT, rel=1e-9)


def test_an_end_past_the_record_is_cut_to_it_and_a_start_before_it_refused():
    """An end_s of 3 s on a record whose last sample is at 2.999 s uses the record's end; a
    start_s before its first sample is refused, naming the record's span (it used the whole
    record, so a start in seconds from the tap on a record of Unix times took the rest and the
    tap in with no word)."""
    tt = np.arange(3000) * DT
    y = np.exp(-0.5 * tt) * np.sin(2 * np.pi * 20 * tt)
    whole, wider = identify_modes(tt, y, 1), identify_modes(tt, y, 1, end_s=3.0)
    np.testing.assert_array_equal(wider.frequencies_hz, whole.frequencies_hz)
    np.testing.assert_array_equal(wider.damping, whole.damping)
    assert (wider.start_s, wider.end_s) == (whole.start_s, whole.end_s) == (0.0, 2.999)
    with pytest.raises(ValueError, match=r"start_s must be within the record, from its first sample at 0 s to before its last at 2.999 s \(t's clock\); got -0.5 s"):
        identify_modes(tt, y, 1, start_s=-0.5, end_s=3.0)


def test_cli_refuses_a_start_outside_a_record_of_unix_times(tmp_path, capsys):
    tt = 1712345678.0 + np.arange(2000) * 2e-3
    _write_record(tmp_path / "r.csv", tt, np.exp(-(tt - tt[0])) * np.sin(2 * np.pi * 13 * (tt - tt[0])), "t,a")
    assert cli.main(["calibrate", "--record", str(tmp_path / "r.csv"), "--record-modes", "1", "--start", "0.22", "--out", str(tmp_path / "a")]) == 2
    assert capsys.readouterr().err.endswith("error: --start must be within the record, from its first sample at 1712345678 s to before its last at 1712345681.998 s "
                                            "(t's clock); got 0.22 s\n")
    assert not os.path.exists(tmp_path / "a")


def test_a_window_of_no_length_is_refused_as_such():
    tt = np.arange(300) * DT
    with pytest.raises(ValueError, match=r"end_s must be after start_s; got start_s = 0.1 s, end_s = 0.1 s"):
        identify_modes(tt, np.sin(2 * np.pi * 20 * tt), 1, start_s=0.1, end_s=0.1)


def test_a_slowly_growing_mode_is_refused():
    """A damping ratio of -4e-4 (growing by 16 % over 3 s) is no free decay: the bound is 0."""
    tt = np.arange(3000) * DT
    y = np.exp(0.05 * tt) * np.sin(2 * np.pi * 20 * tt)
    with pytest.raises(ValueError, match=r"the mode\(s\) at 20 Hz do not decay in the window"):
        identify_modes(tt, y, 1)
    modes = identify_modes(tt, np.exp(-0.05 * tt) * np.sin(2 * np.pi * 20 * tt), 1)  # its mirror image decays
    np.testing.assert_allclose(modes.damping, [0.05 / np.hypot(2 * np.pi * 20, 0.05)], rtol=1e-7)


def _tap_test(start_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The walkthrough's record: modes at 4.1 and 19 Hz (damping ratios 0.01), at rest until a
    10 ms force tap at 0.2 s, then free; a free hub's angle (drifting after the tap) and the tip's
    deflection, 4 s at 500 Hz from ``start_s``, sampled exactly (``expm``, the tap held over its
    samples)."""
    dt, zeta = 2e-3, 0.01
    wn = 2 * np.pi * np.array([4.1, 19.0])
    # the rigid mode (angle, rate), then each flexible mode's (q, q')
    a = scipy.linalg.block_diag([[0, 1], [0, 0]], *([[0, 1], [-w**2, -2 * zeta * w]] for w in wn))
    b = np.array([0, 1.0, 0, 1.0, 0, -0.6])
    step = scipy.linalg.expm(np.block([[a, b[:, None]], [np.zeros((1, 7))]]) * dt)  # the zero-order hold of the force
    ad, bd = step[:6, :6], step[:6, 6]
    x, xs = np.zeros(6), []
    for k in range(2000):
        xs.append(x)
        x = ad @ x + bd * (1.0 if 100 <= k < 105 else 0.0)
    outputs = np.array([[1, 0, 0.2, 0, 0.05, 0], [0, 0, 1, 0, 1, 0]])  # hub angle, tip deflection
    t = dt * np.arange(2000)
    keep = t >= start_s - 1e-9
    return t[keep], (np.stack(xs) @ outputs.T)[keep]


def test_a_window_from_before_the_tap_is_reported_and_one_from_after_it_holds_both_modes():
    """From 0.1 s (0.1 s of rest, then the tap) the poles fitted a mode at 11.7 Hz with a damping
    ratio of 0.41, leaving 0.5 % unexplained, and lost the 19 Hz mode; from the record's start,
    6.3 Hz and 0.30: the record rises in the window (27-32x), which a free decay does not, and
    was identified with no word of it."""
    t, y = _tap_test()
    wn = 2 * np.pi * np.array([4.1, 19.0])
    for start_s, low in ((None, 27), (0.1, 27), (0.16, 10)):  # 0.16: 40 ms of rest
        factor, channel, onset, peak = identify_modes(t, y, 2, start_s=start_s).rise
        assert factor > low and channel == 1 and 0.16 <= onset <= 0.24 and 0.21 < peak < 0.21 + 1 / 4.1
        # the tip; the rise at the tap, within a 60 ms block; the peak within a period of mode 1 after it
    modes = identify_modes(t, y, 2, start_s=0.21)  # the tap's end
    assert modes.rise is None and modes.as_dict()["rise"] is None
    np.testing.assert_allclose(modes.frequencies_hz, wn / (2 * np.pi), rtol=1e-9)
    np.testing.assert_allclose(modes.damping, [0.01, 0.01], rtol=1e-7)
    # and a record that starts there (the rest cut off) is a free decay from its first sample
    np.testing.assert_allclose(identify_modes(*_tap_test(0.21), 2).frequencies_hz, wn / (2 * np.pi), rtol=1e-9)


def test_cli_notes_a_window_from_before_the_tap_naming_start(tmp_path, capsys):
    t, y = _tap_test()
    _write_record(tmp_path / "tap2.csv", t, y, "time_s,hub_deg,tip_mm")
    assert cli.main(["calibrate", "--record", str(tmp_path / "tap2.csv"), "--start", "0.1", "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    said = re.search(r"note: channel 'tip_mm' rises \d+\.?\d*x in the window \(its RMS over a quarter period of mode 1, from the window's first, 0.1 s, to about (0\.\d+) s; "
                     r"its peak at (0\.\d+) s\): a free decay does not grow, so the window may start before the response", err)
    rise = json.loads((tmp_path / "a" / "calibration.json").read_text())["identified"]["rise"]
    assert said and rise["channel"] == 1 and [float(v) for v in said.groups()] == [rise["onset_s"], rise["peak_s"]]  # the note says what the file holds
    assert "give a --start just after the excitation has ended" in err
    assert cli.main(["calibrate", "--record", str(tmp_path / "tap2.csv"), "--start", "0.21", "--out", str(tmp_path / "b")]) == 0
    assert "rises" not in capsys.readouterr().err


def test_the_readme_tap_records_hub_angle_rises_where_its_modes_cancel():
    """Why a rise is a note and not a refusal: the README's tap record (the paper's arm, 8 modes,
    after its 20 ms pulse) is a free decay from any start after 0.02 s, yet from 0.03 s, with
    modes 1 and 2 (13.3 and 35.1 Hz) nearly cancelling in the hub angle over the first quarter
    period, that channel rises over 5x (a refusal here stopped a good record)."""
    with jax.enable_x64(True):
        arm = discretize(make_plant(BeamParams(), 8), 0.001, "zoh")
    ad, bd, cz = (np.asarray(m, np.float64) for m in (arm.Ad, arm.Bd, arm.Cz))
    x, rows = np.zeros(len(ad)), []
    for k in range(1000):
        rows.append([cz[0] @ x, cz[1] @ x])
        x = ad @ x + bd[:, 0] * (0.5 if k < 20 else 0.0)
    t = 0.001 * np.arange(1000)
    modes = identify_modes(t, np.array(rows), 2, start_s=0.03)
    assert modes.rise is not None and modes.rise[0] > 5 and modes.rise[1] == 0  # the hub angle
    np.testing.assert_allclose(modes.frequencies_hz, [13.3103, 35.1065], rtol=1e-4)  # the modes are right


@pytest.mark.parametrize("noise, n_modes", [(0.01, 2), (0.1, 2), (0.3, 1)])
def test_a_noisy_free_decay_is_no_rise(noise, n_modes):
    """Noise lifts every quarter period alike: a tap's decay (from a zero crossing) whose later
    part is mostly noise is a free decay."""
    tt = np.arange(3000) * DT
    clean = np.exp(-0.5 * tt) * np.sin(2 * np.pi * 6 * tt) + 0.5 * np.exp(-1.0 * tt) * np.sin(2 * np.pi * 27 * tt)
    y = clean + noise * np.std(clean) * np.random.default_rng(1).standard_normal(3000)
    modes = identify_modes(tt, y, n_modes)
    assert modes.rise is None
    np.testing.assert_allclose(modes.frequencies_hz, np.hypot([6.0, 27.0], np.array([0.5, 1.0]) / (2 * np.pi))[:n_modes], rtol=1e-3)


def test_a_channel_of_noise_alone_beside_a_fast_mode_is_no_rise():
    """Mode 1 at 100 Hz sampled at 1 kHz has a quarter period of 2 samples, over which a channel
    that sees only noise rose over 5x from a quiet first block (seed 12 of 20: 7.15x): no rise
    over blocks of RISE_BLOCK samples."""
    tt = np.arange(6000) * DT
    clean = np.exp(-3.0 * tt) * np.sin(2 * np.pi * 100 * tt) + 0.5 * np.exp(-5.0 * tt) * np.sin(2 * np.pi * 160 * tt)
    rng = np.random.default_rng(12)
    y = np.column_stack([clean + 0.01 * rng.standard_normal(tt.size), rng.standard_normal(tt.size)])
    modes = identify_modes(tt, y, 2)
    assert modes.rise is None
    # the noise channel, scaled to unit RMS like the other, costs mode 2 2e-4
    np.testing.assert_allclose(modes.frequencies_hz, np.hypot([100.0, 160.0], np.array([3.0, 5.0]) / (2 * np.pi)), rtol=1e-3)


def test_two_close_modes_that_beat_are_no_rise_unless_they_cancel_at_the_start():
    """10 and 10.5 Hz beat every 2 s. Tapped where both move alike, the envelope falls from the
    start; with the second at half the first's amplitude and of opposite sign, it rises from
    where they cancel by (1 + 0.5) / (1 - 0.5) = 3, under RISE_FACTOR; at equal amplitudes from
    where they cancel, it rises from nothing, which is reported, and not from its peak."""
    tt = np.arange(4000) * DT
    hz = np.hypot([10.0, 10.5], 0.3 / (2 * np.pi))
    for second in (1.0, -0.5):
        y = np.exp(-0.3 * tt) * (np.sin(2 * np.pi * 10 * tt) + second * np.sin(2 * np.pi * 10.5 * tt))
        np.testing.assert_allclose(identify_modes(tt, y, 2).frequencies_hz, hz, rtol=1e-9)
    y = np.exp(-0.3 * tt) * (np.sin(2 * np.pi * 10 * tt) - np.sin(2 * np.pi * 10.5 * tt))
    modes = identify_modes(tt, y, 2)
    assert modes.rise[0] > 5
    np.testing.assert_allclose(modes.frequencies_hz, hz, rtol=1e-9)  # a free decay: identified all the same
    modes = identify_modes(tt, y, 2, start_s=0.95)
    assert modes.rise is None
    np.testing.assert_allclose(modes.frequencies_hz, hz, rtol=1e-9)


# -- audit 15 (identify.py): each bound of the record and window checks at its edge, the needed length, small signals that are no constant, a cycle and a half, a component gone within a period, the largest rise --


def test_n_modes_over_100_is_refused_naming_the_range():
    # n_modes is checked against [1, 100] (the range the message names) before the record (I19)
    tt = np.arange(100) * DT
    with pytest.raises(ValueError, match=r"n_modes must be an integer in \[1, 100\]"):
        identify_modes(tt, np.sin(2 * np.pi * 20 * tt), 101)
    # 100 itself passes that check and meets the length one: 3 (2 (100 + 4) + 2 + 1) = 633 samples
    with pytest.raises(ValueError, match=r"holds 100 samples; 100 modes need at least 633"):
        identify_modes(tt, np.sin(2 * np.pi * 20 * tt), 100)


def test_a_record_of_one_sample_is_refused_as_too_short():
    # one sample: "at least 2 samples", not a window of no length (I20)
    with pytest.raises(ValueError, match=r"the record must hold at least 2 samples of at least 1 channel"):
        identify_modes([0.0], [1.0], 1)


def test_a_repeated_sample_time_is_not_strictly_ascending():
    # a time written twice (diff 0) is refused as not strictly ascending (I21)
    tt = np.arange(300) * DT
    tt[150] = tt[149]
    with pytest.raises(ValueError, match=r"t must be strictly ascending"):
        identify_modes(tt, np.sin(2 * np.pi * 20 * np.arange(300) * DT), 1)


def _decay(n=600):
    tt = np.arange(n) * DT
    return tt, np.exp(-0.8 * tt) * np.sin(2 * np.pi * 12 * tt)


def test_a_start_at_the_last_sample_is_outside_the_record():
    # start_s must lie in [t[0], t[-1]): the last sample itself is refused as outside (I22)
    tt = np.arange(100) * DT
    with pytest.raises(ValueError, match=r"start_s must be within the record.*got 0.099 s"):
        identify_modes(tt, np.ones(100), start_s=tt[-1])


def test_a_start_at_the_first_sample_is_the_whole_record():
    # start_s = t[0] is within the record: the same modes as no start_s (I23)
    tt, y = _decay()
    modes = identify_modes(tt, y, 1, start_s=float(tt[0]))
    np.testing.assert_allclose(modes.frequencies_hz, [np.hypot(12.0, 0.8 / (2 * np.pi))], rtol=1e-9)
    assert modes.start_s == 0.0 and modes.reconstruction.shape == (600, 1)


def test_an_end_at_the_first_sample_is_not_after_it():
    # end_s must be after t[0]: t[0] itself gets that message, not "after start_s" (I24)
    tt = np.arange(100) * DT + 2.0
    with pytest.raises(ValueError, match=r"end_s must be after the record's first sample, at 2 s \(t's clock\); got 2 s"):
        identify_modes(tt, np.ones(100), end_s=2.0)


def test_exactly_the_needed_samples_are_enough():
    # 1 mode: order 2 (1 + 4) + 2 = 12, needed 3 (12 + 1) = 39 samples; 39 are accepted (I28)
    tt = np.arange(39) * DT
    y = np.exp(-3.0 * tt) * np.sin(2 * np.pi * 100 * tt)
    modes = identify_modes(tt, y, 1)
    np.testing.assert_allclose(modes.frequencies_hz, [np.hypot(100.0, 3.0 / (2 * np.pi))], rtol=1e-6)
    with pytest.raises(ValueError, match=r"holds 38 samples; 1 modes need at least 39"):
        identify_modes(tt[:38], y[:38], 1)


def test_a_small_vibration_on_a_large_offset_is_no_constant_channel():
    # RMS about the line 3.5e-8 of the largest value: far above round-off (1e-12), a mode (I31)
    tt, y = _decay()
    modes = identify_modes(tt, 1000.0 + 1e-4 * y, 1)
    np.testing.assert_allclose(modes.frequencies_hz, [np.hypot(12.0, 0.8 / (2 * np.pi))], rtol=1e-6)


def test_a_mode_of_one_and_a_half_cycles_counts():
    # the window must hold a cycle or more of a mode (not two): 2.5 Hz over 0.599 s is 1.5 cycles (I35)
    tt, _ = _decay()
    modes = identify_modes(tt, np.exp(-0.5 * tt) * np.sin(2 * np.pi * 2.5 * tt), 1)
    np.testing.assert_allclose(modes.frequencies_hz, [np.hypot(2.5, 0.5 / (2 * np.pi))], rtol=1e-8)


def test_a_component_gone_within_a_period_but_not_half_is_no_mode():
    # 40 Hz with sigma = 3 omega (damping ratio 0.95): its envelope a period after the peak is
    # exp(-6 pi) ~ 7e-9 of it, under the noise floor; half a period after, exp(-3 pi) ~ 8e-5, over
    # it. "Still above it a period after its peak": no mode (I37)
    tt = np.arange(300) * DT
    w = 2 * np.pi * 40
    y = np.exp(-tt) + 0.5 * np.exp(-3 * w * tt) * np.cos(w * tt) + 0.2 * np.exp(-2 * tt) * np.sin(2 * np.pi * 15 * tt)
    with pytest.raises(ValueError, match=r"found 1 mode\(s\) above the noise in the window \(15 Hz\)"):
        identify_modes(tt, y, 2)


def test_the_rise_reported_is_the_largest_of_the_channels():
    # two channels rising 10x and 50x from their first quarter-period block (25 samples at
    # 10 Hz, 1 kHz): the rise is 50x, in channel 1, from the second block (I48)
    from tuning.identify import _rise

    tt = np.arange(250) * DT
    centred = np.ones((250, 2))
    centred[25:, 0] = 10.0
    centred[25:, 1] = 50.0
    factor, channel, onset, peak = _rise(tt, centred, 10.0, DT)
    assert (factor, channel) == (pytest.approx(50.0), 1)
    assert onset == pytest.approx(0.025) and peak == pytest.approx(0.025)


def test_a_small_channel_beside_a_large_one_is_no_constant_channel():
    # "constant" is judged against each channel's own values: a channel in small units beside
    # one in large units is a channel, and both see the mode (I62)
    tt, y = _decay()
    modes = identify_modes(tt, np.c_[1e9 * y, 1e-6 * y], 1)
    np.testing.assert_allclose(modes.frequencies_hz, [np.hypot(12.0, 0.8 / (2 * np.pi))], rtol=1e-8)
    assert modes.rms.shape == (1, 2)
