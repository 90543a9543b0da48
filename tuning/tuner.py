"""The optax tuning loop: one jitted train step, held-out validation, early stopping, checkpoints.

``tune(config, out_dir)`` samples a training batch and a held-out batch of scenarios from one
seed, normalises the objective by the reference gains (the paper's, or ``initial``) on the
training batch, then runs ``steps`` optimiser updates of the unconstrained parameters. Every ``checkpoint_every``
steps it writes ``checkpoint.npz`` atomically; ``resume=True`` continues from it, and since
every step is deterministic the result equals an uninterrupted run with the same seed (on
the same number of devices; on another, to the order of additions). The scenarios are
sharded over all of JAX's devices (``jaxflex tune`` gives it one per CPU core).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import sys
import zipfile
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxflex import beam, checks, fileio
from jaxflex.analysis import stability
from jaxflex.beam import BeamParams
from jaxflex.controllers.dfs import DFSParams
from jaxflex.controllers.fuzzy import check_temperature
from jaxflex.controllers.registry import PARAMETERS, param_values
from jaxflex.heartbeat import Heartbeat
from jaxflex.pade import check_order
from jaxflex.plant import DiscretePlant, check_method, discretize, make_plant
from jaxflex.rollout import rollout
from jaxflex.scenarios import Scenario, ScenarioSpec, batch_modes_hz, batch_plant, check_plants, pad_batch, sample_scenarios
from tuning import objectives
from tuning.objectives import ObjectiveSpec
from tuning.transforms import CONTROLLERS, DELAYS, TunedController, check_capacity, tuned_controller

CHECKPOINT = "checkpoint.npz"
REFERENCES = ("paper", "initial")
"""The gains that may set the objective's scales (``TuneConfig.reference``)."""


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Everything that defines a tuning run (the checkpoint refuses to resume another one).

    Attributes:
      controller: "dfs", "fuzzy" or "dfs+fuzzy".
      n_scenarios: training scenarios (>= 1).
      n_heldout: held-out validation scenarios (>= 1).
      steps: optimiser steps (>= 1).
      learning_rate: Adam step size on the unconstrained parameters (> 0).
      clip_norm: global gradient-norm clip (> 0).
      seed: PRNG seed for the scenarios.
      eval_every: validate every this many steps (>= 1).
      patience: stop after this many validations without improvement (>= 1).
      checkpoint_every: write a checkpoint every this many steps (>= 1).
      n_modes: assumed modes of the plant (>= 1).
      method: "rk4" or "zoh".
      capacity: delay buffer capacity in samples; tau is tuned in [dt, capacity dt].
      delay: how DFS reads theta(t - tau): "linear" or "cubic" buffer interpolation, or
        "pade" states (tuning.transforms.DELAYS). The stability penalty and the reported
        radius are those of the loop simulated, with that read.
      pade_order: Pade order with delay = "pade" (>= 1).
      fuzzy_temperature: smoothing temperature of the fuzzy controller (0 = faithful).
      initial: starting physical parameters by name (k, tau_s, k1, k2, k3); missing names
        take the paper's values.
      reference: the gains whose objective terms on the training batch set the objective's
        scales (one of REFERENCES): "paper" (default), or "initial", for an arm or a sample
        time on which the paper's gains cannot run (a 5 ms delay at dt > 5 ms) or diverge.
      beam: the nominal arm (plain numbers; default the paper's); the scenarios' plant
        perturbations are drawn around it.
      scenarios: the scenario distribution.
      objective: the objective.
    """

    controller: str = "dfs"
    n_scenarios: int = 256
    n_heldout: int = 64
    steps: int = 200
    learning_rate: float = 0.05
    clip_norm: float = 1.0
    seed: int = 0
    eval_every: int = 10
    patience: int = 10
    checkpoint_every: int = 25
    n_modes: int = 2
    method: str = "rk4"
    capacity: int = 32
    delay: str = "linear"
    pade_order: int = 8
    fuzzy_temperature: float = 0.0
    initial: Mapping[str, float] = dataclasses.field(default_factory=dict)
    reference: str = "paper"
    scenarios: ScenarioSpec = ScenarioSpec()
    objective: ObjectiveSpec = ObjectiveSpec()
    beam: BeamParams = BeamParams()

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller must be one of {CONTROLLERS}; got {self.controller!r}")
        for name in ("n_scenarios", "n_heldout", "steps", "eval_every", "patience", "checkpoint_every"):
            object.__setattr__(self, name, checks.integer(name, getattr(self, name)))
        object.__setattr__(self, "n_modes", beam.check_n_modes(self.n_modes))
        object.__setattr__(self, "capacity", check_capacity(self.capacity))
        object.__setattr__(self, "pade_order", check_order(self.pade_order, "pade_order"))
        for name in ("learning_rate", "clip_norm"):
            object.__setattr__(self, name, checks.number(name, getattr(self, name), strict=True))
        object.__setattr__(self, "seed", checks.seed("seed", self.seed))
        if self.reference not in REFERENCES:
            raise ValueError(f"reference must be one of {REFERENCES}; got {self.reference!r}")
        if self.delay not in DELAYS:
            raise ValueError(f"delay must be one of {DELAYS}; got {self.delay!r}")
        object.__setattr__(self, "fuzzy_temperature", check_temperature(self.fuzzy_temperature, "fuzzy_temperature"))
        check_method(self.method)
        checks.instance("scenarios", self.scenarios, ScenarioSpec, "build one with ScenarioSpec(...) or ScenarioSpec.from_mapping({...})")
        checks.instance("objective", self.objective, ObjectiveSpec, "build one with ObjectiveSpec(...) or ObjectiveSpec.from_mapping({...})")
        object.__setattr__(self, "beam", beam.plain_params(self.beam))
        allowed = PARAMETERS[self.controller]
        if not isinstance(self.initial, Mapping):
            raise ValueError(f"initial must be a table of parameter values by name ({sorted(allowed)}); got {self.initial!r}")
        unknown = set(self.initial) - set(allowed)
        if unknown:
            raise fileio.UnknownKeys("initial parameter(s)", unknown, allowed, f" for {self.controller}")
        param_values(self.initial, "initial")
        check_plants(self.scenarios, self.beam, self.n_modes, self.method)  # refuses an arm not finite in the dtype of the run, or RK4 growing one
        # Out-of-range starting values are refused here, not when tune() has made its folder.
        tc = tuned_controller(self.controller, self.scenarios.dt, self.capacity, self.delay, self.pade_order, self.fuzzy_temperature)
        if self.reference == "paper":
            try:  # first: at dt = 10 ms the paper's 5 ms delay was refused as "initial", which the user had not given
                tc.to_raw(tc.paper)
            except ValueError as err:
                raise ValueError(
                    f"the paper's gains, which set the objective's scales, cannot be run with dt = {self.scenarios.dt:g} s and capacity = {self.capacity}: {err}; "
                    'set reference = "initial" to scale the objective by the [initial] gains instead'
                ) from None
        try:
            tc.to_raw(tc.from_named(dict(self.initial)))
        except ValueError as err:
            raise ValueError(f"initial {err} (a name missing from initial takes the paper's value)") from None

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["initial"] = dict(self.initial)
        out["beam"] = self.beam._asdict()
        return out

    def fingerprint_fields(self) -> dict[str, Any]:
        """What a resumed run must share with the checkpoint: everything but ``steps`` (more
        steps may be asked of a resumed run) and ``checkpoint_every`` (which changes when
        the run is saved, not what it computes), and the dtype and the program
        (``fileio.program``), as plain JSON values. ``initial`` is the starting point itself,
        every parameter as a float (the paper's where not given): ``k = 55`` edited to
        ``k = 55.0``, or the paper's values written out, refused a resume of the same run."""
        d = self.to_dict()
        d["initial"] = {name: value for name, value in param_values(self.initial, "initial").items() if name in PARAMETERS[self.controller]}
        d.pop("steps")
        d.pop("checkpoint_every")
        d["dtype"] = str(jnp.zeros(()).dtype)
        d["program"] = fileio.program()
        return json.loads(json.dumps(fileio.to_jsonable(d, exact=True)))

    def fingerprint(self) -> str:
        """Hash of ``fingerprint_fields``."""
        return fileio.digest(self.fingerprint_fields())

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], **overrides: Any) -> "TuneConfig":
        """From a dict shaped like the TOML file: top-level keys, [scenarios], [objective], [initial], [beam]."""
        if not isinstance(values, Mapping):
            raise ValueError(f"values must be a mapping of the config's keys (a TOML file's tables); got {type(values).__name__} {values!r}")
        values = dict(values)
        fileio.check_keys(values, [f.name for f in dataclasses.fields(cls)], "config")
        if "scenarios" in values:
            values["scenarios"] = ScenarioSpec.from_mapping(values["scenarios"])
        if "objective" in values:
            values["objective"] = ObjectiveSpec.from_mapping(values["objective"])
        if "beam" in values:
            values["beam"] = beam.params_from_mapping(values["beam"])
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)


class Problem:
    """The pieces a run needs: batches, the controller, the loss, the jitted functions."""

    def __init__(self, config: TuneConfig, optimizer: optax.GradientTransformation | None = None):
        self.config = config
        spec = config.scenarios
        self.dt = spec.dt
        self.tc: TunedController = tuned_controller(config.controller, spec.dt, config.capacity, config.delay, config.pade_order, config.fuzzy_temperature)
        self.beam = config.beam
        key_train, key_val = jax.random.split(jax.random.key(config.seed))
        # With several devices (a device per core: `jaxflex tune --cpu-devices`) each evaluates
        # its shard of the scenarios, and the batches are laid out so once, not on every step.
        devices = jax.devices()
        self.mesh = Mesh(np.array(devices), ("scenarios",)) if len(devices) > 1 else None
        self.train = self._place(sample_scenarios(spec, key_train, config.n_scenarios, config.n_modes))
        self.heldout = self._place(sample_scenarios(dataclasses.replace(spec, include_paper=False), key_val, config.n_heldout, config.n_modes))
        self.nominal = discretize(make_plant(self.beam, config.n_modes), spec.dt, config.method)
        self.initial_raw = self.tc.to_raw(self.tc.from_named(dict(config.initial)))  # in range: TuneConfig checked both
        try:  # None where they cannot run (a 5 ms delay at dt > 5 ms), which only reference = "initial" lets by
            self.paper_raw = self.tc.to_raw(self.tc.paper)
        except ValueError:
            self.paper_raw = None
        self.reference_raw = self.paper_raw if config.reference == "paper" else self.initial_raw
        inner = optax.adam(config.learning_rate) if optimizer is None else optimizer
        self.optimizer = optax.chain(optax.clip_by_global_norm(config.clip_norm), inner)
        self.scales = jax.jit(self._terms)(self.reference_raw, self.train)
        if not all(np.all(np.isfinite(np.asarray(t))) for t in self.scales):
            who, advice = ("the paper's gains", ', or set reference = "initial" with [initial] gains that hold this arm') if config.reference == "paper" else ("the initial gains", "")
            raise ValueError(
                f"{who}, which set the objective's scales, diverge on the training scenarios: "
                f"check the arm ([beam]), dt and method, and the scenarios' disturbances{advice}"
            )
        self.scales = objectives.reference_scales(self.scales)
        objective, train_step = jax.jit(self._objective), self._make_train_step()
        # The parameters and the optimiser state replicated on every device, whatever made
        # them (the paper's gains, a checkpoint, the last step): under a mesh each other
        # placement would trace and compile the functions again.
        self.evaluate = lambda raw, batch: objective(self._replicated(raw), batch)
        self.train_step = lambda raw, opt_state, batch: train_step(self._replicated(raw), self._replicated(opt_state), batch)

    def _terms(self, raw: Any, batch: Scenario) -> objectives.Terms:
        params = self.tc.to_physical(raw)
        config = self.config

        def run(params: Any, batch: Scenario) -> objectives.Terms:
            plant = batch_plant(self.beam, config.n_modes, self.dt, config.method, batch, self.nominal)
            freqs = batch_modes_hz(self.beam, config.n_modes, batch) if config.objective.vibration > 0 else None
            return jax.vmap(objectives.terms_from_metrics)(rollout(plant, self.tc.controller, params, batch, output="metrics", mode_freqs_hz=freqs))

        if self.mesh is None:
            return run(params, batch)
        # shard_map rather than jit's automatic partitioning: the parameters' cotangent is then
        # summed over the devices once, at the end of the reverse pass, instead of in every
        # reverse step of the loop (benchmarks/README.md, "Three ways to run on 2 cores").
        # The parameters go in as a replicated argument, not by closure: after the first step
        # they carry the mesh's sharding, which the manual region would refuse.
        # check_vma=False: the rollout's scan carries start from constants, which the
        # varying-axes check would reject as carries that turn varying.
        n = batch.x0.shape[0]
        spec = PartitionSpec("scenarios")
        sharded = jax.shard_map(run, mesh=self.mesh, in_specs=(PartitionSpec(), spec), out_specs=spec, check_vma=False)
        return jax.tree.map(lambda t: t[:n], sharded(params, pad_batch(batch, self.mesh.size)))

    def _place(self, batch: Scenario) -> Scenario:
        """``batch`` sharded over the devices, when there are several and it splits evenly
        (otherwise ``_terms`` pads it on every call)."""
        if self.mesh is None or batch.x0.shape[0] % self.mesh.size:
            return batch
        return jax.device_put(batch, NamedSharding(self.mesh, PartitionSpec("scenarios")))

    def _replicated(self, tree: Any) -> Any:
        return tree if self.mesh is None else jax.device_put(tree, NamedSharding(self.mesh, PartitionSpec()))

    @property
    def penalised(self) -> bool:
        """Whether the training loss holds the stability penalty: DFS alone (``log_radius``),
        with a stability_weight above 0."""
        return self.config.controller == "dfs" and self.config.objective.stability_weight > 0

    def log_radius(self, raw: Any) -> jax.Array | None:
        """Log spectral radius of the nominal sampled DFS loop; None unless the controller is
        DFS alone (with a fuzzy part the loop is nonlinear: no loop matrix to penalise)."""
        if self.config.controller != "dfs":
            return None  # a fuzzy part is nonlinear: no sampled-loop matrix
        return self.dfs_log_radius(self.tc.to_physical(raw))

    def dfs_log_radius(self, params: DFSParams) -> jax.Array:
        """Log spectral radius of the sampled loop of the nominal plant under DFS ``params``,
        with its delay states (the Pade filter's with delay = "pade") and without the structural
        eigenvalue 1."""
        return objectives.log_spectral_radius(_deflated_loop(self.nominal, params, self.dt, self.config))

    def _objective(self, raw: Any, batch: Scenario) -> tuple[jax.Array, dict[str, jax.Array]]:
        terms = self._terms(raw, batch)
        losses = objectives.scenario_losses(terms, self.scales, self.config.objective)
        value = objectives.reduce_losses(losses, self.config.objective)
        aux = {"objective": value}
        log_r = self.log_radius(raw)
        if log_r is not None:
            penalty = objectives.stability_penalty(log_r, self.dt, self.config.objective)
            aux["penalty"] = penalty
            value = value + penalty
        return value, aux

    def _make_train_step(self) -> Callable:
        optimizer = self.optimizer

        @jax.jit
        def train_step(raw, opt_state, batch):
            (loss, aux), grads = jax.value_and_grad(self._objective, has_aux=True)(raw, batch)
            updates, opt_state = optimizer.update(grads, opt_state, raw)
            raw = optax.apply_updates(raw, updates)
            return raw, opt_state, {"loss": loss, "grad_norm": optax.tree.norm(grads), **aux}

        return train_step


def _save_checkpoint(path: str, state: dict[str, Any]) -> None:
    leaves = jax.tree.leaves((state["raw"], state["opt_state"], state["best_raw"]))
    meta = {k: v for k, v in state.items() if k not in ("raw", "opt_state", "best_raw")}
    arrays = {f"leaf_{i}": np.asarray(leaf) for i, leaf in enumerate(leaves)}

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.frombuffer(json.dumps(fileio.to_jsonable(meta, finite=False)).encode(), dtype=np.uint8), **arrays)

    fileio.atomic_write(path, write)


def recorded_steps(out_dir: str | os.PathLike) -> int | None:
    """The number of updates the run in ``out_dir`` was asked for (its checkpoint's record);
    None without a readable checkpoint, or one written before jaxflex recorded it.
    ``jaxflex tune --resume`` goes on to it unless ``--steps`` (or the config) says otherwise:
    it went on to the default 200 of a run started for 400, and wrote a final-looking result."""
    path = os.path.join(fileio.check_path("out_dir", out_dir, "folder"), CHECKPOINT)
    try:
        steps = _load_checkpoint(path).get("steps")
    except ValueError:  # missing or damaged: the resume itself names it
        return None
    return steps if isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1 else None


def _load_checkpoint(path: str, template: tuple[Any, Any, Any] | None = None) -> dict[str, Any]:
    """The checkpoint's metadata and, given a ``template`` (raw, opt_state, best_raw), its arrays.

    Raises:
      ValueError: naming the file when it is damaged or not a checkpoint of ``tune`` (empty,
        truncated, another kind of file, metadata without its fingerprint and step).
    """
    damaged = f"--resume: {path} is damaged or not a checkpoint of jaxflex tune"
    try:
        with np.load(path, allow_pickle=False) as data:
            state = json.loads(bytes(data["meta"]).decode())
            if template is not None:
                treedef = jax.tree.structure(template)
                leaves = [jnp.asarray(data[f"leaf_{i}"]) for i in range(treedef.num_leaves)]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"{damaged} ({type(err).__name__}); start a new run in another --out") from None
    if not isinstance(state, dict) or not {"fingerprint", "step"} <= state.keys():
        raise ValueError(f"{damaged} (its metadata lacks the run's fingerprint and step); start a new run in another --out")
    if template is not None:
        expected = [np.shape(leaf) for leaf in jax.tree.leaves(template)]
        if [leaf.shape for leaf in leaves] != expected:  # an edited or foreign file with the right names
            raise ValueError(f"{damaged} (its arrays have shapes {[leaf.shape for leaf in leaves]}, this run's {expected}); start a new run in another --out")
        state["raw"], state["opt_state"], state["best_raw"] = jax.tree.unflatten(treedef, leaves)
    return state


def _resume_line(out_dir: str, meta: dict[str, Any], steps: int) -> str:
    """Where a resumed run goes on from, or that it has nothing left to do and only writes
    its results again."""
    history = meta.get("history") or [{}]
    if meta.get("stopped_early"):
        return f"the run in {out_dir} stopped early after {meta['step']} updates; writing its results again"
    if meta["step"] == steps and history[-1].get("step") == steps:
        return f"the run in {out_dir} has finished all {steps} updates; writing its results again (--steps above {steps} goes on)"
    return f"resuming from {os.path.join(out_dir, CHECKPOINT)}, after {meta['step']} of {steps} updates"


def _deflated_loop(nominal: DiscretePlant, params: DFSParams, dt: float, config: TuneConfig) -> jax.Array:
    """The sampled DFS loop of the run's delay, without its structural eigenvalue: the Pade
    filter's with delay = "pade", else the buffer's read as the run reads it."""
    if config.delay == "pade":
        return stability.deflated_pade_loop_matrix(nominal, params.k, params.tau_s, config.pade_order)
    return stability.deflated_loop_matrix(nominal, params.k, params.tau_s / dt, config.capacity, config.delay)


def _history_csv(history: list[dict[str, Any]], names: list[str]) -> str:
    cols = ["step", "loss", "objective", "penalty", "val_objective", "grad_norm"] + names
    buf = io.StringIO()
    buf.write(",".join(cols) + "\n")
    for row in history:
        buf.write(",".join("" if row.get(c) is None else repr(float(row[c])) if c != "step" else str(row[c]) for c in cols) + "\n")
    return buf.getvalue()


def tune(
    config: TuneConfig,
    out_dir: str | os.PathLike,
    *,
    resume: bool = False,
    progress: bool = True,
    on_step: Callable[[int], None] | None = None,
    optimizer: optax.GradientTransformation | None = None,
    on_start: Callable[[], None] | None = None,
) -> dict[str, Any]:
    """Run (or resume) a tuning run; returns the final state (raw/best parameters, history).

    Args:
      config: the run.
      out_dir: folder for checkpoint.npz and history.csv.
      resume: continue from ``out_dir/checkpoint.npz`` (an error if it is missing or was made
        with another configuration). An interrupted run ends as the uninterrupted one would.
        A finished run resumed with more ``steps`` goes on as one longer run would, except
        when its final point fell between validations (every run scores the parameters after
        its last update): that extra score may have moved the best parameters and the
        early-stopping count.
      progress: show a tqdm progress bar with the loss and the validation objective (a
        resumed run says where it goes on from either way).
      on_step: called with the step number after each step (tests use it to interrupt).
      optimizer: any optax GradientTransformation (default Adam at ``config.learning_rate``);
        gradients are clipped to ``config.clip_norm`` before it. A resumed run must use the
        same optimizer (its state is in the checkpoint).
      on_start: called once the folder and the checkpoint's configuration have been checked,
        before anything is sampled, compiled or written.

    Raises:
      ValueError: bad configuration, a checkpoint of another run, an objective that
        became NaN (the last checkpoint is kept), or a gradient exactly zero at the start
        (nothing written).
    """
    checks.instance("config", config, TuneConfig, "build one with TuneConfig(...)")
    resume, progress = checks.flag("resume", resume), checks.flag("progress", progress)
    checks.callback("on_step", on_step, "the step number")
    checks.callback("on_start", on_start, "no arguments")
    if optimizer is not None:
        checks.instance("optimizer", optimizer, optax.GradientTransformation, "e.g. optax.adam(1e-2)")
    with fileio.run_lock(out_dir, "out_dir (--out)"):
        return _tune_locked(config, os.fspath(out_dir), resume, progress, on_step, optimizer, on_start)


def _tune_locked(
    config: TuneConfig,
    out_dir: str,
    resume: bool,
    progress: bool,
    on_step: Callable[[int], None] | None,
    optimizer: optax.GradientTransformation | None,
    on_start: Callable[[], None] | None,
) -> dict[str, Any]:
    """``tune`` with the folder's run lock held."""
    ckpt_path = os.path.join(out_dir, CHECKPOINT)
    fingerprint = config.fingerprint()
    # The folder and the checkpoint's configuration are checked before any sampling or compiling.
    if not resume and os.path.exists(ckpt_path):
        raise ValueError(f"{out_dir} already holds a tuning run ({CHECKPOINT}): pass --resume (resume=True) to continue it, choose another --out (out_dir), or delete the folder to start over in it")
    if resume:
        if not os.path.exists(ckpt_path):
            raise ValueError(f"--resume: no checkpoint at {ckpt_path}")
        meta = _load_checkpoint(ckpt_path)
        if meta["fingerprint"] != fingerprint:
            what = fileio.changed_fields(meta.get("config"), config.fingerprint_fields())
            raise ValueError(f"--resume: {ckpt_path} was written by a run with another configuration ({what}; fingerprint {meta['fingerprint']} != {fingerprint}): "
                             "resume with the command that started it, its --config and options, and --resume")
        if config.steps < meta["step"]:
            raise ValueError(f"--resume: the run in {out_dir} has taken {meta['step']} steps already; steps = {config.steps} cannot undo them (pass --steps {meta['step']} or more)")
    if on_start is not None:
        on_start()
    os.makedirs(out_dir, exist_ok=True)
    if resume:  # said with or without the progress bar (--no-progress): where the run goes on from
        print(f"tune: {_resume_line(out_dir, meta, config.steps)}", file=sys.stderr, flush=True)
    # said with or without the bar too: a log under a scheduler (--no-progress) shows the devices
    print(f"tune: sampling {config.n_scenarios} training and {config.n_heldout} held-out scenarios on {jax.device_count()} device(s), compiling", file=sys.stderr, flush=True)
    problem = Problem(config, optimizer)
    names = list(problem.tc.named(problem.tc.to_physical(problem.initial_raw)))
    if resume:
        template = (problem.initial_raw, problem.optimizer.init(problem.initial_raw), problem.initial_raw)
        state = _load_checkpoint(ckpt_path, template)
    else:
        state = {
            "step": 0,
            "raw": problem.initial_raw,
            "opt_state": problem.optimizer.init(problem.initial_raw),
            "best_raw": problem.initial_raw,
            "best_val": math.inf,  # the validation at step 0 sets it; any finite value improves on it
            "best_step": 0,
            "bad_evals": 0,
            "stopped_early": False,
            "history": [],
            "fingerprint": fingerprint,
            "config": config.fingerprint_fields(),
        }
    state["steps"] = config.steps  # the target, which the fingerprint leaves out: a bare --resume goes on to it (recorded_steps)

    # which device count took which steps: a run resumed on another count goes on within
    # rounding, not bit for bit (a checkpoint of an older jaxflex starts at its resume step)
    devices = 1 if problem.mesh is None else problem.mesh.size
    segments = state.setdefault("devices_from_step", [])
    if not segments or segments[-1]["devices"] != devices:
        if segments:  # said, not only recorded in tuned.json
            print(f"tune: note: the run took steps on {segments[-1]['devices']} device(s) and goes on on {devices}: its result matches an uninterrupted run's "
                  "within rounding, not bit for bit (a batch sum splits otherwise)", file=sys.stderr, flush=True)
        segments.append({"from_step": state["step"], "devices": devices})
    bar = None
    heartbeat = None if progress else Heartbeat("tune", "updates", config.steps, state["step"])  # a line every 30 s for a log
    history = state["history"]
    carried = None
    if history and history[-1]["step"] == state["step"] < config.steps:
        # A finished run resumed with more steps: its final point becomes an ordinary one, and
        # its held-out score, already counted in best_* and bad_evals, is carried over rather
        # than counted twice.
        carried = history.pop()
    try:
        while not state["stopped_early"] and not (history and history[-1]["step"] == config.steps):
            # Each history row is one point: the parameters after `step` updates, the training
            # objective and gradient norm there (from which the next update is taken), and
            # every eval_every updates the held-out objective there. The final point, after
            # the last update, is scored (training and held-out objectives) but not updated;
            # a non-finite training objective there leaves it unvalidated, so it is not kept.
            at, n = state["raw"], state["step"]
            final = n == config.steps
            if final:
                value, aux = problem.evaluate(at, problem.train)
                info = {"loss": value, **aux}
            else:
                raw, opt_state, info = problem.train_step(at, state["opt_state"], problem.train)
                loss, grad_norm = float(info["loss"]), float(info["grad_norm"])
                if not (math.isfinite(loss) and math.isfinite(grad_norm)):
                    became = "is" if n == 0 else "became"
                    what = f"the objective {became} {loss}" if not math.isfinite(loss) else f"the gradient norm {became} {grad_norm}"
                    kept = f"the last checkpoint in {out_dir} is kept" if os.path.exists(ckpt_path) else f"no checkpoint was written yet (every {config.checkpoint_every} steps)"
                    if n == 0:  # no update has been taken: the learning rate is not the cause
                        raise ValueError(f"{what} at the starting parameters, before any update: check [initial], [objective] and [scenarios]; {kept}")
                    # a resume keeps the run's learning rate and would meet the same NaN: the advice was to lower it, and the folder then refused both
                    raise ValueError(f"{what} at step {n + 1}: start again with a lower learning_rate (--lr) or clip_norm (a config key), or check the scenarios, "
                                     f"in another --out or after deleting {out_dir} (a --resume keeps the run's learning rate and meets the same NaN); {kept}")
                if n == 0 and grad_norm == 0.0:  # no update could ever move them
                    spec = config.scenarios
                    raise ValueError(f"the objective's gradient is exactly zero at the starting parameters, so no update can move them: over the "
                                     f"horizon of {spec.horizon_s:g} s ({spec.steps} samples of dt = {spec.dt:g} s) the objective does not "
                                     "depend on them (too short a horizon for the controller's torque to reach what [objective] weighs, or "
                                     "scenarios with nothing to respond to); lengthen [scenarios] horizon_s, or check [scenarios] and [objective]")
                state["raw"], state["opt_state"], state["step"] = raw, opt_state, n + 1
            row = {"step": n, **{k: fileio.shortest(v) for k, v in info.items()}}
            row.update(problem.tc.named(problem.tc.to_physical(at)))
            if carried is not None and n == carried["step"] and "val_objective" in carried:
                row["val_objective"] = carried["val_objective"]
                if n % config.eval_every == 0:  # where a longer run would have stopped
                    state["stopped_early"] = state["bad_evals"] >= config.patience
            elif (n % config.eval_every == 0 or final) and math.isfinite(row["loss"]):
                val = fileio.shortest(problem.evaluate(at, problem.heldout)[0])
                row["val_objective"] = val
                if val < state["best_val"]:
                    state["best_val"], state["best_raw"], state["best_step"], state["bad_evals"] = val, at, n, 0
                else:
                    state["bad_evals"] += 1
                    state["stopped_early"] = state["bad_evals"] >= config.patience and not final
            history.append(row)
            if final:
                if bar is not None:  # it ends on the final point's scores, not on the step before it
                    bar.set_postfix(loss=f"{row['loss']:.4g}", best_val=f"{state['best_val']:.4g}")
                    bar.close()
                    bar = None
                if heartbeat is not None:  # its last line, withheld at the last update, has the final point's scores
                    # (a run resumed from a checkpoint of the last update has counted it already)
                    heartbeat.update(1 if heartbeat.done < config.steps else 0, f"; loss {row['loss']:.4g}, best held-out {state['best_val']:.4g}")
                continue
            if progress and bar is None:
                # opened after this process's first step, which compiled: timed with it, the
                # bar's rate and time left were off by the compile time (16 s/step at first)
                from tqdm.auto import tqdm

                bar = tqdm(total=config.steps, initial=state["step"], desc=f"tune {config.controller}", unit="step")
            elif bar is not None:
                bar.update(1)
            if bar is not None:
                bar.set_postfix(loss=f"{loss:.4g}", best_val=f"{state['best_val']:.4g}")
            if heartbeat is not None and state["step"] < config.steps:
                heartbeat.update(1, f"; loss {loss:.4g}, best held-out {state['best_val']:.4g}")
            if state["step"] % config.checkpoint_every == 0:
                _save_checkpoint(ckpt_path, state)
                fileio.write_text(os.path.join(out_dir, "history.csv"), _history_csv(history, names))
            if on_step is not None:
                on_step(state["step"])
    finally:
        if bar is not None:
            bar.close()
    _save_checkpoint(ckpt_path, state)
    fileio.write_text(os.path.join(out_dir, "history.csv"), _history_csv(history, names))
    state["problem"] = problem
    state["names"] = names
    return state


def summarize(state: dict[str, Any]) -> dict[str, Any]:
    """The content of tuned.json: parameters, objectives before/after, stability."""
    problem: Problem = state["problem"]
    tc = problem.tc
    best = state["best_raw"]
    ev = lambda raw, batch: None if raw is None else fileio.shortest(problem.evaluate(raw, batch)[1]["objective"])
    reference = problem.config.reference
    out: dict[str, Any] = {
        "controller": problem.config.controller,
        "params": tc.named(tc.to_physical(best)),
        "paper_params": tc.named(tc.paper),
        "initial_params": tc.named(tc.to_physical(problem.initial_raw)),
        "objective": {
            "train": {"before": ev(problem.initial_raw, problem.train), "after": ev(best, problem.train), "paper": ev(problem.paper_raw, problem.train)},
            "heldout": {"before": ev(problem.initial_raw, problem.heldout), "after": ev(best, problem.heldout), "paper": ev(problem.paper_raw, problem.heldout)},
            "definition": f"weighted per-scenario losses, each term normalised by its mean under the {reference} gains on the training batch "
            f"(so the mean of the {reference} gains scores 1.0 per unit weight; 'paper' is null where the paper's gains cannot run), "
            f"combined by {problem.config.objective.reduction}",
        },
        "dtype": str(jax.tree.leaves(best)[0].dtype),  # of the simulation: float32, or float64 under --x64
        "devices": state["devices_from_step"][-1]["devices"],  # this session's scenarios were sharded over
        "devices_from_step": state["devices_from_step"],  # every session's, when a resumed run changed the count
        "steps_run": state["step"],
        "best_step": state["best_step"],
        "stopped_early": state["stopped_early"],
        "config": problem.config.to_dict(),
    }
    dfs_params = None
    physical = tc.to_physical(best)
    if problem.config.controller == "dfs":
        dfs_params = physical
    elif problem.config.controller == "dfs+fuzzy":
        dfs_params = physical[0]
    if dfs_params is not None:
        # In float64 whatever the run's dtype, as `jaxflex stability` reports it: the radius
        # lies within 1e-2 of 1, and a float32 loop matrix moves it in the 7th digit
        # (0.99065495 against 0.99065454 for the paper's gains).
        with jax.enable_x64(True):
            nominal = discretize(make_plant(problem.beam, problem.config.n_modes), problem.dt, problem.config.method)

            def log_radius(p: DFSParams) -> float:
                # A delay at an end of its range, rounded in the run's dtype, may come out a
                # hair outside [1, capacity] samples (64.000003); it is that end.
                tau = min(max(float(p.tau_s), problem.dt), problem.config.capacity * problem.dt)
                loop = _deflated_loop(nominal, DFSParams(float(p.k), tau), problem.dt, problem.config)
                return math.log(float(jnp.max(jnp.abs(jnp.linalg.eigvals(loop)))))

            log_rho = log_radius(dfs_params)
            paper_log_rho = None if problem.paper_raw is None else log_radius(tc.paper if problem.config.controller == "dfs" else tc.paper[0])
        out["stability"] = {
            "spectral_radius": math.exp(log_rho),
            "paper_spectral_radius": None if paper_log_rho is None else math.exp(paper_log_rho),
            "decay_rate_per_s": -log_rho / problem.dt,
            "stable": log_rho < 0,
            "note": "sampled DFS loop on the nominal plant with its delay states; the structural z = 1 (no position action) is excluded"
            + ("; the fuzzy part of dfs+fuzzy is not included (nonlinear)" if problem.config.controller == "dfs+fuzzy" else ""),
        }
    return out


__all__ = ["TuneConfig", "Problem", "tune", "summarize"]
