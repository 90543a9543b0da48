"""Reproduction of the paper: its three runs, figures, a side-by-side report and results.json.

``reproduce(out_dir)`` simulates, from the paper's scenario (3 s at 1 kHz, RK4 with the
torque held over each sample): the open loop, DFS (k = 55, tau = 5 ms) and the PD-type fuzzy
controller (k1 = 1.02, k2 = 0.30, k3 = 1.0, Mamdani centroid). It writes the paper's figures,
``report.md`` with every number the paper reports beside jaxflex's, and ``results.json``.
The files are renamed over the folder's at the end (``results.json`` last), so a run
interrupted before that leaves the folder as it was.
"""

from __future__ import annotations

import json
import math
import os
import platform
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxflex
from jaxflex import beam, checks, fileio, plotting
from jaxflex.analysis import PSDSettings, region_reduction_db, signal_metrics, samples_at, vibration_reduction_db, welch
from jaxflex.analysis.metrics import RUN_DIVERGED_DOC, diverged, run_diverged
from jaxflex.controllers import by_name
from jaxflex.controllers.base import same_dt
from jaxflex.controllers.dfs import CAPACITY_REMEDY
from jaxflex.controllers.fuzzy import PAPER_RULES, check_temperature, fuzzy_params, fuzzy_surface
from jaxflex.controllers.registry import PAPER_PARAMS, PARAMETERS
from jaxflex.plant import check_method, discretize, make_plant, rk4_amplified_omega
from jaxflex.rollout import rollout
from jaxflex.scenarios import paper_scenario

DT = 1e-3
HORIZON_S = 3.0
SAMPLE_TIMES_S = (0.1, 0.5, 1.0)
RUNS = ("open_loop", "dfs", "fuzzy")
TUNED_CONTROLLERS = ("dfs", "fuzzy", "dfs+fuzzy")

# What the paper reports (Ahmad, Nasir and Hambali, ISMA'09: its text and figures 5-8).
PAPER = {
    "natural_frequencies_hz": [16.0, 55.0],
    "open_loop_range_m": [-0.03, 0.03],
    "dfs": {"settling_time_s": 0.25, "min": -0.010, "max": 0.027, "reduction_db": [123.36, 66.94]},
    "fuzzy": {"settling_time_s": 0.25, "min": -0.006, "max": 0.025, "reduction_db": [102.24, 23.19]},
}

# PSD estimators: the first is the default behind results.json's vibration_reduction_db; the
# others show how strongly the dB figures depend on the window and the segment length.
ESTIMATORS = {
    "hann-1024": PSDSettings(window="hann", nperseg=1024, noverlap=512, detrend="constant"),
    "hann-256": PSDSettings(window="hann", nperseg=256, noverlap=128, detrend="constant"),
    "hann-3000": PSDSettings(window="hann", nperseg=3000, noverlap=0, detrend="constant"),
    "boxcar-3000": PSDSettings(window="boxcar", nperseg=3000, noverlap=0, detrend="constant"),
}
REL_BAND = 0.15


def _run_metrics(traj, dt: float) -> dict[str, Any]:
    """A run on the paper's arm: ``diverged`` is ``run_diverged``."""
    signals = {"q1": traj.x[:, 1], "tip_deflection_m": traj.z[:, 1], "hub_angle_rad": traj.z[:, 0]}
    metrics = {name: signal_metrics(s, dt) for name, s in signals.items()}
    tip = metrics["tip_deflection_m"]  # its peak |tip| is max(-min, max)
    is_diverged = bool(run_diverged(diverged(traj.x), jnp.maximum(-tip.min, tip.max), beam.BeamParams().length_m))
    out: dict[str, Any] = {"diverged": is_diverged}
    for name, m in metrics.items():
        values = {k: fileio.shortest(getattr(m, k)) for k in ("min", "max", "settling_time_s", "ise", "iae")}
        out[name] = {k: None for k in values} if is_diverged else values
    out["samples"] = {name: fileio.shortest(samples_at(signals[name], dt, SAMPLE_TIMES_S)) for name in ("q1", "hub_angle_rad")}
    out["samples"]["t_s"] = list(SAMPLE_TIMES_S)
    out["control_effort"] = fileio.shortest(jnp.sum(traj.u**2) * dt)
    return out


def _paper_gains(name: str) -> dict[str, float]:
    """The paper's values of the parameters controller ``name`` uses, by name."""
    return {key: PAPER_PARAMS[key] for key in PARAMETERS[name]}


def moved_peaks(results: dict[str, Any]) -> list[str]:
    """One sentence per mode whose closed-loop peak lies outside the +-REL_BAND band that the
    paper's reduction reads (``results["region_reduction_db"]``; none without it): report.md
    and the command's summary say it."""
    region = results.get("region_reduction_db", {})
    frequencies = results["model"]["natural_frequencies_hz"]
    return [f"{plotting.LABELS[run]} moves mode {m + 1}'s resonance from {f:.2f} to {f_at:.1f} Hz, where it is {abs(db):.1f} dB {'below' if db >= 0 else 'above'} the open-loop peak "
            f"(the open-loop peak's bin gives {results['vibration_reduction_db'][run][m]:.1f} dB)"
            for run in region for m, (f, f_at, db, peak) in enumerate(zip(frequencies, region[run]["closed_loop_highest_hz"], region[run]["db"], region[run]["is_peak"]))
            if peak and abs(f_at - f) > REL_BAND * f]


def format_value(v: Any, spec: str = ".4g") -> str:
    """``v`` formatted with ``spec``; ``n/a`` for a missing (diverged run) or non-finite value."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    return format(v, spec)


def _settling(v: float | None) -> str:
    """A settling time for the report: +inf (still outside the band at the end) is said so,
    rather than shown as the ``n/a`` of a diverged run."""
    return "not settled" if v == math.inf else f"{format_value(v, '.3f')} s"


def _report_md(results: dict[str, Any]) -> str:
    model = results["model"]
    runs = results["runs"]
    dfs, fz = results["controllers"]["dfs"], results["controllers"]["fuzzy"]
    n = model["n_modes"]
    lines = [
        "# jaxflex reproduction of Ahmad, Nasir & Hambali (ISMA'09)",
        "",
        f"Command: `jaxflex reproduce --modes {n}{' --x64' if model['dtype'] == 'float64' else ''}"
        f"{' --params ' + results['tuned']['file'] if results.get('tuned') else ''}`. jaxflex {results['versions']['jaxflex']}, "
        f"JAX {results['versions']['jax']}, {model['dtype']}, device {results['versions']['device']}.",
        f"Setting: {n}-mode assumed-mode model, RK4 at {1 / DT:g} Hz with the torque held over each sample, "
        f"{HORIZON_S:g} s, the paper's initial condition read in its printed order "
        "(q1(0) = 1e-3 m, q1_dot(0) = 1e-5 m/s). Rayleigh damping: 1 % in both flexible modes of the 2-mode model "
        f"(alpha = {model['rayleigh_alpha']:.4g} 1/s, beta = {model['rayleigh_beta']:.4g} s; the paper gives no values); "
        f"its alpha M term also damps the hub's rigid rotation, like viscous hub friction (a real pole at -alpha = {-model['rayleigh_alpha']:.4g} 1/s).",
        f"Controllers, with the paper's gains: DFS u = -k (theta(t) - theta(t - tau)), k = {dfs['k']:g} N*m/rad, tau = {dfs['tau_s'] * 1e3:g} ms "
        "(the sign of the paper's eqs. (9)-(10) and final controller; its eq. (8) prints +, which is unstable); PD-type fuzzy "
        f"k1 = {fz['k1']:g}, k2 = {fz['k2']:g}, k3 = {fz['k3']:g}, the paper's {len(PAPER_RULES)} rules and set centres, {fz['defuzz']} defuzzification.",
        "",
        "## Where the model and the paper differ, in short",
        "",
        "- **Natural frequencies.** The paper's parameters cannot give 16 and 55 Hz: for this beam the first flexible "
        f"frequency cannot exceed the pinned-free value ({model['pinned_free_bound_hz']:.2f} Hz) whatever the hub inertia. "
        "jaxflex reports its own frequencies, checked against the exact hub-beam frequency equation, and does not bend the physics.",
        "- **Amplitudes.** The paper's 'modal displacement' of about +-0.03 m cannot come from a 1 mm initial modal "
        "displacement with this normalisation (|phi_i(L)| = 2); the paper does not say which signal or normalisation it plots. "
        "jaxflex shows q1 (m) and the elastic tip deflection (m).",
        "- **dB reductions.** The paper does not state its PSD estimator. Ratios of PSDs of a decaying transient move by "
        "tens of dB with the window and the segment length (table below), so only the sign is comparable, and an ordering only "
        "where it holds under every estimator below (a single frequency bin can carry it: a narrow dip of one PSD on the bin at the mode).",
        "",
        "## Natural frequencies (Hz)",
        "",
        f"| mode | paper | jaxflex, {n}-mode model | its damping ratio | exact hub-beam equation | note |",
        "|---|---|---|---|---|---|",
    ]
    for i in range(max(n, 2)):
        paper = PAPER["natural_frequencies_hz"][i] if i < 2 else None
        amm = model["natural_frequencies_hz"][i] if i < n else None
        zeta = model["damping_ratios"][i] if i < n else None
        exact = model["exact_natural_frequencies_hz"][i] if i < len(model["exact_natural_frequencies_hz"]) else None
        note = "differs: the paper's is above the pinned-free bound" if (paper is not None and i == 0) else ("differs" if paper is not None else "")
        if i == 0 and amm is not None and amm > model["pinned_free_bound_hz"]:  # one assumed mode: the model's too, from above
            note += f"; the {n}-mode model's too: assumed-mode frequencies converge to the exact ones from above"
        if amm is None:
            note = f"not in the {n}-mode model"
        lines.append(f"| {i + 1} | {format_value(paper)} | {format_value(amm, '.3f')} | {format_value(zeta, '.3g')} | {format_value(exact, '.3f')} | {note} |")

    lines += ["", "## Time responses", "", "| run | quantity | paper | jaxflex q1 (m) | jaxflex tip deflection (m) | note |", "|---|---|---|---|---|---|"]
    ol = runs["open_loop"]
    lines.append(
        f"| open loop | range | {PAPER['open_loop_range_m'][0]} .. {PAPER['open_loop_range_m'][1]} m | "
        f"{format_value(ol['q1']['min'])} .. {format_value(ol['q1']['max'])} | {format_value(ol['tip_deflection_m']['min'])} .. {format_value(ol['tip_deflection_m']['max'])} | "
        "differs: signal and normalisation unstated in the paper |"
    )
    for run in ("dfs", "fuzzy"):
        r, p = runs[run], PAPER[run]
        label = plotting.LABELS[run]
        if r["diverged"]:
            lines.append(f"| {label} | all | | diverged | diverged | the closed loop diverged |")
            continue
        lines.append(
            f"| {label} | settling time | {p['settling_time_s']} s | {_settling(r['q1']['settling_time_s'])} | "
            f"{_settling(r['tip_deflection_m']['settling_time_s'])} | stays within 2 % of its peak deviation from the final value (mean of the last 10 %) |"
        )
        lines.append(
            f"| {label} | range | {p['min']} .. {p['max']} m | {format_value(r['q1']['min'])} .. {format_value(r['q1']['max'])} | "
            f"{format_value(r['tip_deflection_m']['min'])} .. {format_value(r['tip_deflection_m']['max'])} | differs in scale, as the open loop |"
        )

    names = list(results["vibration_reduction_db_by_estimator"])
    lines += [
        "",
        "## Level of vibration reduction at the natural frequencies (dB)",
        "",
        "10 log10 of the open-loop over the closed-loop PSD of the tip deflection, at the bin where the open-loop PSD peaks "
        f"within +-{REL_BAND:.0%} of each model frequency. Default estimator: {names[0]} (Welch, {results['psd']['window']} window, "
        f"{results['psd']['nperseg']}-sample segments, {results['psd']['noverlap']} overlap, mean detrend, fs = {results['psd']['fs_hz']:g} Hz).",
        "",
        "The last column sets the same open-loop peak against the closed loop's highest PSD anywhere in the mode's region "
        "(between the geometric midpoints with the neighbouring modes; from half the first mode's frequency, to twice the last's), "
        "with that bin's frequency, and whether it is a peak or the skirt of a peak beyond the region: a loop that moves a resonance leaves its new peak off the open loop's bin.",
        "",
        "| controller | mode | paper | " + " | ".join(f"jaxflex {name}" for name in names) + " | jaxflex q1, " + names[0] + " | least over the region, " + names[0] + " |",
        "|---|---|---|" + "---|" * len(names) + "---|---|",
    ]
    region = results["region_reduction_db"]
    for run in ("dfs", "fuzzy"):
        for m in range(len(results["vibration_reduction_db"][run])):
            vals = " | ".join(format_value(results["vibration_reduction_db_by_estimator"][name][run][m], ".1f") for name in names)
            q1 = format_value(results["vibration_reduction_db_q1"][run][m], ".1f")
            paper = PAPER[run]["reduction_db"][m] if m < len(PAPER[run]["reduction_db"]) else "-"
            f_at = region[run]["closed_loop_highest_hz"][m]  # None for a diverged run
            where = "" if f_at is None else f" (a peak at {f_at:.1f} Hz)" if region[run]["is_peak"][m] else f" (at {f_at:.1f} Hz, a skirt)"
            least = format_value(region[run]["db"][m], ".1f") + where
            lines.append(f"| {plotting.LABELS[run]} | {m + 1} | {paper} | {vals} | {q1} | {least} |")
    # the paper compares its two modes; a third model mode is shown but not compared
    n_compared = len(PAPER["dfs"]["reduction_db"])
    dfs_db, fz_db = (results["vibration_reduction_db"][run][:n_compared] for run in ("dfs", "fuzzy"))
    ordering = "agrees" if all(a is not None and b is not None and a > b for a, b in zip(dfs_db, fz_db)) else "does not agree"
    compared = "at both modes" if len(dfs_db) >= 2 else "at mode 1 (the only mode of this 1-mode model; the paper also compares mode 2)"
    by_estimator = []
    for name in names:
        table = results["vibration_reduction_db_by_estimator"][name]
        ahead = [m + 1 for m, (a, b) in enumerate(zip(table["dfs"][:n_compared], table["fuzzy"][:n_compared])) if a is not None and b is not None and a > b]
        by_estimator.append(f"{name} at {'mode' if len(ahead) == 1 else 'modes'} {', '.join(map(str, ahead))}" if ahead else f"{name} at no mode")
    lines += [
        "",
        f"The paper's conclusion that DFS reduces vibration more than the fuzzy controller {compared} {ordering} "
        f"with jaxflex's default estimator. Comparing {'mode 1 (the paper compares modes 1-2)' if len(dfs_db) == 1 else f'modes 1-{len(dfs_db)}, as the paper does'}, "
        f"DFS is ahead, by estimator: {'; '.join(by_estimator)}.",
    ]
    if moved := moved_peaks(results):  # DFS moves the 4-mode model's mode 3 from 64.8 to 81 Hz: 67.2 dB at the open-loop bin, 10.0 at the new peak
        lines += ["", f"A closed-loop peak outside a mode's +-{REL_BAND:.0%} band is missed by the reduction at the open-loop peak's bin: {'; '.join(moved)}."]
    amplified = [f"{plotting.LABELS[run]} at mode {m + 1} (by {-v:.1f} dB)" for run in ("dfs", "fuzzy") for m, v in enumerate(results["vibration_reduction_db"][run]) if v is not None and v < 0]
    if amplified:  # DFS at mode 4 of a 4-mode model: -16.5 dB, not a word
        lines += ["", f"A negative reduction is an amplification, the closed loop raising the vibration; with the default estimator: {', '.join(amplified)}."]
    lines += [
        "",
        "## Figures",
        "",
    ]
    lines += [f"- `{name}`: {caption}" for name, caption in FIGURES.items()]
    tuned = results.get("tuned")
    if tuned:
        run = tuned["run"]
        lines += [
            f"- `{TUNED_FIGURE}`: q1 and tip deflection, tuned {tuned['controller']} beside the paper's gains",
            "",
            f"## Tuned gains ({tuned['controller']}) beside the paper's, on the paper scenario",
            "",
        ]
        if tuned["tuned_for"]:
            lines += [f"These gains were tuned for {', '.join(tuned['tuned_for'])}; they are shown here on the paper's arm, model and sampling.", ""]
        if tuned["kept_start"]:
            lines += [f"{KEPT_START}.", ""]
        if run["diverged"]:
            lines += ["**The tuned gains' closed loop diverged on this scenario.**", ""]
        lines += ["| | parameters | q1 settling | tip range (m) | tip ISE (m^2 s) |", "|---|---|---|---|---|"]
        lines += [f"| {' | '.join(row)} |" for row in tuned_comparison(tuned)]
    return "\n".join(lines) + "\n"


class TunedRow(NamedTuple):
    """One row of ``tuned_comparison``, each cell formatted."""

    label: str
    gains: str
    q1_settling: str
    tip_range: str  # m
    tip_ise: str  # m^2 s


def tuned_comparison(tuned: dict[str, Any]) -> list[TunedRow]:
    """The paper's gains and the tuned ones on the paper scenario, as report.md's table and
    ``jaxflex reproduce --params``' printout give them: the "paper" row, then the "tuned" one,
    "diverged" in every cell of a diverged run."""
    rows = []
    for label, params, run in (("paper", tuned["paper_params"], tuned["paper_run"]), ("tuned", tuned["params"], tuned["run"])):
        gains = ", ".join(f"{k} = {v:.4g}" for k, v in params.items() if isinstance(v, float))
        if run["diverged"]:
            rows.append(TunedRow(label, gains, "diverged", "diverged", "diverged"))
            continue
        tip = run["tip_deflection_m"]
        rows.append(TunedRow(label, gains, _settling(run["q1"]["settling_time_s"]), f"{format_value(tip['min'])} .. {format_value(tip['max'])}", format_value(tip["ise"])))
    return rows


TUNED_FIGURE = "fig_tuned_response.png"  # with --params only
# a tuned row equal to the paper's read as a tuned result when the run started from the paper's gains
KEPT_START = "jaxflex tune kept the gains it started from: no update improved its held-out objective"
FIGURES = {
    "fig4_fuzzy_surface.png": "control surface of the fuzzy controller over the normalised (angle, velocity) square (paper Fig. 4)",
    "fig5_dfs_response.png": "q1 and tip deflection, DFS against open loop, and beside them the stretch in which DFS settles (paper Fig. 5)",
    "fig6_dfs_psd.png": "PSD of the tip deflection, DFS against open loop, on fig8's scale (paper Fig. 6)",
    "fig7_fuzzy_response.png": "q1 and tip deflection, PD-fuzzy against open loop, and beside them the stretch in which PD-fuzzy settles (paper Fig. 7)",
    "fig8_fuzzy_psd.png": "PSD of the tip deflection, PD-fuzzy against open loop, on fig6's scale (paper Fig. 8)",
    "fig9_reduction.png": "vibration reduction in dB at each mode, per PSD estimator, beside the paper's (paper Fig. 9)",
}


class Tuned(NamedTuple):
    """A tuned.json from ``jaxflex tune``, read back (see ``load_tuned``).

    Attributes:
      name: the controller's name, one of TUNED_CONTROLLERS.
      named: the parameters by name (k, tau_s, k1, k2, k3).
      options: how the run built the controller, under its config's keys (``CONFIG_OPTIONS``:
        ``capacity``, ``delay``, ``pade_order`` and ``fuzzy_temperature``).
      beam: the arm it was tuned for (the run's ``[beam]``; the paper's when absent).
      dt: the run's sample time (s; its ``[scenarios]`` dt, the paper's 1 ms when absent).
      n_modes, method: the plant model it was tuned on (default 2 modes, ``"rk4"``).
      best_step: the update after which the run's held-out objective was best: 0 when no
        update improved on the starting gains, which the run then kept (None when the file
        does not say).
    """

    name: str
    named: dict[str, float]
    options: dict[str, Any]
    beam: beam.BeamParams
    dt: float
    n_modes: int = 2
    method: str = "rk4"
    best_step: int | None = None

    @property
    def kept_start(self) -> bool:
        """Whether the run kept the gains it started from (``best_step`` 0: ``KEPT_START``)."""
        return self.best_step == 0

    def build(self, dt: float) -> tuple[Any, Any]:
        """The controller as it was tuned, for a loop sampled every ``dt`` seconds, and its
        checked parameters.

        Raises:
          ValueError: when a parameter is out of range at this ``dt`` (a tuned delay longer
            than the buffer's ``capacity`` samples of ``dt``).
        """
        opts = self.options
        controller, params = by_name(
            self.name, dt=dt, params=self.named, capacity=opts["capacity"], delay=opts["delay"], pade_order=opts["pade_order"], temperature=opts["fuzzy_temperature"]
        )
        try:
            controller.check(params)
        except ValueError as err:
            # reproduce has no capacity option: name where these gains' buffer is set
            err = str(err).replace(CAPACITY_REMEDY, f"The buffer is the capacity in the tuned.json's config ({opts['capacity']} samples), which its tune run set.")
            raise ValueError(err if same_dt(self.dt, dt) else f"tuned at dt = {self.dt:g} s, run at dt = {dt:g} s: {err}") from None
        return controller, params

    def differences(self, arm: beam.BeamParams, n_modes: int, dt: float, method: str) -> list[str]:
        """How the model these gains were tuned on differs from ``arm`` with ``n_modes`` modes
        sampled by ``method`` every ``dt`` s: one phrase per difference (empty when they
        agree), e.g. "another arm (length_m = 1.2)" for the tuned arm's own values."""
        other = [f"{k} = {'derived' if v is None else f'{v:g}'}" for k, v in self.beam._asdict().items() if v != getattr(arm, k)]
        out = [f"another arm ({', '.join(other)})"] if other else []
        if self.n_modes != n_modes:
            out.append(f"{self.n_modes} modes (here {n_modes})")
        if not same_dt(self.dt, dt):
            out.append(f"dt = {self.dt:g} s (here {dt:g} s)")
        if self.method != method:
            out.append(f"method = '{self.method}' (here '{method}')")
        return out


def load_tuned(path: str | os.PathLike) -> Tuned:
    """Read tuned.json from ``jaxflex tune``: the controller's name, parameters and options
    (delay approximation, buffer capacity, fuzzy temperature), its arm and its sample time.

    Raises:
      ValueError: naming what is missing or out of range (the parameters are checked at the
        run's own sample time).
    """
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError) as err:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        inside = os.path.join(path, "tuned.json")
        hint = f" (the tune run's folder: pass {inside})" if os.path.isdir(path) and os.path.isfile(inside) else ""
        raise ValueError(f"--params: cannot read {path} as tuned.json: {err}{hint}") from None
    if isinstance(data, dict) and "metrics" in data and "n_scenarios" in data:
        # its params are the gains it simulated, without the model they were tuned on
        raise ValueError(f"--params: {path} is a jaxflex montecarlo summary.json; pass the tuned.json that jaxflex tune wrote")
    name = data.get("controller") if isinstance(data, dict) else None
    named = data.get("params") if isinstance(data, dict) else None
    if name not in TUNED_CONTROLLERS or not isinstance(named, dict):
        raise ValueError(f"--params: {path} must hold 'controller' (one of {TUNED_CONTROLLERS}) and 'params'")
    config = data.get("config", {}) if isinstance(data.get("config"), dict) else {}
    needed = PARAMETERS[name]
    missing = [n for n in needed if isinstance(named.get(n), bool) or not isinstance(named.get(n), (int, float))]
    if missing:
        raise ValueError(f"--params: {path} lacks numeric parameter(s) {missing} for {name}")
    values = {n: float(named[n]) for n in needed}
    options = {
        "capacity": checks.integer(f"--params: {path}'s capacity", config.get("capacity", 64)),
        "delay": config.get("delay", "linear"),
        "pade_order": checks.integer(f"--params: {path}'s pade_order", config.get("pade_order", 8)),
        "fuzzy_temperature": check_temperature(config.get("fuzzy_temperature", 0.0), f"--params: {path}'s fuzzy_temperature"),
    }
    table = config.get("scenarios", {})
    dt = checks.number(f"--params: {path}'s scenarios.dt", table.get("dt", DT) if isinstance(table, dict) else table, strict=True)
    n_modes = checks.integer(f"--params: {path}'s n_modes", config.get("n_modes", 2))
    method = config.get("method", "rk4")
    check_method(method, f"--params: {path}'s method")
    best_step = data.get("best_step")
    best_step = None if best_step is None else checks.integer(f"--params: {path}'s best_step", best_step, low=0)
    arm = config.get("beam", {})
    try:
        tuned_beam = beam.params_from_mapping({k: v for k, v in arm.items() if v is not None} if isinstance(arm, dict) else arm)
        tuned = Tuned(name, values, options, tuned_beam, dt, n_modes, method, best_step)
        tuned.build(dt)
    except ValueError as err:
        raise ValueError(f"--params: {path}: {err}") from None
    return tuned


def reproduce(out_dir: str | os.PathLike, n_modes: int = 2, progress: Callable[[str], None] | None = None, params_file: str | os.PathLike | None = None) -> dict[str, Any]:
    """Run the paper's study and write figures, report.md and results.json into ``out_dir``.

    Args:
      out_dir: output folder (created if missing).
      n_modes: number of assumed modes (int >= 1; the paper uses 2).
      progress: called with a short message before each stage (e.g. ``print``), the last
        just before the files replace ``out_dir``'s: an exception it raises (the CLI raises
        a Ctrl-C that Python dropped) leaves ``out_dir`` as it was.
      params_file: tuned.json from ``jaxflex tune``; its gains are simulated on the paper
        scenario too and shown beside the paper's (table, figure, ``results.json["tuned"]``).

    Returns:
      The results dictionary written to results.json.
    """
    n_modes = beam.check_n_modes(n_modes)
    fastest = rk4_amplified_omega(make_plant(beam.BeamParams(), n_modes), DT)
    if fastest is not None:
        held = next(m for m in range(1, n_modes + 1) if rk4_amplified_omega(make_plant(beam.BeamParams(), m), DT) is not None) - 1  # the fastest pole grows with the modes
        raise ValueError(
            f"n_modes = {n_modes} (--modes): the paper's integrator, RK4 at {DT:g} s, amplifies the plant's pole at |s| = 2 pi x {fastest / (2 * np.pi):.4g} Hz "
            f"(omega dt = {fastest * DT:.3g}; RK4 holds up to about 2.8), so the runs would blow up. reproduce takes n_modes <= {held}; "
            "tune and montecarlo take more with method = 'zoh'"
        )
    tuned = load_tuned(params_file) if params_file is not None else None
    if tuned is not None:
        try:
            tuned_controller, tuned_params = tuned.build(DT)
        except ValueError as err:
            raise ValueError(f"--params: {params_file} cannot run on the paper's scenario (dt = {DT:g} s): {err}") from None
    say = progress or (lambda msg: None)
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    dtype = jnp.zeros(()).dtype
    params = beam.BeamParams(*(None if v is None else jnp.asarray(v, dtype) for v in beam.BeamParams()))

    say(f"building the {n_modes}-mode model")
    plant = discretize(make_plant(params, n_modes), DT, "rk4")
    freqs_model = np.asarray(beam.natural_frequencies_hz(params, n_modes))  # in the run's dtype
    freqs_exact = beam.exact_natural_frequencies_hz(beam.BeamParams(), max(n_modes, 2))
    pinned_free = beam.exact_natural_frequencies_hz(beam.BeamParams(hub_inertia_kg_m2=1e-12), 1)[0]
    alpha, beta = beam.rayleigh_coefficients(params)
    scenario = paper_scenario(plant, HORIZON_S, DT)

    simulate = jax.jit(rollout, static_argnums=1)
    trajectories, runs = {}, {}
    for name in RUNS:
        controller, cparams = by_name(name, dt=DT)  # the paper's gains
        say(f"simulating {plotting.LABELS[name]}")
        traj = jax.block_until_ready(simulate(plant, controller, cparams, scenario))
        trajectories[name] = traj
        runs[name] = _run_metrics(traj, DT)

    tuned_results = None
    if tuned is not None:
        say(f"simulating tuned {tuned.name}")
        ttraj = jax.block_until_ready(simulate(plant, tuned_controller, tuned_params, scenario))
        if tuned.name in runs:  # the paper's own run of this controller
            paper_traj, paper_run = trajectories[tuned.name], runs[tuned.name]
        else:  # dfs+fuzzy, which the paper does not run: the paper's gains in the same loop
            say(f"simulating {plotting.LABELS[tuned.name]} with the paper's gains")
            controller, cparams = by_name(tuned.name, dt=DT)
            paper_traj = jax.block_until_ready(simulate(plant, controller, cparams, scenario))
            paper_run = _run_metrics(paper_traj, DT)
        tuned_results = {
            "controller": tuned.name,
            "file": os.fspath(params_file),
            "params": tuned.named,
            "paper_params": _paper_gains(tuned.name),
            "paper_run": paper_run,
            "beam": tuned.beam._asdict(),
            "tuned_for": tuned.differences(beam.BeamParams(), n_modes, DT, "rk4"),
            "kept_start": tuned.kept_start,
            "run": _run_metrics(ttraj, DT),
        }

    say("estimating PSDs")
    mode_freqs = freqs_model.astype(float)
    by_estimator: dict[str, dict[str, list[float]]] = {}
    psd_curves: dict[str, dict[str, np.ndarray]] = {}
    for est_name, settings in ESTIMATORS.items():
        psd = {name: welch(tr.z[:, 1], 1 / DT, settings=settings) for name, tr in trajectories.items()}
        f = np.asarray(psd["open_loop"][0])
        if est_name == next(iter(ESTIMATORS)):
            psd_curves = {name: np.asarray(p[1]) for name, p in psd.items()}
            freqs_psd = f
        by_estimator[est_name] = {
            run: [None if runs[run]["diverged"] else fileio.shortest(v) for v in vibration_reduction_db(f, psd["open_loop"][1], psd[run][1], mode_freqs, REL_BAND)]
            for run in ("dfs", "fuzzy")
        }
    region_reduction = {}  # where the closed loop moved a resonance, the paper's bin misses its new peak
    for run in ("dfs", "fuzzy"):
        if runs[run]["diverged"]:
            region_reduction[run] = {"db": [None] * n_modes, "closed_loop_highest_hz": [None] * n_modes, "is_peak": [None] * n_modes}
        else:
            region = region_reduction_db(freqs_psd, psd_curves["open_loop"], psd_curves[run], mode_freqs, REL_BAND)
            region_reduction[run] = {"db": fileio.shortest(region.db), "closed_loop_highest_hz": fileio.shortest(region.f_closed_hz), "is_peak": region.is_peak.tolist()}
    default = ESTIMATORS[next(iter(ESTIMATORS))]
    f_q1, psd_q1_open = welch(trajectories["open_loop"].x[:, 1], 1 / DT, settings=default)
    reduction_q1 = {
        run: [None if runs[run]["diverged"] else fileio.shortest(v) for v in vibration_reduction_db(f_q1, psd_q1_open, welch(trajectories[run].x[:, 1], 1 / DT, settings=default)[1], mode_freqs, REL_BAND)]
        for run in ("dfs", "fuzzy")
    }

    results: dict[str, Any] = {
        "model": {
            "n_modes": n_modes,
            "natural_frequencies_hz": fileio.shortest(freqs_model),
            "exact_natural_frequencies_hz": fileio.shortest(freqs_exact[: max(n_modes, 2)]),
            "pinned_free_bound_hz": fileio.shortest(pinned_free),
            "paper_natural_frequencies_hz": PAPER["natural_frequencies_hz"],
            "rayleigh_alpha": fileio.shortest(alpha),
            "rayleigh_beta": fileio.shortest(beta),
            # each flexible mode's own ratio under alpha M + beta K (1 % only in the 2-mode model's two)
            "damping_ratios": fileio.shortest(np.asarray(beam.modal_damping_ratios(params, freqs_model))),
            "dt_s": DT,
            "horizon_s": HORIZON_S,
            "integrator": "rk4",
            "scenario": "paper (printed reading)",
            "dtype": str(dtype),
        },
        "runs": runs,
        "diverged_definition": RUN_DIVERGED_DOC,
        "controllers": {"dfs": _paper_gains("dfs"), "fuzzy": {**_paper_gains("fuzzy"), "defuzz": "centroid"}},
        "vibration_reduction_db": by_estimator[next(iter(ESTIMATORS))],
        "vibration_reduction_db_by_estimator": by_estimator,
        "vibration_reduction_db_q1": reduction_q1,
        "region_reduction_db": region_reduction,
        "psd": {**default.to_dict(), "name": next(iter(ESTIMATORS)), "fs_hz": 1 / DT, "signal": "tip_deflection_m", "scaling": "density, one-sided", "rel_band": REL_BAND},
        "paper": PAPER,
        "tuned": tuned_results,
        "versions": {"jaxflex": jaxflex.__version__, "jax": jax.__version__, "python": platform.python_version(), "device": jax.devices()[0].device_kind},
    }

    say("drawing figures")
    # Renamed into place at the end: Ctrl-C leaves the folder as it was, and a figure of an
    # earlier run with other options (fig_tuned_response.png) does not survive beside these.
    with fileio.replace_outputs(out_dir, [*FIGURES, TUNED_FIGURE, "report.md", "results.json"], last="results.json") as stage:
        t = np.asarray(trajectories["open_loop"].t)
        div = {name: r["diverged"] for name, r in runs.items()}
        signals = lambda tr: {"q1": np.asarray(tr.x[:, 1]), "tip": np.asarray(tr.z[:, 1])}
        sig = {name: signals(tr) for name, tr in trajectories.items()}
        panels = [("q1", "q1 (m)"), ("tip", "Tip deflection (m)")]
        # fig6 and fig8 on one scale, to be read side by side (a non-finite curve is not drawn)
        shared = plotting.psd_limits(freqs_psd, [c for name, c in psd_curves.items() if name in ("open_loop", "dfs", "fuzzy") and np.all(np.isfinite(c))], mode_freqs)
        for run, resp, psdfig in (("dfs", "fig5_dfs_response.png", "fig6_dfs_psd.png"), ("fuzzy", "fig7_fuzzy_response.png", "fig8_fuzzy_psd.png")):
            label = plotting.LABELS[run]
            pair = {"open_loop": sig["open_loop"], run: sig[run]}
            settled = {run: {"q1": runs[run]["q1"]["settling_time_s"]}} if runs[run]["q1"]["settling_time_s"] is not None else None  # the report's table, on the figure
            plotting.save(plotting.responses(t, pair, panels, div, f"Modal displacement and tip deflection with {label}", settling=settled), os.path.join(stage, resp))
            curves = {"open_loop": psd_curves["open_loop"], run: psd_curves[run]}
            plotting.save(plotting.psds(freqs_psd, curves, mode_freqs, "PSD of tip deflection (m^2/Hz)", f"PSD with {label} ({next(iter(ESTIMATORS))})", ylim=shared), os.path.join(stage, psdfig))
        paper_db = {run: PAPER[run]["reduction_db"] for run in ("dfs", "fuzzy")}
        plotting.save(plotting.reduction_bars(by_estimator, paper_db), os.path.join(stage, "fig9_reduction.png"))
        grid = jnp.linspace(-1.0, 1.0, 41, dtype=dtype)
        fparams = fuzzy_params(1.02, 0.30, 1.0, dtype=dtype)
        surf = jax.vmap(lambda e: jax.vmap(lambda v: fuzzy_surface(fparams, e, v))(grid))(grid)
        # at angle -0.8, velocity 0.8 the rule (NS, PS -> ZE) fires at 0.4: the corners are not all rule-less
        corners = "flat at 0 in the corners (|angle|, |velocity| > 0.5): no rule fires where their signs agree; where they differ, (NS, PS) and (PS, NS) fire, to zero torque"
        plotting.save(plotting.surface(np.asarray(grid), np.asarray(grid), np.asarray(surf), note=corners), os.path.join(stage, "fig4_fuzzy_surface.png"))

        if tuned is not None:
            # each legend entry gives its gains (the figure showed neither), and the hub angle,
            # which a tip-only objective moves most, gets a panel
            gains = lambda named: ", ".join(f"{key} = {value:.4g}" for key, value in named.items())
            paper_gains = f"{plotting.LABELS[tuned.name]}, paper gains ({gains(_paper_gains(tuned.name))})"  # the legend said "DFS" beside "tuned dfs"
            tuned_gains = f"tuned {tuned.name} ({gains(tuned.named)})"
            with_hub = lambda tr: {**signals(tr), "hub": np.asarray(tr.z[:, 0])}
            pair = {"open_loop": with_hub(trajectories["open_loop"]), paper_gains: with_hub(paper_traj), tuned_gains: with_hub(ttraj)}
            div[paper_gains] = tuned_results["paper_run"]["diverged"]
            div[tuned_gains] = tuned_results["run"]["diverged"]
            figure = plotting.responses(t, pair, [*panels, ("hub", "Hub angle (rad)")], div, f"Paper gains against tuned {tuned.name} ({params_file})", style_of={paper_gains: tuned.name})
            plotting.save(figure, os.path.join(stage, TUNED_FIGURE))

        fileio.write_text(os.path.join(stage, "report.md"), _report_md(results))
        fileio.write_json(os.path.join(stage, "results.json"), results)
        say(f"writing the files into {out_dir}")
    return results
