"""``jaxflex stability``: the DFS loop's stability at one operating point and over a (k, tau) grid.

``run(out_dir, k, tau_s, n_modes)`` writes ``stability_chart.png`` and, last,
``stability.json`` (together: an interrupted run leaves an earlier run's pair as it was) and returns the JSON content as a dict. The analysis
(:mod:`jaxflex.analysis.stability`) runs in float64 whatever the caller's JAX setting
(a scoped ``jax.enable_x64``): eigenvalues near the unit circle need it.
"""

from __future__ import annotations

import math
import os
from typing import Any, Callable

import jax
import numpy as np

import jaxflex
from jaxflex import beam, checks, fileio, plotting
from jaxflex.analysis import stability as st
from jaxflex.controllers.base import check_finite_scalar
from jaxflex.plant import check_method, discretize, make_plant

CHART_FILE = "stability_chart.png"
JSON_FILE = "stability.json"
_MAX_N_TAU = 80  # chart rows at most; longer delay ranges are subsampled (whole samples)
# The chart's sampled-loop matrices carry every delay sample up to tau_max_s, and its grid
# is one batch: at 160 samples (tau = 20 ms, the default range 8 tau) it took 54 s and
# 4.5 GB on the 2-core machine, growing with the square of the range and beyond.
_MAX_CHART_SAMPLES = 160
# The first destabilising delay is recomputed with this many modes more: a crossing above the
# model's top mode moves with the modes left out (the paper's arm at k = 55: 7.315 ms with 2
# modes, 6.153 with 3, 6.338 from 6 on).
MORE_MODES = 4


def run(
    out_dir: str | os.PathLike,
    k: float = 55.0,
    tau_s: float = 0.005,
    n_modes: int = 2,
    *,
    dt: float = 1e-3,
    method: str = "zoh",
    k_range: tuple[float, float] | None = None,
    tau_max_s: float | None = None,
    n_k: int = 41,
    n_tau: int | None = None,
    n_cheb: int = st.DEFAULT_N_CHEB,
    beam_params: beam.BeamParams | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Stability of DFS ``u = -k (theta(t) - theta(t - tau))`` on the n-mode arm.

    Args:
      out_dir: output folder (created).
      k: DFS gain (N*m/rad), finite.
      tau_s: delay (s), > 0 and a whole number of samples of dt.
      n_modes: assumed modes, integer >= 1.
      dt: sample time of the sampled loop (s), > 0.
      method: discretisation of the sampled loop, ``"zoh"`` (default: exact for the held
        torque) or ``"rk4"`` (the paper's integrator); the other is reported alongside.
      k_range: (k_lo, k_hi) of the chart; default ``[0, 3 k]`` (``[3 k, 0]`` for k < 0,
        ``[0, 150]`` for k = 0).
      tau_max_s: largest delay of the chart (s), from ``tau_s`` to 160 samples of dt (its sampled-loop
        matrices grow with it); default ``min(max(8 tau, 40 ms, 20 dt), 160 dt)``.
      n_k: chart columns (>= 2).
      n_tau: chart rows (>= 2); default every sample up to tau_max_s, at most 80.
      n_cheb: Chebyshev intervals of the continuous-loop generator (>= 2): the chart's, and
        the first of the operating point's rightmost root, doubled until it converges
        (:func:`~jaxflex.analysis.stability.rightmost_root_converged`; ``rightmost_root`` in
        the JSON holds the intervals it took, and ``converged``).
      beam_params: the arm (plain numbers); ``None``: the paper's.
      progress: called with a short message before each stage, the last just before the
        files replace ``out_dir``'s: an exception it raises leaves ``out_dir`` as it was.

    Returns:
      The content of ``stability.json``.
    """
    say = progress or (lambda msg: None)
    k = st.check_gain(k)
    n_modes = beam.check_n_modes(n_modes)
    arm = beam.plain_params(beam.BeamParams() if beam_params is None else beam_params)
    dt = check_finite_scalar("dt", dt, positive=True)
    d = st.delay_steps_of(tau_s, dt)
    tau = float(tau_s)
    if d > _MAX_CHART_SAMPLES:  # no --tau-max can chart it (tau = 5 s, 5 ms typed without its unit, was sent to --tau-max)
        raise ValueError(
            f"tau_s must be at most {_MAX_CHART_SAMPLES} samples of dt = {dt:g} s, {_MAX_CHART_SAMPLES * dt:g} s, for the chart to hold it; "
            f"got {tau:g} s, {d} samples (tau_s is in seconds, 5 ms is 0.005; or a larger dt)"
        )
    check_method(method)
    n_k = checks.integer("n_k", n_k, 2)
    n_cheb = checks.integer("n_cheb", n_cheb, 2)
    if k_range is None:
        k_range = (0.0, 3 * k) if k > 0 else ((3 * k, 0.0) if k < 0 else (0.0, 150.0))
    k_lo, k_hi = (check_finite_scalar("k_range", v) for v in k_range)
    if not k_lo < k_hi:
        raise ValueError(f"k_range must be (k_lo, k_hi) with k_lo < k_hi; got {k_range}")
    # The default is capped at the chart's limit, which holds tau (checked above): 40 ms alone is
    # 400 samples at dt = 0.1 ms, and 8 tau was refused from tau = 21 samples on, a range never typed.
    limit = _MAX_CHART_SAMPLES * dt
    tau_max = min(max(8 * tau, 0.04, 20 * dt), limit) if tau_max_s is None else check_finite_scalar("tau_max_s", tau_max_s, positive=True)
    if tau_max < tau:
        raise ValueError(f"tau_max_s must be at least the delay analysed, tau_s = {tau:g} s, so that the chart holds that point; got {tau_max:g} s")
    d_max = int(math.floor(tau_max / dt + 1e-9))
    if d_max < 2:
        raise ValueError(f"tau_max_s must cover at least 2 samples of dt = {dt:g} s; got {tau_max:g} s")
    if d_max > _MAX_CHART_SAMPLES:
        raise ValueError(
            f"the chart's delay range tau_max_s = {tau_max:g} s is {d_max} samples of dt = {dt:g} s; at most "
            f"{_MAX_CHART_SAMPLES} are supported: pass tau_max_s (jaxflex stability --tau-max) from tau_s to {limit:g} s, "
            f"or leave it out (its default: the largest of 8 tau_s, 40 ms and 20 samples, at most {_MAX_CHART_SAMPLES} samples)"
        )
    n_tau = min(d_max, _MAX_N_TAU) if n_tau is None else min(checks.integer("n_tau", n_tau, 2), d_max)
    delay_grid = np.unique(np.round(np.linspace(1, d_max, n_tau)).astype(np.int64))
    k_grid = np.linspace(k_lo, k_hi, n_k)

    with jax.enable_x64(True):
        plant = make_plant(arm, n_modes)
        other = "rk4" if method == "zoh" else "zoh"
        dplant, dplant_other = (discretize(plant, dt, m, check_rk4=False) for m in (method, other))  # a growing RK4 map is reported as such

        say("critical delays")
        crit = st.critical_delays(plant, k, max(tau_max, 2 * tau))
        first = st.first_destabilising_delay(k, plant=plant, tau_max_s=max(1.0, 2 * tau_max))
        n_more = n_modes + MORE_MODES
        try:
            first_more, more_error = st.first_destabilising_delay(k, plant=make_plant(arm, n_more), tau_max_s=max(1.0, 2 * tau_max)), None
        except ValueError as err:  # beyond the modes whose characteristic polynomial float64 holds (17 on the paper's arm)
            first_more, more_error = None, str(err)

        say("rightmost root (Chebyshev collocation of the generator)")
        rightmost = st.rightmost_root_converged(plant, k, tau, n_cheb)
        root = rightmost.root
        validation = None
        if math.isfinite(first):
            below, above = (complex(st.rightmost_root(plant, k, first * f, rightmost.n_cheb)) for f in (0.99, 1.01))
            validation = {"tau_below_s": 0.99 * first, "rightmost_real_below": below.real, "tau_above_s": 1.01 * first, "rightmost_real_above": above.real}

        say("sampled loop")
        radius = float(st.spectral_radius(dplant, k, d))
        radius_other = float(st.spectral_radius(dplant_other, k, d))
        # the sampled loop's own first destabilising delay (whole samples up to the chart's
        # range): at 1 kHz it can lie well below the continuous loop's
        unstable = np.flatnonzero(np.asarray(st.sampled_radius_grid(dplant, [k], np.arange(1, d_max + 1)))[:, 0] >= 1)
        first_sampled = float((unstable[0] + 1) * dt) if unstable.size else None
        v = st.structural_directions(dplant)
        mat = np.asarray(st.sampled_loop_matrix(dplant, k, d))
        r_vec = np.concatenate([v, np.ones((d, 1)) * (np.asarray(dplant.C[:1]) @ v)])
        struct_residual = float(np.max(np.abs(mat @ r_vec - r_vec))) if v.shape[1] else None

        # the range sets the cost (160 samples: about a minute and 4.5 GB), so it is named before
        say(f"stability chart ({delay_grid.size} delays up to {d_max * dt:g} s, {d_max} samples of dt, x {n_k} gains; tau_max_s, jaxflex stability --tau-max, sets the range)")
        try:
            chart = st.stability_chart(plant, k_grid, delay_grid, dt, method, n_cheb)
        except ValueError as err:
            raise ValueError(f"the chart over k_range [{k_lo:g}, {k_hi:g}] (default [0, 3 k]): {err}") from None

    fig = plotting.stability_chart(
        chart.k, chart.tau_s, chart.spectral_radius, chart.rightmost_real, chart.first_destabilising_delay_s, point=(k, tau),
        title=f"DFS stability: {plotting.arm_label(arm.length_m, beam.natural_frequencies_hz(arm, n_modes))}, sampled at {dt * 1e3:g} ms ({method})",
    )
    result = {
        "k": k,
        "tau_s": tau,
        "delay_steps": d,
        "n_modes": n_modes,
        "beam": arm._asdict(),
        "dt": dt,
        "method": method,
        "crossings": [
            {"freq_hz": c.freq_hz, "omega_rad_s": c.omega, "beta_rad": c.beta, "tau_s": c.tau_s, "re_dsdtau": c.re_dsdtau, "direction": c.direction}
            for c in crit.crossings
        ],
        "crossings_tau_max_s": crit.tau_max_s,
        "zero_crossing": None if crit.zero_crossing is None else crit.zero_crossing._asdict(),
        "first_destabilising_delay_s": first,
        "first_destabilising_validation": validation,
        # s null: no destabilising delay; error: why none was computed (the larger model's
        # characteristic polynomial overflows float64)
        "first_destabilising_delay_more_modes": {"n_modes": n_more, "s": first_more, "error": more_error},
        "first_destabilising_delay_sampled_s": first_sampled,
        "first_destabilising_delay_sampled_tau_max_s": d_max * dt,
        "spectral_radius": radius,
        f"spectral_radius_{other}": radius_other,
        "stable_sampled": radius < 1,
        "rightmost_root": {
            "real": root.real,
            "imag": root.imag,
            "freq_hz": abs(root.imag) / (2 * math.pi),
            "n_cheb": rightmost.n_cheb,
            "change_from_half_n_cheb": rightmost.change,
            "converged": rightmost.converged,
        },
        "stable_continuous": root.real < 0,
        "exp_dt_rightmost_real": math.exp(dt * root.real),
        "excluded_structural": {
            **crit.structural,
            "directions": st.structural_directions(plant).T,
            "continuous": "root s = 0 of Delta(s, tau) (eigenvector: constant history of a structural direction), deflated",
            "sampled": "eigenvalue z = 1 of the sampled loop (eigenvector [v, c v, ..., c v]), deflated",
            "sampled_eigvec_residual": struct_residual,
        },
        "chart": {
            "file": CHART_FILE,
            "k_range": [float(k_grid[0]), float(k_grid[-1])],
            "n_k": int(k_grid.size),
            "tau_range_s": [float(chart.tau_s[0]), float(chart.tau_s[-1])],
            "n_tau": int(chart.tau_s.size),
            "stable_fraction_sampled": float(np.mean(chart.spectral_radius < 1)),
            "stable_fraction_continuous": float(np.mean(chart.rightmost_real < 0)),
        },
        "jaxflex_version": getattr(jaxflex, "__version__", None),
        "jax_version": jax.__version__,
    }
    result = fileio.to_jsonable(result)
    # Both files replace an earlier run's together: an interrupted run leaves the old pair.
    with fileio.replace_outputs(out_dir, (CHART_FILE, JSON_FILE), last=JSON_FILE) as stage:
        plotting.save(fig, os.path.join(stage, CHART_FILE))
        fileio.write_json(os.path.join(stage, JSON_FILE), result)
        say(f"writing the files into {out_dir}")
    return result
