"""The edge of ``jaxflex tune``: run the tuner, then write tuned.json, history.csv and figures."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Callable

import jax
import numpy as np

from jaxflex import beam, checks, fileio, plotting
from jaxflex.analysis import welch
from jaxflex.rollout import rollout
from jaxflex.scenarios import scenario_modes_hz, scenario_plant
from tuning.tuner import CHECKPOINT, Problem, TuneConfig, summarize, tune

N_SHOWN_HELDOUT = 3
FIGURES = ("loss.png", *(f"{kind}_{idx}.png" for kind in ("response", "psd") for idx in range(N_SHOWN_HELDOUT + 1)))
"""Every figure ``run_tune`` may draw: the loss, and the responses and PSDs (the reference
gains, ``TuneConfig.reference``, against the tuned) of the paper scenario and of up to
``N_SHOWN_HELDOUT`` held-out ones, numbered from 0."""


def _figures(state: dict[str, Any], out_dir: str, reference_objective: float) -> list[str]:
    problem: Problem = state["problem"]
    tc, config = problem.tc, problem.config
    history = state["history"]
    steps = np.array([h["step"] for h in history])
    loss = np.array([h["loss"] for h in history])
    val_rows = [h for h in history if h.get("val_objective") is not None]
    written = []
    nominal_hz = np.asarray(beam.natural_frequencies_hz(problem.beam, config.n_modes))
    fig = plotting.loss_curves(steps, loss, np.array([h["step"] for h in val_rows]), np.array([h["val_objective"] for h in val_rows]), f"Tuning {config.controller} for the {plotting.arm_label(problem.beam.length_m, nominal_hz)}", state["best_step"], (config.reference, reference_objective), penalised=problem.penalised)
    plotting.save(fig, os.path.join(out_dir, "loss.png"))
    written.append("loss.png")

    simulate = jax.jit(rollout, static_argnums=1)
    reference = f"{config.reference} gains"
    gains = {reference: tc.paper if config.reference == "paper" else tc.from_named(dict(config.initial)), "tuned": tc.to_physical(state["best_raw"])}
    members = [("paper scenario", jax.tree.map(lambda a: a[0], problem.train))] if config.scenarios.include_paper else []
    members += [(f"held-out scenario {i + 1}", jax.tree.map(lambda a, i=i: a[i], problem.heldout)) for i in range(min(N_SHOWN_HELDOUT, config.n_heldout))]
    for idx, (label, scenario) in enumerate(members):
        plant = problem.nominal if scenario.plant is None else scenario_plant(problem.beam, config.n_modes, problem.dt, config.method, scenario)
        trajs = {name: simulate(plant, tc.controller, params, scenario) for name, params in gains.items()}
        t = np.asarray(trajs["tuned"].t)
        runs = {name: {"tip": np.asarray(tr.z[:, 1]), "hub": np.asarray(tr.z[:, 0])} for name, tr in trajs.items()}
        div = {name: bool(~np.all(np.isfinite(np.asarray(tr.x)))) for name, tr in trajs.items()}
        modes_hz = np.asarray(scenario_modes_hz(problem.beam, config.n_modes, scenario))
        whose = "" if np.allclose(modes_hz, nominal_hz, rtol=1e-6, atol=0) else " (this scenario's plant)"  # a held-out scenario's perturbed arm, not the nominal one
        title = f"{config.controller}: {config.reference} vs tuned gains, {label}\n{plotting.arm_label(problem.beam.length_m, modes_hz)}{whose}"
        fig = plotting.responses(t, runs, [("tip", "Tip deflection (m)"), ("hub", "Hub angle (rad)")], div, title, style_of={reference: config.controller})
        name = f"response_{idx}.png"
        plotting.save(fig, os.path.join(out_dir, name))
        written.append(name)
        nperseg = min(1024, t.shape[0])
        estimates = {n: welch(tr.z[:, 1], 1 / problem.dt, nperseg=nperseg) for n, tr in trajs.items()}
        psd = {n: np.asarray(p) for n, (_, p) in estimates.items()}
        freqs = np.asarray(estimates["tuned"][0])
        fig = plotting.psds(freqs, psd, modes_hz, "PSD of tip deflection (m^2/Hz)", title, style_of={reference: config.controller})
        name = f"psd_{idx}.png"
        plotting.save(fig, os.path.join(out_dir, name))
        written.append(name)
    return written


def run_tune(config: TuneConfig, out_dir: str | os.PathLike, *, resume: bool = False, progress: bool = True, on_step: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Tune, then write ``tuned.json`` (last), ``history.csv`` and figures into ``out_dir``.

    ``tuned.json`` is there only when the run has finished: a resumed run removes the
    folder's previous one and its figures (``FIGURES``) first (once the folder and the
    checkpoint have been checked), and its end writes them anew, staged and moved in
    together, so that a run stopped while drawing leaves no figure (it left those drawn so
    far, with no tuned.json). A new run refuses a folder that holds an earlier tuned.json
    (ValueError) rather than removing it."""
    checks.instance("config", config, TuneConfig, "build one with TuneConfig(...)")  # before the lock makes the folder
    resume, progress = checks.flag("resume", resume), checks.flag("progress", progress)
    out_dir = fileio.check_path("out_dir (--out)", out_dir, "folder")

    def discard_previous_result() -> None:
        # A resumed run's tuned.json and figures are rewritten at its end; until then the
        # previous ones would describe fewer steps than checkpoint.npz and history.csv.
        for name in (*FIGURES, "tuned.json"):
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(out_dir, name))

    with fileio.run_lock(out_dir, "out_dir (--out)"):  # tune's, held on to the figures and tuned.json
        if not resume and os.path.exists(os.path.join(out_dir, "tuned.json")) and not os.path.exists(os.path.join(out_dir, CHECKPOINT)):
            # a new run removes the folder's tuned.json and figures at its start (they would not be its own); one stopped then had lost them
            raise ValueError(f"{out_dir} holds the tuned.json of an earlier run: choose another --out (out_dir), or remove that tuned.json to start over in this folder (the new run replaces its figures)")
        state = tune(config, out_dir, resume=resume, progress=progress, on_step=on_step, on_start=discard_previous_result)
        print("tune: evaluating the tuned gains and drawing figures", file=sys.stderr, flush=True)  # with or without the bar
        summary = summarize(state)
        with fileio.replace_outputs(out_dir, (*FIGURES, "tuned.json"), last="tuned.json") as stage:
            summary["figures"] = _figures(state, stage, summary["objective"]["train"]["paper" if config.reference == "paper" else "before"])
            fileio.write_json(os.path.join(stage, "tuned.json"), summary)
    return summary
