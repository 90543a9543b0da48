"""Monte Carlo over scenarios: chunked, device-sharded, resumable, with streaming memory.

Chunk ``i`` holds the scenarios drawn from ``jax.random.fold_in(key(seed), i)``, so every
scenario is fixed by the seed and its chunk alone, whatever the number of devices or the
order in which chunks run. Each chunk is one jitted, batched ``rollout(output="metrics")``
with its scenario axis sharded over all local devices (``jax.sharding``; on a CPU the
``jaxflex montecarlo`` command makes one device per core, ``--cpu-devices``); only per-scenario
scalar metrics come back, so memory grows with the chunk, not with N x horizon. Each
chunk's metrics are written atomically to ``chunks/chunk_NNNNNN.npz``; a resumed run skips
the chunks already on disk. ``summary.json`` is computed from the chunk files at the end.

Across hosts, start the same command on every host after ``jax.distributed.initialize()``
(see the README); the scenario axis is then sharded over all global devices.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import numbers
import os
import re
import sys
import zipfile
from functools import partial
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxflex import beam, checks, fileio
from jaxflex.analysis.metrics import RUN_DIVERGED_DOC, diverged, run_diverged
from jaxflex.beam import BeamParams
from jaxflex.controllers import Controller, OpenLoopParams, by_name, open_loop
from jaxflex.controllers.fuzzy import check_temperature
from jaxflex.controllers.registry import CONFIG_OPTIONS, DELAYS, NAMES, PARAMETERS, param_values
from jaxflex.delay import check_capacity
from jaxflex.heartbeat import Heartbeat
from jaxflex.pade import check_order
from jaxflex.plant import check_method, discretize, make_plant
from jaxflex.rollout import MAX_UNROLL, RunMetrics, rollout
from jaxflex.scenarios import Scenario, ScenarioSpec, batch_modes_hz, batch_plant, check_plants, pad_batch, sample_scenarios

CONTROLLERS = NAMES
META = "montecarlo.json"
FIGURES = ("histograms.png", "tip_bands.png")
"""The figures a run draws into its folder, beside summary.json."""
"""The file in a Monte Carlo folder that says which configuration wrote its chunks."""
METRICS = {
    "settling_time_s": "settling time of the tip deflection (s; 2 % of its peak, around 0)",
    "peak_tip_deflection_m": "peak |tip deflection| (m)",
    "tip_ise": "integral of tip deflection^2 (m^2 s)",
    "control_effort": "integral of torque^2 (N^2 m^2 s)",
    "final_hub_angle_rad": "hub angle at the end of the horizon (rad)",
}
REDUCTION_DOC = (
    "10 log10 of the open-loop over the closed-loop energy of the tip deflection at mode i of the scenario's own plant "
    "(Hann-windowed single-bin DFT over the horizon, streamed in the rollout) (dB); NaN when the mode is at or above "
    "the Nyquist frequency, where the samples hold only its alias"
)
REDUCTION_LABEL = "vibration reduction at mode i: open over closed-loop energy of the tip deflection (dB)"
"""``REDUCTION_DOC`` short enough for a histogram's axis (it took four lines under the panel)."""


@dataclasses.dataclass(frozen=True)
class MCConfig:
    """A Monte Carlo run.

    Attributes:
      controller: one of CONTROLLERS.
      params: controller parameters by name (k, tau_s, k1, k2, k3); missing names take the
        paper's values.
      n_scenarios: N >= 1.
      chunk: scenarios per chunk (>= 1). For sharding, a chunk is padded to a multiple of the
        device count with copies of its last scenario, whose results are dropped.
      seed: PRNG seed.
      percentiles: reported percentiles, each in [0, 100].
      scenarios: the scenario distribution (default 3 s, as the paper).
      n_modes, method, capacity: plant modes, "rk4"/"zoh", DFS buffer capacity (samples).
      delay, pade_order: how DFS reads the delayed angle (``by_name``'s ``delay``, one of
        ``DELAYS``) and the Pade order with ``delay="pade"``.
      fuzzy_temperature: smoothing temperature of the fuzzy controller (0 = faithful).
      band_scenarios: scenarios of chunk 0 whose tip deflection feeds the percentile-band plot.
      beam: the nominal arm (plain numbers; default the paper's); plant perturbations are
        drawn around it.
      unroll: samples per compiled loop iteration (``rollout``'s ``unroll``), in [1, 64].
        On an H100, 8 ran a chunk 3.0-3.8x as fast as 1 (2.6-2.7x in another process) but
        compiled for 5-6 s longer, which pays from about 0.4 million scenarios at a chunk
        of 4,096 and 4.6 million at 65,536; on the CPU it is 2.4-4.7x slower
        (benchmarks/README.md, "Scan unrolling"). Default 1.
    """

    controller: str = "dfs+fuzzy"
    params: dict = dataclasses.field(default_factory=dict)
    n_scenarios: int = 10_000
    chunk: int = 4096
    seed: int = 0
    percentiles: Sequence[float] = (5.0, 50.0, 95.0)
    scenarios: ScenarioSpec = ScenarioSpec(horizon_s=3.0)
    n_modes: int = 2
    method: str = "rk4"
    capacity: int = 64
    delay: str = "linear"
    pade_order: int = 8
    fuzzy_temperature: float = 0.0
    band_scenarios: int = 256
    beam: BeamParams = BeamParams()
    unroll: int = 1

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller must be one of {CONTROLLERS}; got {self.controller!r}")
        for name in ("n_scenarios", "chunk", "band_scenarios"):
            object.__setattr__(self, name, checks.integer(name, getattr(self, name)))
        object.__setattr__(self, "capacity", check_capacity(self.capacity))
        object.__setattr__(self, "pade_order", check_order(self.pade_order, "pade_order"))
        object.__setattr__(self, "n_modes", beam.check_n_modes(self.n_modes))
        object.__setattr__(self, "unroll", checks.integer("unroll", self.unroll, 1, high=MAX_UNROLL))
        object.__setattr__(self, "seed", checks.seed("seed", self.seed))
        if not isinstance(self.params, dict) or not all(isinstance(k, str) for k in self.params):
            raise ValueError(f"params must be a dict of parameter values by name; got {self.params!r}")
        param_values(self.params)
        checks.instance("scenarios", self.scenarios, ScenarioSpec, "build one with ScenarioSpec(...) or ScenarioSpec.from_mapping({...})")
        # A NumPy or JAX array is a sequence of numbers to a user (its elements, not Python ones).
        values = self.percentiles.tolist() if isinstance(self.percentiles, (np.ndarray, jax.Array)) else self.percentiles
        if (
            isinstance(values, (str, bytes))
            or not isinstance(values, Sequence)
            or not values
            or any(isinstance(p, bool) or not (isinstance(p, numbers.Real) and 0 <= p <= 100) for p in values)
        ):
            raise ValueError(f"percentiles must be numbers in [0, 100] (a non-empty list, tuple or 1-D array); got {self.percentiles!r}")
        object.__setattr__(self, "percentiles", tuple(float(p) for p in values))
        keys = [f"p{p:g}" for p in self.percentiles]
        if len(set(keys)) != len(keys):
            raise ValueError(f"percentiles must differ in their first 6 significant digits (each is reported as p<value>: {keys}); got {self.percentiles!r}")
        check_method(self.method)
        if self.delay not in DELAYS:
            raise ValueError(f"delay must be one of {DELAYS}; got {self.delay!r}")
        object.__setattr__(self, "fuzzy_temperature", check_temperature(self.fuzzy_temperature, "fuzzy_temperature"))
        object.__setattr__(self, "beam", beam.plain_params(self.beam))
        check_plants(self.scenarios, self.beam, self.n_modes, self.method)  # refuses an arm not finite in the dtype of the run, or RK4 growing one
        # Out-of-range parameter values are refused here, not when the run starts.
        controller, params = controller_and_params(self.controller, self.params, self.scenarios.dt, self.capacity, self.delay, self.pade_order, self.fuzzy_temperature)
        controller.check(params)

    @property
    def run_chunk(self) -> int:
        """Scenarios per chunk as run: ``chunk``, or all of them when there are fewer."""
        return min(self.chunk, self.n_scenarios)

    def fingerprint_fields(self) -> dict[str, Any]:
        """What a resumed run must share with the folder, as plain JSON values: everything (the
        parameters the controller reads, by value) but ``n_scenarios`` (more may be asked of a resumed run), ``chunk`` (the folder records
        the chunk it was run with) and what only the summary and the figures read
        (``percentiles``, ``band_scenarios``: a resume may ask for others), and the dtype and
        the program (``fileio.program``)."""
        d = dataclasses.asdict(self)
        d["beam"] = self.beam._asdict()
        # the parameters the controller runs with: names it does not read, or a paper value
        # given or left out, change nothing (an edited unused k refused a resume)
        d["params"] = {name: value for name, value in param_values(self.params).items() if name in PARAMETERS[self.controller]}
        for name in ("n_scenarios", "chunk", *_SUMMARY_ONLY):
            d.pop(name)
        d["dtype"] = str(jnp.zeros(()).dtype)
        d["program"] = fileio.program()
        return json.loads(json.dumps(fileio.to_jsonable(d, exact=True)))

    def fingerprint(self) -> str:
        """Hash of ``fingerprint_fields``."""
        return fileio.digest(self.fingerprint_fields())


_SUMMARY_ONLY = ("percentiles", "band_scenarios")  # read by the summary and the figures only


def controller_and_params(name: str, params: dict, dt: float, capacity: int, delay: str = "linear", pade_order: int = 8, temperature: float = 0.0) -> tuple[Controller, Any]:
    """The controller ``name`` and its parameters (paper values for missing names); DFS reads
    its ``capacity``-sample buffer with linear interpolation unless ``delay`` says otherwise."""
    return by_name(name, dt=dt, params=params, capacity=capacity, delay=delay, pade_order=pade_order, temperature=temperature)


def metric_names(n_modes: int, reduction: str = REDUCTION_DOC) -> dict[str, str]:
    """Per-scenario metrics and their definitions, including the dB reduction at each mode
    (``reduction``, its "mode i" named: ``REDUCTION_DOC``, or ``REDUCTION_LABEL`` for a figure)."""
    n_modes = beam.check_n_modes(n_modes)
    return {**METRICS, **{f"reduction_db_mode{i + 1}": re.sub(r"\bmode i\b", f"mode {i + 1}", reduction) for i in range(n_modes)}}


def _metrics_row(m: RunMetrics, open_loop_energy: jax.Array, freqs_hz: jax.Array, length_m: float, nyquist_hz: float) -> dict[str, jax.Array]:
    """One scenario's row; ``diverged`` is ``run_diverged``, and the reduction at a mode of
    ``freqs_hz`` at or above ``nyquist_hz`` is NaN."""
    reduction = jnp.where(freqs_hz < nyquist_hz, 10 * (jnp.log10(open_loop_energy) - jnp.log10(m.modal_energy)), jnp.nan)
    return {
        "settling_time_s": m.settling_time_s,
        "peak_tip_deflection_m": m.peak_tip_m,
        "tip_ise": m.tip_ise,
        "control_effort": m.control_effort,
        "final_hub_angle_rad": m.final_hub_angle_rad,
        "diverged": run_diverged(m.diverged, m.peak_tip_m, length_m),
        **{f"reduction_db_mode{i + 1}": reduction[i] for i in range(reduction.shape[0])},
    }


class _Runner:
    """Jitted, sharded chunk evaluation for one configuration."""

    def __init__(self, config: MCConfig):
        self.config = config
        spec = config.scenarios
        self.beam = config.beam
        self.controller, self.params = controller_and_params(
            config.controller, config.params, spec.dt, config.capacity, config.delay, config.pade_order, config.fuzzy_temperature
        )
        self.controller.check(self.params)
        self.nominal = discretize(make_plant(self.beam, config.n_modes), spec.dt, config.method)
        devices = jax.devices()
        self.n_devices = len(devices)
        self.chunk = config.run_chunk
        self.sharding = NamedSharding(Mesh(np.array(devices), ("scenarios",)), PartitionSpec("scenarios"))
        self.key = jax.random.key(config.seed)

        def evaluate(batch: Scenario) -> dict[str, jax.Array]:
            plant = batch_plant(self.beam, config.n_modes, spec.dt, config.method, batch, self.nominal)
            freqs = batch_modes_hz(self.beam, config.n_modes, batch)
            closed = rollout(plant, self.controller, self.params, batch, output="metrics", mode_freqs_hz=freqs, unroll=config.unroll)
            opened = rollout(plant, open_loop(), OpenLoopParams(), batch, output="metrics", mode_freqs_hz=freqs, unroll=config.unroll)
            return jax.vmap(partial(_metrics_row, length_m=self.beam.length_m, nyquist_hz=0.5 / spec.dt))(closed, opened.modal_energy, jnp.broadcast_to(freqs, opened.modal_energy.shape))

        self.evaluate = jax.jit(evaluate)

    def sample(self, index: int) -> Scenario:
        spec = self.config.scenarios if index == 0 else dataclasses.replace(self.config.scenarios, include_paper=False)
        return sample_scenarios(spec, jax.random.fold_in(self.key, index), self.chunk, self.config.n_modes)

    def run_chunk(self, index: int) -> dict[str, np.ndarray]:
        batch = self.sample(index)
        batch = pad_batch(batch, self.n_devices)
        if jax.process_count() == 1:
            out = self.evaluate(jax.device_put(batch, self.sharding))
            return {k: np.asarray(v)[: self.chunk] for k, v in out.items()}
        # Several hosts (jax.distributed): every process drew the same chunk; each hands over
        # the shards its devices hold, and the metrics are gathered back on every process.
        from jax.experimental import multihost_utils

        global_batch = jax.tree.map(lambda a: jax.make_array_from_callback(a.shape, self.sharding, lambda idx, a=np.asarray(a): a[idx]), batch)
        out = self.evaluate(global_batch)
        return {k: np.asarray(multihost_utils.process_allgather(v, tiled=True))[: self.chunk] for k, v in out.items()}


def _chunk_path(out_dir: str, index: int) -> str:
    return os.path.join(out_dir, "chunks", f"chunk_{index:06d}.npz")


def _statistics(values: np.ndarray, percentiles: Sequence[float]) -> dict[str, Any]:
    """Count, mean, std, min, max and percentiles of the finite ``values``, computed in float64
    and given with the digits of the values' own dtype (a float32 run's settling time of
    0.312 s was 0.31200000643730164)."""
    finite = values[np.isfinite(values)].astype(np.float64)
    stats: dict[str, Any] = {"count": int(finite.size), "nonfinite": int(values.size - finite.size)}
    if finite.size == 0:
        return {**stats, "mean": None, "std": None, "min": None, "max": None, **{f"p{p:g}": None for p in percentiles}}
    found = {"mean": finite.mean(), "std": finite.std(), "min": finite.min(), "max": finite.max()}
    found.update({f"p{p:g}": v for p, v in zip(percentiles, np.percentile(finite, list(percentiles)))})
    dtype = values.dtype if values.dtype.kind == "f" else np.float64
    return {**stats, **{name: fileio.shortest(np.asarray(v, dtype)) for name, v in found.items()}}


def summarize(config: MCConfig, columns: dict[str, np.ndarray]) -> dict[str, Any]:
    """Statistics per metric over the non-diverged runs, and the diverged fraction.

    Non-finite values (a settling time of +inf: still outside the band at the end) are
    counted in ``nonfinite`` and left out of the statistics.

    Raises:
      ValueError: naming ``config`` when it is not an MCConfig, or ``columns`` when it lacks
        a column (``diverged`` and ``metric_names``, each one value per run).
    """
    checks.instance("config", config, MCConfig, "build one with MCConfig(...)")
    names = metric_names(config.n_modes)
    if not isinstance(columns, Mapping) or (missing := sorted({*names, "diverged"} - set(columns))):
        raise ValueError(f"columns must map each of {sorted({*names, 'diverged'})} to its values, one per run; "
                         f"{f'missing {missing}' if isinstance(columns, Mapping) else f'got {type(columns).__name__}'}")
    failed = np.asarray(columns["diverged"]).astype(bool)
    ok = ~failed
    return {
        "n_scenarios": int(failed.size),
        "diverged_fraction": float(failed.mean()),
        "diverged_definition": RUN_DIVERGED_DOC,
        "controller": config.controller,
        "params": {name: value for name, value in param_values(config.params).items() if name in PARAMETERS[config.controller]},
        "controller_options": {name: getattr(config, name) for name in CONFIG_OPTIONS},
        "metrics": {name: _statistics(np.asarray(columns[name])[ok], config.percentiles) for name in names},
        "metric_definitions": names,
        "percentiles": list(config.percentiles),
        "scenarios": dataclasses.asdict(config.scenarios),
        "beam": config.beam._asdict(),
        "n_modes": config.n_modes,
        "method": config.method,
        "seed": config.seed,
    }


def run_montecarlo(
    config: MCConfig, out_dir: str | os.PathLike, *, resume: bool = False, progress: bool = True, figures: bool = True, on_chunk: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """Run (or resume) the Monte Carlo; writes chunk files, summary.json (last) and (optionally)
    figures (``FIGURES``). summary.json and the figures are there only when the run has
    finished: resuming removes the previous ones first, once the folder's configuration has
    been checked, and the end writes them staged and moved in together.

    Raises:
      ValueError: bad configuration, or a resume into a folder made by another configuration.
    """
    checks.instance("config", config, MCConfig, "build one with MCConfig(...)")
    resume, progress, figures = (checks.flag(name, value) for name, value in (("resume", resume), ("progress", progress), ("figures", figures)))
    checks.callback("on_chunk", on_chunk, "the chunk's index")
    with fileio.run_lock(out_dir, "out_dir (--out)"):
        return _run_locked(config, os.fspath(out_dir), resume, progress, figures, on_chunk)


def _run_locked(config: MCConfig, out_dir: str, resume: bool, progress: bool, figures: bool, on_chunk: Callable[[int], None] | None) -> dict[str, Any]:
    """``run_montecarlo`` with the folder's run lock held."""
    meta_path, summary_path, chunks_dir = (os.path.join(out_dir, name) for name in (META, "summary.json", "chunks"))
    meta = {"fingerprint": config.fingerprint(), "chunk": config.run_chunk, "n_scenarios": config.n_scenarios, "config": config.fingerprint_fields()}
    # The folder is checked before any sampling or compiling.
    if os.path.exists(meta_path):
        if not resume:
            raise ValueError(f"{out_dir} already holds a Monte Carlo run: pass --resume (resume=True) to continue it, choose another --out (out_dir), or delete the folder to start over in it")
        _check_resume(meta_path, meta, config.n_scenarios)
        if _read_meta(meta_path).get("n_scenarios") != config.n_scenarios:  # the count a later bare --resume goes on to
            fileio.write_json(meta_path, meta)
        # summary.json and the figures are rewritten at the end; until then the previous ones
        # would describe another set of chunks.
        for path in (summary_path, *(os.path.join(out_dir, name) for name in FIGURES)):
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
    elif os.path.isdir(chunks_dir) and os.listdir(chunks_dir):
        # Chunks without the metadata that says which configuration made them: a new run
        # would take them as its own, and a resumed one cannot check them.
        raise ValueError(f"{'--resume: ' if resume else ''}{chunks_dir} holds chunk files but {out_dir} has no {META} to say which run wrote them, "
                         f"so they cannot be used: delete {chunks_dir} and start again{' without --resume' if resume else ''}, or choose another --out (out_dir)")
    elif resume:
        raise ValueError(f"--resume: {out_dir} holds no Monte Carlo run (no {META}); leave out --resume (resume=False) to start one")
    os.makedirs(chunks_dir, exist_ok=True)
    runner = _Runner(config)

    n_chunks = int(math.ceil(config.n_scenarios / runner.chunk))
    keeps = [min(runner.chunk, config.n_scenarios - index * runner.chunk) for index in range(n_chunks)]
    stored = [os.path.exists(_chunk_path(out_dir, index)) for index in range(n_chunks)]
    bar = None
    if resume:  # said with or without the progress bar (--no-progress)
        print(f"montecarlo: resuming: {sum(stored)} of {n_chunks} chunks already in {chunks_dir}", file=sys.stderr, flush=True)
    if not all(stored):  # the bar sat at its start through the compile with no word of it
        print(f"montecarlo: {config.n_scenarios} scenarios in {n_chunks} chunk(s) of {runner.chunk} on {runner.n_devices} device(s), compiling", file=sys.stderr, flush=True)
    heartbeat = None if progress else Heartbeat("montecarlo", "scenarios", config.n_scenarios, sum(k for k, s in zip(keeps, stored) if s))
    if progress:
        from tqdm.auto import tqdm

        # the stored chunks count from the start, so that the bar's rate and time left are those of the chunks run
        bar = tqdm(total=config.n_scenarios, initial=sum(k for k, s in zip(keeps, stored) if s), desc=f"montecarlo {config.controller}", unit="scenario")
    columns: dict[str, list[np.ndarray]] = {}
    try:
        for index in range(n_chunks):
            path = _chunk_path(out_dir, index)
            if stored[index]:
                rows = _load_chunk(path, runner.chunk, config.n_modes)
            else:
                rows = runner.run_chunk(index)
                if not os.path.exists(meta_path):
                    # Written with the first chunk, so that a run failing before it (out of
                    # memory, a bad option found late) leaves no run that blocks the next one.
                    fileio.write_json(meta_path, meta)

                def write(tmp: str, rows=rows) -> None:
                    with open(tmp, "wb") as f:
                        np.savez(f, **rows)

                fileio.atomic_write(path, write)
            keep = keeps[index]
            for k, v in rows.items():
                columns.setdefault(k, []).append(v[:keep])
            if bar is not None and not stored[index]:
                bar.update(keep)
            if heartbeat is not None and not stored[index]:
                heartbeat.update(keep)
            if on_chunk is not None:
                on_chunk(index)
    finally:
        if bar is not None:
            bar.close()
    merged = {k: np.concatenate(v) for k, v in columns.items()}
    summary = summarize(config, merged)
    summary["devices"] = runner.n_devices
    summary["chunk"] = runner.chunk
    summary["dtype"] = meta["config"]["dtype"]
    if figures:  # with or without the bar, as each stage is said
        print("montecarlo: drawing figures", file=sys.stderr, flush=True)
    # staged and moved in together, summary.json last: a run stopped while drawing leaves
    # neither a figure nor the summary (it left the figures drawn so far)
    with fileio.replace_outputs(out_dir, (*FIGURES, "summary.json"), last="summary.json") as stage:
        summary["figures"] = _figures(runner, merged, stage) if figures else []
        fileio.write_json(os.path.join(stage, "summary.json"), summary)
    return summary


def _load_chunk(path: str, chunk: int, n_modes: int) -> dict[str, np.ndarray]:
    """A chunk file's columns, refused by name when it is damaged or incomplete."""
    expected = {*metric_names(n_modes), "diverged"}
    fix = "delete it and pass --resume again to compute that chunk anew"
    try:
        with np.load(path) as data:
            rows = {k: data[k] for k in data.files}
    except OSError as err:
        raise ValueError(f"--resume: cannot read {path} ({err}); {fix}") from None
    except (ValueError, EOFError, zipfile.BadZipFile):  # NumPy's message for some junk is about pickles
        raise ValueError(f"--resume: {path} is damaged (not a chunk's .npz archive); {fix}") from None
    if set(rows) != expected or any(v.shape != (chunk,) for v in rows.values()):
        got = ", ".join(f"{k} {v.shape}" for k, v in sorted(rows.items()))
        raise ValueError(f"--resume: {path} does not hold this run's {chunk}-scenario columns ({got}); {fix}")
    return rows


def _read_meta(meta_path: str) -> Any:
    """The folder's record (``META``), as JSON; ValueError when it cannot be read."""
    try:
        with open(meta_path, encoding="utf-8") as f:
            return json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"--resume: cannot read {meta_path} ({err}); start a new run in another --out") from None


def recorded_settings(out_dir: str | os.PathLike) -> dict[str, Any]:
    """The ``n_scenarios``, ``chunk``, ``unroll``, ``controller`` and ``seed`` that the run in
    ``out_dir`` recorded, those it holds (none when it has no readable record, which
    ``run_montecarlo`` names; no ``n_scenarios`` in a folder written before it was recorded):
    ``jaxflex montecarlo --resume`` runs at them unless told otherwise (it took the first three
    and then refused the default controller and seed as "changed"). A resume with another
    ``n_scenarios`` records that."""
    out_dir = fileio.check_path("out_dir", out_dir, "folder")
    try:
        previous = _read_meta(os.path.join(out_dir, META))
    except ValueError:
        return {}
    config = previous.get("config") if isinstance(previous, dict) else None
    record = previous if isinstance(previous, dict) else {}
    config = config if isinstance(config, dict) else {}
    found = {"n_scenarios": record.get("n_scenarios"), "chunk": record.get("chunk"), "unroll": config.get("unroll"), "seed": config.get("seed")}
    taken: dict[str, Any] = {key: value for key, value in found.items() if isinstance(value, int) and not isinstance(value, bool)}
    if config.get("controller") in CONTROLLERS:
        taken["controller"] = config["controller"]
    return taken


def _check_resume(meta_path: str, meta: dict[str, Any], n_scenarios: int) -> None:
    """Refuse to resume a folder written by another configuration, naming what changed."""
    previous = _read_meta(meta_path)
    before = previous.get("config", {}) if isinstance(previous, dict) and isinstance(previous.get("config"), dict) else {}
    # a folder written while _SUMMARY_ONLY still counted has them in its config and its hash
    same = isinstance(previous, dict) and meta["fingerprint"] in (previous.get("fingerprint"), fileio.digest({k: v for k, v in before.items() if k not in _SUMMARY_ONLY}))
    if not same:
        raise ValueError(f"--resume: {meta_path} was written by a run with another configuration ({fileio.changed_fields(before, meta['config'])}): "
                         "resume with the command that started it, its --config and options, and --resume")
    if previous.get("chunk") != meta["chunk"]:
        chunk = previous.get("chunk")
        fix = f"--chunk {chunk}" if not isinstance(chunk, int) or n_scenarios >= chunk else f"--scenarios {chunk} or more and --chunk {chunk}"
        raise ValueError(
            f"--resume: the run in {os.path.dirname(meta_path)} has chunks of {chunk} scenarios, this one {meta['chunk']} "
            f"(a chunk is capped at the number of scenarios); pass {fix}"
        )


def tip_bands(runner: _Runner, percentiles: Sequence[float]) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Percentiles of the tip deflection's magnitude at each time over the first
    ``band_scenarios`` scenarios of chunk 0 that did not diverge (as in the histograms).
    The magnitude: the scenarios start and are struck with either sign, so the signed
    deflection's median sat at 0 throughout and its bands were mirror images.

    Returns:
      ``(t, bands, kept, count)``: ``bands`` is ``[len(percentiles), T]`` (NaN when every run
      diverged), over ``kept`` of the ``count`` scenarios drawn.
    """
    config = runner.config
    count = min(config.band_scenarios, runner.chunk)
    batch = jax.tree.map(lambda a: a[:count], runner.sample(0))
    spec = config.scenarios

    def run(batch: Scenario) -> tuple[jax.Array, jax.Array]:
        traj = rollout(batch_plant(runner.beam, config.n_modes, spec.dt, config.method, batch, runner.nominal), runner.controller, runner.params, batch)
        tip = traj.z[..., 1]
        return tip, run_diverged(jax.vmap(diverged)(traj.x), jnp.max(jnp.abs(tip), axis=-1), runner.beam.length_m)  # as the chunks' rows

    tips, bad = jax.jit(run)(batch)
    tips = np.abs(np.asarray(tips)[~np.asarray(bad)])  # [kept, T]
    t = np.arange(tips.shape[1]) * spec.dt
    bands = np.percentile(tips, list(percentiles), axis=0) if tips.shape[0] else np.full((len(percentiles), t.size), np.nan)
    return t, bands, tips.shape[0], count


def _figures(runner: _Runner, columns: dict[str, np.ndarray], out_dir: str) -> list[str]:
    from jaxflex import plotting

    ok = ~columns["diverged"].astype(bool)
    names = metric_names(runner.config.n_modes)
    data = {name: columns[name][ok] for name in names}
    labels = metric_names(runner.config.n_modes, REDUCTION_LABEL)
    arm = f"nominal {plotting.arm_label(runner.beam.length_m, beam.natural_frequencies_hz(runner.beam, runner.config.n_modes))}"
    plotting.save(plotting.histograms(data, labels, f"{runner.config.controller}: {int(ok.sum())} of {ok.size} runs (diverged left out)\n{arm}"), os.path.join(out_dir, FIGURES[0]))
    percentiles = sorted(set(runner.config.percentiles) | {50.0})
    t, bands, kept, count = tip_bands(runner, percentiles)
    title = f"{runner.config.controller}: percentiles of |tip deflection| over {kept} of {count} scenarios (diverged left out)\n{arm}"
    plotting.save(plotting.percentile_bands(t, bands, percentiles, "|Tip deflection| (m)", title), os.path.join(out_dir, FIGURES[1]))
    return list(FIGURES)
