"""Closed-loop throughput benchmark: plant steps per second of batched rollouts.

The edge behind ``jaxflex bench`` (and the measuring core of ``benchmarks/bench_rollout.py``).
One configuration is a controller, a sampling method, a dtype, a batch of scenarios, a
horizon and a mode:

* ``"forward"``: ``jit(rollout(..., output="metrics"))`` of the whole batch (one rollout of
  ``B`` scenarios, as the Monte Carlo runner and the tuner run them);
* ``"grad"``: ``jit(value_and_grad)`` of the batch-mean tip ISE through the same rollout,
  with respect to every controller parameter (``wrt="all"``: the whole parameter pytree,
  20 values for DFS+fuzzy) or to the gains ``jaxflex tune`` tunes (``wrt="gains"``: k,
  tau_s, k1-k3, ``controllers.registry.PARAMETERS``; the fuzzy set centres held).

The scenarios of a batch differ in their initial state (random modal displacements and
rates around the paper's) and share one tip-force sequence (a 0.5 N, 10 ms pulse at 0.1 s)
and one sensor-noise sequence, so inputs cost O(T), not O(batch x T), memory. The plant is
the paper's two-mode arm at 1 kHz, closed over as a constant (as the tuner and the Monte
Carlo runner do with the nominal plant).

Timing: the first call (trace, compile, run) is timed apart; then ``runs`` calls, each
ended by ``block_until_ready``. ``steps_per_second`` = batch * horizon / median wall time,
``steps_per_second_best`` uses the fastest call, ``compile_s`` = first call - median call,
and ``cpu_util`` = process CPU time / wall time over the timed calls (about the number of
busy cores; below the core count when other processes compete for the machine).

This module never changes the JAX configuration: float64 rows run inside
``jax.enable_x64(True)``, and several host devices (one per CPU core) are the caller's
choice (``jax.config.update("jax_num_cpu_devices", n)`` before first use; the ``jaxflex
bench`` command makes one per core, ``--cpu-devices``); when there are several devices the
batch is sharded across them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import beam, checks, fileio
from jaxflex.controllers import by_name
from jaxflex.controllers.registry import NAMES, PARAMETERS
from jaxflex.plant import METHODS, discretize, make_plant
from jaxflex.rollout import rollout
from jaxflex.scenarios import Scenario

CONTROLLERS = NAMES
DEFUZZ = ("centroid", "singleton", "smooth")  # the fuzzy part: faithful centroid, singleton, smooth
DTYPES = ("float32", "float64")
MODES = ("forward", "grad")
WRT = ("all", "gains")  # what a gradient row differentiates: every parameter, or the tuned gains
SMOOTH_TEMPERATURE = 0.02  # the smooth mode's temperature (the tuner's recommended range 0.01-0.05)
DT = 1e-3  # s, the paper's 1 kHz
DELAY_SAMPLES = 5  # the paper's tau = 5 ms at DT
N_MODES = 2
WINDOW_S = 1.0  # timed seconds per configuration of `jaxflex bench` (BenchConfig.min_time_s)


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """One benchmark configuration.

    Attributes:
      controller: one of ``CONTROLLERS``.
      defuzz: fuzzy part (``DEFUZZ``): ``"centroid"`` (faithful, exact closed form),
        ``"singleton"``, or ``"smooth"`` (centroid at ``SMOOTH_TEMPERATURE``). Ignored without
        a fuzzy part.
      integrator: ``"rk4"`` or ``"zoh"`` (``plant.discretize``).
      dtype: ``"float32"`` or ``"float64"``.
      batch: number of scenarios, >= 1.
      horizon: samples per scenario, >= 2.
      mode: ``"forward"`` or ``"grad"``.
      wrt: with ``mode="grad"``, what is differentiated (``WRT``): ``"all"`` (every leaf of the
        parameter pytree) or ``"gains"`` (the controller's ``PARAMETERS``, the values
        ``jaxflex tune`` tunes; the fuzzy set centres held). Forward rows keep ``"all"``, and
        their JSON rows record ``wrt`` as null.
      runs: timed calls after the first, >= 1.
      min_time_s: keep calling (after ``runs`` calls) until the timed calls add up to this
        many seconds, >= 0. A call at a small batch takes milliseconds, and a median over a
        few of them samples the host at one instant; a window of a second or two gives the
        typical rate on a host whose speed drifts.
      capacity: DFS delay-buffer capacity in samples, >= 5 (the benchmarked delay is 5
        samples); 64 is ``dfs()``'s default.
      unroll: ``rollout``'s ``unroll`` (samples per compiled loop iteration), >= 1.
    """

    controller: str = "dfs+fuzzy"
    defuzz: str = "centroid"
    integrator: str = "zoh"
    dtype: str = "float32"
    batch: int = 4096
    horizon: int = 1000
    mode: str = "forward"
    wrt: str = "all"
    runs: int = 5
    capacity: int = 64
    min_time_s: float = 0.0
    unroll: int = 1

    def __post_init__(self) -> None:
        for name, allowed in (("controller", CONTROLLERS), ("defuzz", DEFUZZ), ("integrator", METHODS), ("dtype", DTYPES), ("mode", MODES), ("wrt", WRT)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}; got {getattr(self, name)!r}")
        for name, low in (("batch", 1), ("horizon", 2), ("runs", 1), ("capacity", DELAY_SAMPLES), ("unroll", 1)):
            object.__setattr__(self, name, checks.integer(name, getattr(self, name), low))
        object.__setattr__(self, "min_time_s", checks.number("min_time_s", self.min_time_s, unit="seconds"))
        if self.mode == "grad" and self.controller == "open_loop":
            raise ValueError("mode='grad' needs controller parameters; the open loop has none")
        if self.mode == "forward" and self.wrt != "all":
            raise ValueError(f"wrt={self.wrt!r} applies to mode='grad' only; a forward row differentiates nothing (leave wrt='all')")

    @property
    def has_fuzzy(self) -> bool:
        return "fuzzy" in self.controller


def controller_and_params(controller: str, defuzz: str = "centroid", dtype: Any = jnp.float32, capacity: int = 64) -> tuple[Any, Any]:
    """The benchmarked controller and its (paper) parameters in ``dtype``.

    DFS: k = 55 N*m/rad, tau = 5 ms, nearest-sample ring buffer of ``capacity`` samples
    (``dfs()``'s default 64). Fuzzy: k1 = 1.02, k2 = 0.30, k3 = 1.0, the paper's rule table and centres;
    ``defuzz="smooth"`` is the centroid at ``SMOOTH_TEMPERATURE``.
    """
    if defuzz == "smooth":
        return by_name(controller, dt=DT, capacity=capacity, temperature=SMOOTH_TEMPERATURE, dtype=dtype)
    return by_name(controller, dt=DT, capacity=capacity, defuzz=defuzz, dtype=dtype)


def bench_plant(integrator: str, dtype: Any):
    """The paper's two-mode arm sampled at 1 ms, in ``dtype``."""
    params = beam.BeamParams(*(None if v is None else jnp.asarray(v, dtype) for v in beam.BeamParams()))
    return discretize(make_plant(params, N_MODES), DT, integrator)


def bench_inputs_np(batch: int, horizon: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x0`` [batch, n_x], shared ``force`` [horizon, 1] and ``noise`` [horizon, 2], float64 NumPy.

    x0: modal displacements ~ N(0, (1 mm)^2), modal rates ~ N(0, (10 um/s)^2), hub at rest;
    member 0 is the paper's printed initial state. force: 0.5 N from 0.1 s for 10 ms.
    noise: N(0, (10 urad)^2) on the angle and N(0, (1 mrad/s)^2) on the velocity.
    """
    rng = np.random.default_rng(seed)
    n_q = N_MODES + 1
    x0 = np.zeros((batch, 2 * n_q))
    x0[:, 1:n_q] = 1e-3 * rng.standard_normal((batch, N_MODES))
    x0[:, n_q + 1 :] = 1e-5 * rng.standard_normal((batch, N_MODES))
    x0[0] = 0.0
    x0[0, 1], x0[0, n_q + 1] = 1e-3, 1e-5
    force = np.zeros((horizon, 1))
    start = int(round(0.1 / DT))
    force[start : start + 10] = 0.5
    noise = rng.standard_normal((horizon, 2)) * np.array([1e-5, 1e-3])
    return x0, force, noise


def bench_inputs(batch: int, horizon: int, dtype: Any, seed: int = 0) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``bench_inputs_np`` as jnp arrays of ``dtype``."""
    return tuple(jnp.asarray(a, dtype) for a in bench_inputs_np(batch, horizon, seed))


def make_benchmark(cfg: BenchConfig) -> tuple[Callable, tuple]:
    """The jitted function of one configuration and its arguments: ``(params, x0)``, or
    ``(gains, params, x0)`` for a gradient with ``wrt="gains"`` (``gains`` a dict by name)."""
    dtype = jnp.dtype(cfg.dtype)
    plant = bench_plant(cfg.integrator, dtype)
    controller, params = controller_and_params(cfg.controller, cfg.defuzz, dtype, cfg.capacity)
    x0, force, noise = bench_inputs(cfg.batch, cfg.horizon, dtype)
    devices = jax.devices()
    sharded = len(devices) > 1 and cfg.batch % len(devices) == 0
    if sharded:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        mesh = Mesh(np.array(devices), ("batch",))
        x0 = jax.device_put(x0, NamedSharding(mesh, PartitionSpec("batch")))

    def metrics(params, x0):
        return rollout(plant, controller, params, Scenario(x0, force, noise), output="metrics", unroll=cfg.unroll)

    if cfg.mode == "forward":
        return jax.jit(metrics), (params, x0)

    def loss(params, x0):
        return jnp.mean(metrics(params, x0).tip_ise)

    # What is differentiated comes first; the parameters (and their held leaves) and x0 follow.
    if cfg.wrt == "all":
        objective, lead = loss, (params,)
    else:
        objective, lead = (lambda gains, params, x0: loss(_with_gains(params, gains), x0)), (_gains(cfg.controller, params), params)
    if not sharded:
        return jax.jit(jax.value_and_grad(objective)), (*lead, x0)

    # Data parallel: each device differentiates the mean over its own shard, then one psum.
    # Under plain jit with a sharded batch, the parameter cotangent is reduced over the batch
    # in every reverse step, and the compiled reverse loop body holds an all-reduce (checked
    # in its HLO). check_vma=False: the rollout's scan carries start from constants (zeros),
    # which shard_map's varying-axes check would reject as carries that turn varying.
    n_dev = len(devices)

    def local(*args):
        value, grad = jax.value_and_grad(objective)(*args)
        return jax.lax.psum(value, "batch") / n_dev, jax.tree.map(lambda g: jax.lax.psum(g, "batch") / n_dev, grad)

    replicated = PartitionSpec()
    fn = jax.shard_map(local, mesh=mesh, in_specs=(*(replicated for _ in lead), PartitionSpec("batch")), out_specs=(replicated, replicated), check_vma=False)
    return jax.jit(fn), (*lead, x0)


def _parts(params: Any) -> tuple[Any, ...]:
    """The NamedTuples of a parameter pytree: one, or the pair of a combined controller."""
    return (params,) if hasattr(params, "_fields") else tuple(params)


def _gains(controller: str, params: Any) -> dict[str, jax.Array]:
    """The gains of ``params`` that ``jaxflex tune`` tunes (``PARAMETERS[controller]``), by name."""
    return {name: getattr(part, name) for part in _parts(params) for name in part._fields if name in PARAMETERS[controller]}


def _with_gains(params: Any, gains: dict[str, jax.Array]) -> Any:
    """``params`` with the named gains replaced, the other leaves as they are."""
    parts = tuple(part._replace(**{name: value for name, value in gains.items() if name in part._fields}) for part in _parts(params))
    return parts[0] if hasattr(params, "_fields") else parts


def device_info() -> dict[str, Any]:
    """Device, machine and version fields shared by every row."""
    dev = jax.devices()[0]
    info = {
        "device": dev.platform,
        "device_kind": dev.device_kind,
        "n_devices": len(jax.devices()),
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "python": platform.python_version(),
    }
    if dev.platform == "cpu":
        info["gpu"] = "no GPU available in this session"
    return info


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; all cores off Linux)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's model name, with its family and model numbers where Linux gives them.

    A virtual machine may report only "AMD EPYC" for different generations (family 23 is
    Zen 1, 25 is Zen 3), whose rates differ by more than the spread of a run.
    """
    fields: dict[str, str] = {}
    try:
        with open(cpuinfo, encoding="utf-8") as f:
            for line in f:
                if not line.strip():
                    break  # the first processor's block
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    name = fields.get("model name") or platform.processor() or "unknown"
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def time_calls(fn: Callable, args: tuple, runs: int, min_time_s: float = 0.0) -> dict[str, float]:
    """First-call and steady-state timings of ``fn(*args)`` (each ended by block_until_ready):
    at least ``runs`` timed calls (>= 1), and more until they add up to ``min_time_s`` seconds.

    Raises:
      ValueError: naming ``runs`` or ``min_time_s`` and the accepted range.
    """
    runs = checks.integer("runs", runs)
    min_time_s = checks.number("min_time_s", min_time_s, unit="seconds")
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    walls, cpus = [], []
    while len(walls) < runs or sum(walls) < min_time_s:
        start, cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
    median = float(np.median(walls))
    return {
        "first_call_s": first,
        "median_s": median,
        "min_s": float(min(walls)),
        "p10_s": float(np.percentile(walls, 10)),
        "p90_s": float(np.percentile(walls, 90)),
        "compile_s": max(first - median, 0.0),
        "cpu_util": float(sum(cpus) / sum(walls)),
        "runs": len(walls),
        "window_s": float(sum(walls)),
    }


def measure(cfg: BenchConfig) -> dict[str, Any]:
    """Run one configuration; returns its JSON row."""
    with jax.enable_x64(cfg.dtype == "float64"):
        fn, args = make_benchmark(cfg)
        timing = time_calls(fn, args, cfg.runs, cfg.min_time_s)
    steps = cfg.batch * cfg.horizon
    row = {"kind": "rollout", **dataclasses.asdict(cfg)}
    if not cfg.has_fuzzy:
        row["defuzz"] = None
    if "dfs" not in cfg.controller:
        row["capacity"] = None
    if cfg.mode == "forward":
        row["wrt"] = None
    row.update(timing)
    row["steps_per_second"] = steps / timing["median_s"]
    row["steps_per_second_best"] = steps / timing["min_s"]
    row["steps_per_second_p10"] = steps / timing["p90_s"]  # the slowest tenth of the calls
    row["steps_per_second_p90"] = steps / timing["p10_s"]
    row.update(device_info())
    return row


def quick_configs() -> list[BenchConfig]:
    """The quick subset (under two minutes on 2 CPU cores): every controller and both
    integrators in float32 forward at batch 4096, the fuzzy defuzzifiers, float64 and the
    gradients of the paper's DFS+fuzzy controller (every parameter, and the tuned gains) beside
    its forward pass at the same batch."""
    quick = {"horizon": 500, "min_time_s": WINDOW_S}
    cfgs = [BenchConfig(controller=c, integrator=i, **quick) for c in CONTROLLERS for i in METHODS]
    cfgs += [BenchConfig(defuzz=d, **quick) for d in ("singleton", "smooth")]
    cfgs += [BenchConfig(dtype="float64", **quick)]
    cfgs += [BenchConfig(batch=1024, **quick)] + [BenchConfig(mode="grad", wrt=wrt, batch=1024, runs=3, **quick) for wrt in WRT]
    return cfgs


def format_spread(row: dict[str, Any]) -> str:
    """A row's middle 80 % of per-call rates and its number of timed calls, as
    ``p10-p90 (calls)``; ``-`` for rows from before these fields."""
    if "steps_per_second_p10" not in row:
        return "-"
    return f"{row['steps_per_second_p10']:.3g}-{row['steps_per_second_p90']:.3g} ({row['runs']})"


def mode_label(row: dict[str, Any]) -> str:
    """A row's mode as the tables print it: ``"grad (gains)"`` for a gradient over the tuned gains."""
    return f"{row['mode']} (gains)" if row.get("wrt") == "gains" else row["mode"]


SAME_PROGRAM = ("controller", "defuzz", "integrator", "dtype", "batch", "horizon", "capacity", "unroll", "device", "n_devices")
"""The fields in which a gradient row and its forward row agree (``gradient_ratios``)."""


def gradient_ratios(rows: Sequence[dict[str, Any]]) -> list[str]:
    """One line per gradient row that has a forward row of the same loop and batch
    (``SAME_PROGRAM``): its rate as a fraction of the forward rate, the figure the issue's
    25 % target is about (set across two batches, the ratio also holds the batch's effect)."""
    lines = []
    for grad in (r for r in rows if r.get("mode") == "grad"):
        key = tuple(grad.get(f) for f in SAME_PROGRAM)
        forward = next((r for r in rows if r.get("mode") == "forward" and tuple(r.get(f) for f in SAME_PROGRAM) == key), None)
        if forward is not None:
            ratio = grad["steps_per_second"] / forward["steps_per_second"]
            over = f" over {', '.join(PARAMETERS[grad['controller']])}" if grad.get("wrt") == "gains" else ""
            lines.append(f"value_and_grad{over} {grad['controller']}/{grad['defuzz'] or '-'} {grad['integrator']} {grad['dtype']} B={grad['batch']}: {ratio:.1%} of the forward rate at the same batch")
    return lines


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """A plain-text table of benchmark rows."""
    head = f"{'controller':<10} {'defuzz':<9} {'integ':<5} {'dtype':<7} {'batch':>6} {'mode':<12} {'steps/s':>10} {'p10-p90 (calls)':>23} {'compile s':>9} {'cpu util':>8}"
    lines = [head, "-" * len(head)]
    for r in rows:
        spread = format_spread(r)
        lines.append(
            f"{r['controller']:<10} {r['defuzz'] or '-':<9} {r['integrator']:<5} {r['dtype']:<7} {r['batch']:>6} {mode_label(r):<12} "
            f"{r['steps_per_second']:>10.3g} {spread:>23} {r['compile_s']:>9.2f} {r['cpu_util']:>8.2f}"
        )
    lines += gradient_ratios(rows)
    if rows:
        r = rows[0]
        lines.append(f"device: {r['device']} ({r['device_kind']}, {r['n_devices']} device(s)), {r['cpu_model']}, jax {r['jax_version']}")
        if "gpu" in r:
            lines.append(f"GPU: {r['gpu']}")
    return "\n".join(lines)


def run_bench(json_path: str | os.PathLike | None = None, quick: bool = True, *, configs: Sequence[BenchConfig] | None = None, progress: Callable[[str], None] | None = print) -> list[dict[str, Any]]:
    """Run the benchmark; print a table; optionally write one JSON object per line.

    Args:
      json_path: file for the rows (JSON Lines: one object per configuration), or None;
        written atomically once every configuration has run.
      quick: the quick subset (``quick_configs``, under two minutes on 2 cores); False adds
        the batch sweep of the paper's DFS+fuzzy controller (1 .. 65536) and float64 for
        every controller (several minutes). ``benchmarks/bench_rollout.py`` is the full suite.
      configs: explicit configurations instead (tests use tiny ones).
      progress: called with one line per finished configuration and with the table (None:
        silent).

    Returns:
      The rows (dicts with at least ``controller``, ``integrator``, ``dtype``, ``batch``,
      ``mode``, ``steps_per_second``, ``compile_s``, ``device``).
    """
    if configs is None:
        configs = quick_configs()
        if not quick:
            configs += [BenchConfig(batch=b, min_time_s=WINDOW_S) for b in (1, 16, 256, 1024, 16384, 65536)]
            configs += [BenchConfig(controller=c, dtype="float64", min_time_s=WINDOW_S) for c in CONTROLLERS]
    rows = []
    for cfg in configs:
        row = measure(cfg)
        rows.append(row)
        if progress is not None:
            progress(f"{cfg.controller}/{row['defuzz'] or '-'} {cfg.integrator} {cfg.dtype} B={cfg.batch} {mode_label(row)}: {row['steps_per_second']:.3g} steps/s")
    if json_path is not None:  # at the end and atomically: an interrupted run leaves an earlier file whole
        fileio.write_text(json_path, "".join(json.dumps(fileio.to_jsonable(row), allow_nan=False) + "\n" for row in rows))
    if progress is not None:
        progress(format_table(rows))
    return rows
