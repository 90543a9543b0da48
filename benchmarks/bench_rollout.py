"""Closed-loop rollout benchmark: plant steps per second against batch size, controller,
sampling method, dtype and mode, with NumPy / python-control / scikit-fuzzy baselines.

Prints one JSON line per configuration (style.md section 8); ``--out FILE.json`` also writes
them as one JSON document ``{"meta": ..., "rows": [...]}``. Until the run ends, the document
is ``FILE.json.partial``, rewritten atomically after every row (``FILE.json``, say an earlier
run's results, stays as it was); ``--resume`` continues an interrupted run from it: the
sections it finished are kept and the others run again (with the same options, on the same
machine and JAX setup).
``--tables FILE.json ...`` turns result documents into the Markdown tables of
``benchmarks/README.md``.

Sections (``--section``, default all):

* ``matmul``: the float32 matmul rate of this machine (jnp.dot and NumPy), the reference for
  the FLOP fraction.
* ``sweep``: the paper's DFS+fuzzy controller (faithful centroid, ZOH, float32) forward over
  batch sizes 1 .. 131072 (while memory allows), the singleton and smooth variants and the
  gradient at a few sizes (over every parameter; ``--grad-wrt gains`` for the tuned gains).
* ``matrix``: every controller x {rk4, zoh} x {float32, float64} x {forward, grad} at one
  batch size.
* ``capacity``: DFS and DFS+fuzzy forward with delay buffers of 64 (``dfs()``'s default),
  16 and 8 samples, for the same 5-sample delay.
* ``memory``: compiled memory of metrics-only and trajectory rollouts at two horizons.
* ``flops``: floating-point operations per closed-loop step, counted on the rollout's jaxpr;
  and per step of ``value_and_grad`` against the forward pass, on the jaxprs and on the
  programs XLA compiles (``grad_ops_per_step``).
* ``baselines``: NumPy (batch 4096), python-control and scikit-fuzzy (one scenario, short
  horizon), each checked against jaxflex before it is timed, with jaxflex timed beside them.
* ``ab``: the rollout and fuzzy modules of git revision ``--ab-rev`` (before the layout
  changes) against the working tree's, in one process, timed in interleaved rounds.
* ``cost``: the open loop and DFS+fuzzy (singleton and centroid) forward at ``--cost-batches``,
  timed in interleaved rounds, and a straight line through each one's time per step against
  the scenarios per device: a fixed cost per step and a cost per scenario-step, whose
  inverse bounds the rate at any batch.
* ``unroll``: ``lax.scan``'s ``unroll`` (``--unrolls``) for three programs: the DFS+fuzzy
  rollout forward (``--unroll-batches``) and value_and_grad (``--grad-batch``), and a Monte
  Carlo chunk (``--unroll-batches`` scenarios of the default ``MCConfig``: a batch of
  plants, the closed and the open loop over 3 s). Each program's unrolls are timed in
  interleaved rounds, and their outputs compared with the first unroll's.

Examples::

    python benchmarks/bench_rollout.py --out benchmarks/results/cpu_default.json
    python benchmarks/bench_rollout.py --host-devices 2 --no-intra-op-threads --section sweep matrix
    taskset -c 1 python benchmarks/bench_rollout.py --section sweep --out benchmarks/results/cpu_1core.json
    python benchmarks/bench_rollout.py --tables benchmarks/results/*.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any, Callable

SECTIONS = ("matmul", "flops", "memory", "baselines", "sweep", "matrix", "capacity", "ab", "cost", "unroll")
CAPACITIES = (64, 16, 8)  # DFS buffer sizes of the capacity section (the delay is 5 samples)
AB_REV = "620479b"  # the last commit before the layout changes of rollout.py and fuzzy.py
SWEEP_BATCHES = (1, 16, 256, 1024, 4096, 16384, 65536, 131072)
MAX_SWEEP_STEPS = 1.4e8  # default cap on batch * horizon of one call in the sweep (CPU time)
VARIANT_BATCHES = (1024, 4096, 16384)  # sweep batches of the singleton, smooth and RK4 rows
COST_BATCHES = (2048, 4096, 8192, 16384, 32768)  # batches of the cost section
UNROLLS = (1, 2, 8)  # scan unrolls of the unroll section
RTOL_NUMPY = 1e-10  # float64, same arithmetic in another order (observed ~3e-15)
RTOL_CONTROL = 1e-10  # python-control: float64, the same maps (observed ~1e-14)
# scikit-fuzzy integrates the centroid on a sampled universe (2001 points, step 1e-3): each
# clip kink between samples moves the area and moment by <= DU^2 / 4 (tests/test_fuzzy.py),
# so the surface is off by ~1e-6 relative where rules fire well; along a closed loop that
# stays O(1e-5) of the peak (observed 4e-6).
RTOL_SKFUZZY = 1e-4


def _setup_jax(args: argparse.Namespace) -> None:
    """Host devices and XLA flags must be set before JAX starts its backend."""
    if args.no_intra_op_threads:
        flag = "--xla_cpu_multi_thread_eigen=false"
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()
    import jax

    if args.host_devices > 1:
        jax.config.update("jax_num_cpu_devices", args.host_devices)


def _meta() -> dict[str, Any]:
    import jax
    import numpy as np

    from jaxflex.bench import device_info, usable_cores

    meta = device_info()
    meta.update(
        {
            "affinity_cores": usable_cores(),
            "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
            "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "scipy_version": _version("scipy"),
            "control_version": _version("control"),
            "skfuzzy_version": _version("skfuzzy"),
            "command": " ".join(sys.argv),
            "xla_python_client_mem_fraction": os.environ.get("XLA_PYTHON_CLIENT_MEM_FRACTION"),
        }
    )
    if jax.devices()[0].platform != "cpu":
        meta["gpu"] = meta["device_kind"]
    del jax, np
    return meta


def _peak_device_bytes() -> int | None:
    """The most memory the first device held during the run (GPU allocators); None on the CPU."""
    import jax

    stats = jax.devices()[0].memory_stats()
    return stats.get("peak_bytes_in_use") if stats else None


def _version(module: str) -> str | None:
    try:
        return __import__(module).__version__
    except Exception:  # noqa: BLE001 - a missing optional package
        return None


class Emitter:
    """Prints each row as one JSON line and keeps it, tagged with the section that measured it.

    With ``out`` (the run's ``.partial`` document), the result document ``{"meta": ...,
    "rows": [...]}`` is rewritten there (atomically) after every row, so that an interrupted
    run keeps what it measured;
    ``rows`` are those a resumed run keeps from the document it resumes.
    """

    def __init__(self, meta: dict[str, Any], out: str | None = None, rows: list[dict[str, Any]] | None = None):
        self.meta = meta
        self.out = out
        self.rows: list[dict[str, Any]] = list(rows or [])
        self.section: str | None = None

    def __call__(self, row: dict[str, Any]) -> None:
        row = {**row, "affinity_cores": self.meta["affinity_cores"], "section": self.section}
        self.rows.append(row)
        print(json.dumps(_jsonable(row)), flush=True)
        self.save()

    def save(self, path: str | None = None) -> None:
        """Write the result document to ``path``, by default ``out`` (nothing without either)."""
        path = path or self.out
        if path is not None:
            from jaxflex.fileio import write_json

            write_json(path, {"meta": self.meta, "rows": self.rows})


def _jsonable(value: Any) -> Any:
    from jaxflex.fileio import to_jsonable

    return to_jsonable(value)


# -- matmul ------------------------------------------------------------------------------------


def section_matmul(emit: Callable, runs: int) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxflex.bench import time_calls

    for n in (1024, 2048, 4096):
        a = jnp.asarray(np.random.default_rng(0).standard_normal((n, n)), jnp.float32)
        t = time_calls(jax.jit(jnp.dot), (a, a), runs)
        a_np = np.asarray(a)
        walls = []
        for _ in range(runs):
            start = time.perf_counter()
            a_np @ a_np
            walls.append(time.perf_counter() - start)
        flops = 2.0 * n**3
        emit({"kind": "matmul", "n": n, "dtype": "float32", "jax_gflops": flops / t["median_s"] / 1e9, "jax_gflops_best": flops / t["min_s"] / 1e9, "numpy_gflops": flops / float(np.median(walls)) / 1e9, "numpy_gflops_best": flops / min(walls) / 1e9, "cpu_util": t["cpu_util"]})


# -- flops -------------------------------------------------------------------------------------

_ONE_FLOP = {"add", "sub", "mul", "div", "max", "min", "neg", "abs", "select_n", "gt", "lt", "ge", "le", "eq", "ne", "sign", "floor", "round", "clamp", "add_any"}
_SELECT_MIN_MAX = (["lt", "select_n"], ["gt", "select_n"])  # controllers/fuzzy.py's _select_op
_TRANSCENDENTAL = {"exp", "log", "log1p", "logistic", "tanh", "sin", "cos", "sqrt", "rsqrt", "expm1", "pow"}


def _counted_names(jaxpr: Any) -> list[str]:
    """The ``_ONE_FLOP`` primitives of a jaxpr in order, with those of nested jaxprs (``jit``)
    in place (dtype conversions and other data movement left out)."""
    names = []
    for eqn in jaxpr.eqns:
        inner = eqn.params.get("jaxpr")
        if inner is not None:
            names += _counted_names(getattr(inner, "jaxpr", inner))
        elif eqn.primitive.name in _ONE_FLOP:
            names.append(eqn.primitive.name)
    return names


def count_flops(jaxpr: Any) -> tuple[int, int]:
    """(arithmetic, transcendental) floating-point operations of a jaxpr, recursing into
    sub-jaxprs; an elementwise op counts once per output element, ``integer_pow`` as its
    multiplications, ``dot_general`` as 2 M N K."""
    import numpy as np

    arith = trans = 0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        out = eqn.outvars[0].aval if eqn.outvars else None
        size = int(np.prod(out.shape)) if out is not None and hasattr(out, "shape") else 1
        if name == "custom_jvp_call" and _counted_names(eqn.params["call_jaxpr"].jaxpr) in _SELECT_MIN_MAX:
            arith += size  # the fuzzy controller's min or max as compare and select: one op, as jnp.minimum
            continue
        floating = out is not None and hasattr(out, "dtype") and np.issubdtype(out.dtype, np.floating)
        compare = name in {"gt", "lt", "ge", "le", "eq", "ne"} and np.issubdtype(eqn.invars[0].aval.dtype, np.floating)
        if name in _ONE_FLOP and (floating or compare):
            arith += size
        elif name == "integer_pow" and floating:
            arith += size * max(abs(int(eqn.params["y"])) - 1, 1)
        elif name in _TRANSCENDENTAL and floating:
            trans += size
        elif name == "dot_general" and floating:
            (contract, _), _ = eqn.params["dimension_numbers"]
            k = int(np.prod([eqn.invars[0].aval.shape[d] for d in contract]))
            arith += 2 * size * k
        elif name == "reduce_sum" and floating:
            arith += int(np.prod(eqn.invars[0].aval.shape))
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None and hasattr(inner, "eqns"):
                    a, t = count_flops(inner)
                    arith, trans = arith + a, trans + t
                elif hasattr(sub, "eqns"):
                    a, t = count_flops(sub)
                    arith, trans = arith + a, trans + t
    return arith, trans


def _rollout_jaxprs(controller: str, defuzz: str, integrator: str = "zoh") -> tuple[Any, Any]:
    """The closed jaxprs of one unbatched scenario's tip ISE and of its ``value_and_grad``
    with respect to every controller parameter (8 steps: the scan bodies do not depend on it)."""
    import jax
    import jax.numpy as jnp

    from jaxflex.bench import bench_inputs, bench_plant, controller_and_params
    from jaxflex.rollout import rollout
    from jaxflex.scenarios import Scenario

    plant = bench_plant(integrator, jnp.float32)
    ctrl, params = controller_and_params(controller, defuzz, jnp.float32)
    x0, force, noise = bench_inputs(1, 8, jnp.float32)
    ise = lambda p, x: rollout(plant, ctrl, p, Scenario(x, force, noise), output="metrics").tip_ise  # noqa: E731
    return jax.make_jaxpr(ise)(params, x0[0]), jax.make_jaxpr(jax.value_and_grad(ise))(params, x0[0])


def _scans(jaxpr: Any) -> list[Any]:
    """The scan equations of a jaxpr, outermost first, recursing into sub-jaxprs."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            found.append(eqn)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found += _scans(inner)
    return found


def flops_per_step(controller: str, defuzz: str, integrator: str = "zoh") -> tuple[int, int]:
    """Per-step FLOPs of the metrics rollout: the scan body of one unbatched scenario."""
    forward, _ = _rollout_jaxprs(controller, defuzz, integrator)
    return count_flops(_scans(forward.jaxpr)[0].params["jaxpr"].jaxpr)


def grad_ops_per_step(controller: str, defuzz: str, batch: int = 4096) -> dict[str, Any]:
    """Operations per step of ``value_and_grad`` against the forward pass, counted twice.

    * On the jaxprs JAX builds (``count_flops``, arithmetic and transcendental together): the
      forward scan body, and the two scans of ``value_and_grad``: its forward pass, which also
      writes the residuals, and its reverse pass.
    * On the programs XLA compiles for the benchmark (``jaxflex.bench.make_benchmark``, one
      device, ``batch`` scenarios): ``cost_analysis()["flops"]`` per scenario. XLA counts a
      loop body once, and after fusion, so a value copied into several kernels counts once
      in each.

    The ratio forward / value_and_grad of either count is the throughput ratio that the same
    rate per operation would give."""
    import jax

    from jaxflex.bench import BenchConfig, make_benchmark

    forward, grad = _rollout_jaxprs(controller, defuzz)
    jaxpr_forward = sum(count_flops(_scans(forward.jaxpr)[0].params["jaxpr"].jaxpr))
    jaxpr_grad = [sum(count_flops(e.params["jaxpr"].jaxpr)) for e in _scans(grad.jaxpr)]
    xla = {}
    for mode in ("forward", "grad"):
        fn, args = make_benchmark(BenchConfig(controller=controller, defuzz=defuzz, mode=mode, batch=batch, horizon=100))
        cost = fn.lower(*args).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, list) else cost
        xla[mode] = float(cost["flops"]) / batch
    return {
        "batch": batch,
        "n_params": sum(int(leaf.size) for leaf in jax.tree.leaves(args[0])),
        "jaxpr_forward": jaxpr_forward,
        "jaxpr_grad_scans": jaxpr_grad,
        "jaxpr_ratio": jaxpr_forward / sum(jaxpr_grad),
        "xla_forward": xla["forward"],
        "xla_grad": xla["grad"],
        "xla_ratio": xla["forward"] / xla["grad"],
    }


def section_flops(emit: Callable) -> None:
    for controller, defuzz in (("open_loop", "centroid"), ("dfs", "centroid"), ("fuzzy", "centroid"), ("fuzzy", "singleton"), ("fuzzy", "smooth"), ("dfs+fuzzy", "centroid"), ("dfs+fuzzy", "singleton"), ("dfs+fuzzy", "smooth")):
        arith, trans = flops_per_step(controller, defuzz)
        row = {"controller": controller, "defuzz": None if "fuzzy" not in controller else defuzz}
        emit({"kind": "flops", **row, "flops_per_step": arith, "transcendental_per_step": trans})
        if controller != "open_loop":
            emit({"kind": "grad_ops", **row, **grad_ops_per_step(controller, defuzz)})


# -- memory ------------------------------------------------------------------------------------


def section_memory(emit: Callable, batch: int) -> None:
    import jax
    import jax.numpy as jnp

    from jaxflex.bench import bench_inputs, bench_plant, controller_and_params
    from jaxflex.rollout import rollout
    from jaxflex.scenarios import Scenario

    plant = bench_plant("zoh", jnp.float32)
    ctrl, params = controller_and_params("dfs+fuzzy", "centroid", jnp.float32)
    for output in ("metrics", "trajectory"):
        for horizon in (1000, 10000):
            x0, force, noise = bench_inputs(batch, horizon, jnp.float32)

            def f(p, x0, force, noise):
                return rollout(plant, ctrl, p, Scenario(x0, force, noise), output=output)

            compiled = jax.jit(f).lower(params, x0, force, noise).compile()
            m = compiled.memory_analysis()
            emit(
                {
                    "kind": "memory",
                    "controller": "dfs+fuzzy",
                    "output": output,
                    "batch": batch,
                    "horizon": horizon,
                    "dtype": "float32",
                    "temp_bytes": int(m.temp_size_in_bytes),
                    "argument_bytes": int(m.argument_size_in_bytes),
                    "output_bytes": int(m.output_size_in_bytes),
                    "peak_bytes": int(m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes - m.alias_size_in_bytes),
                }
            )


# -- baselines ---------------------------------------------------------------------------------


def _rel_err(a: Any, b: Any) -> float:
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def check_baselines(batch: int = 8, horizon: int = 300, skfuzzy_horizon: int = 300, control_horizon: int = 300, controllers: tuple[str, ...] = ("open_loop", "dfs", "fuzzy", "dfs+fuzzy")) -> list[dict[str, Any]]:
    """Every baseline against the jaxflex trajectory in float64 (raises on disagreement).

    NumPy: every controller in ``controllers`` (both faithful defuzzifiers) on ``batch``
    scenarios; scikit-fuzzy and python-control: DFS+fuzzy on one scenario (python-control
    without sensor noise).
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    from benchmarks import baselines as bl
    from jaxflex.bench import bench_inputs, bench_plant, controller_and_params
    from jaxflex.rollout import rollout
    from jaxflex.scenarios import Scenario

    rows = []
    with jax.enable_x64(True):
        plant = bench_plant("zoh", jnp.float64)
        pa = bl.plant_arrays(plant, np.float64)
        x0, force, noise = bench_inputs(batch, horizon, jnp.float64)
        for controller in controllers:
            for defuzz in ("centroid", "singleton") if "fuzzy" in controller else ("centroid",):
                ctrl, params = controller_and_params(controller, defuzz, jnp.float64)
                traj = rollout(plant, ctrl, params, Scenario(x0, force, noise))
                ref = bl.numpy_closed_loop(pa, bl.loop_spec(controller, defuzz), np.asarray(x0), np.asarray(force), np.asarray(noise), record=True)
                err = max(_rel_err(ref["x"].transpose(1, 0, 2), traj.x), _rel_err(ref["u"].T, traj.u[..., 0]) if controller != "open_loop" else 0.0)
                rows.append({"kind": "baseline_check", "baseline": "numpy", "controller": controller, "defuzz": defuzz if "fuzzy" in controller else None, "max_rel_err": err, "rtol": RTOL_NUMPY})
        ctrl, params = controller_and_params("dfs+fuzzy", "centroid", jnp.float64)
        spec = bl.loop_spec("dfs+fuzzy")
        one = Scenario(x0[1, :], force[:skfuzzy_horizon], noise[:skfuzzy_horizon])
        traj = rollout(plant, ctrl, params, one)
        sk = bl.skfuzzy_closed_loop(pa, spec, np.asarray(one.x0), np.asarray(one.force), np.asarray(one.noise))
        err = max(_rel_err(sk["x"], traj.x), _rel_err(sk["u"], traj.u[:, 0]))
        rows.append({"kind": "baseline_check", "baseline": "skfuzzy", "controller": "dfs+fuzzy", "defuzz": "centroid", "max_rel_err": err, "rtol": RTOL_SKFUZZY})
        quiet = Scenario(x0[1, :], force[:control_horizon], jnp.zeros_like(noise[:control_horizon]))
        traj = rollout(plant, ctrl, params, quiet)
        pc = bl.python_control_closed_loop(pa, spec, np.asarray(quiet.x0), np.asarray(quiet.force))
        err = max(_rel_err(pc["x"], traj.x), _rel_err(pc["u"], traj.u[:, 0]))
        rows.append({"kind": "baseline_check", "baseline": "python-control", "controller": "dfs+fuzzy", "defuzz": "centroid", "max_rel_err": err, "rtol": RTOL_CONTROL})
    for row in rows:
        if not row["max_rel_err"] <= row["rtol"]:
            raise AssertionError(f"baseline disagrees with jaxflex: {row}")
    return rows


def _config_maker(runs: int, min_time: float, horizon: int) -> Callable[..., Any]:
    """``BenchConfig`` with this run's horizon and timing. Gradient rows time half as many calls
    (at least 2), each being several times slower; the window ``min_time`` applies to both."""
    from jaxflex.bench import BenchConfig

    def make(**fields: Any) -> Any:
        calls = max(runs // 2, 2) if fields.get("mode") == "grad" else runs
        return BenchConfig(**{"horizon": horizon, "runs": calls, "min_time_s": min_time, **fields})

    return make


def section_baselines(emit: Callable, runs: int, min_time: float, batch: int, horizon: int, short_horizon: int) -> None:
    import jax.numpy as jnp
    import numpy as np

    import jax

    from benchmarks import baselines as bl
    from jaxflex.bench import bench_inputs_np, bench_plant, measure

    config = _config_maker(runs, min_time, horizon)

    for row in check_baselines():
        emit(row)
    spec = bl.loop_spec("dfs+fuzzy")
    with jax.enable_x64(True):
        plant64 = bl.plant_arrays(bench_plant("zoh", jnp.float64), np.float64)
    # NumPy, batched, in both dtypes, the same configuration as jaxflex's beside it.
    for dtype in ("float32", "float64"):
        pa = {k: v.astype(dtype) for k, v in plant64.items()}
        x0, force, noise = (a.astype(dtype) for a in bench_inputs_np(batch, horizon))
        walls = []
        for _ in range(max(runs // 2, 2)):
            start = time.perf_counter()
            bl.numpy_closed_loop(pa, spec, x0, force, noise)
            walls.append(time.perf_counter() - start)
        emit({"kind": "baseline", "baseline": "numpy", "controller": "dfs+fuzzy", "defuzz": "centroid", "integrator": "zoh", "dtype": dtype, "batch": batch, "horizon": horizon, "median_s": float(np.median(walls)), "steps_per_second": batch * horizon / float(np.median(walls)), "steps_per_second_best": batch * horizon / min(walls)})
        emit({**measure(config(dtype=dtype, batch=batch)), "kind": "rollout_vs_baseline"})
    # One scenario: python-control and scikit-fuzzy per step, jaxflex at batch 1 beside them.
    pa = plant64
    x0, force, noise = bench_inputs_np(2, short_horizon)
    start = time.perf_counter()
    bl.python_control_closed_loop(pa, spec, x0[1], force)
    wall = time.perf_counter() - start
    emit({"kind": "baseline", "baseline": "python-control", "controller": "dfs+fuzzy", "defuzz": "centroid", "integrator": "zoh", "dtype": "float64", "batch": 1, "horizon": short_horizon, "median_s": wall, "steps_per_second": short_horizon / wall, "seconds_per_step": wall / short_horizon})
    start = time.perf_counter()
    bl.skfuzzy_closed_loop(pa, spec, x0[1], force, noise)
    wall = time.perf_counter() - start
    emit({"kind": "baseline", "baseline": "skfuzzy", "controller": "dfs+fuzzy", "defuzz": "centroid", "integrator": "zoh", "dtype": "float64", "batch": 1, "horizon": short_horizon, "median_s": wall, "steps_per_second": short_horizon / wall, "seconds_per_step": wall / short_horizon})
    for dtype in ("float64", "float32"):
        emit({**measure(config(dtype=dtype, batch=1)), "kind": "rollout_vs_baseline"})


# -- throughput --------------------------------------------------------------------------------


def _measure_or_skip(emit: Callable, cfg: Any) -> bool:
    from jaxflex.bench import measure

    try:
        emit(measure(cfg))
        return True
    except (MemoryError, RuntimeError) as exc:  # XLA reports allocation failures as RuntimeError
        emit({"kind": "skipped", "config": cfg.__dict__, "reason": f"{type(exc).__name__}: {str(exc)[:200]}"})
        return False


def section_sweep(emit: Callable, runs: int, min_time: float, horizon: int, batches: tuple[int, ...], grad_batches: tuple[int, ...], variant_batches: tuple[int, ...], max_steps: float, grad_wrt: tuple[str, ...] = ("all",)) -> None:
    config = _config_maker(runs, min_time, horizon)
    for batch in batches:
        h = horizon if batch * horizon <= max_steps else max(int(max_steps // batch), 100)
        if not _measure_or_skip(emit, config(batch=batch, horizon=h)):
            break
    for defuzz in ("singleton", "smooth"):
        for batch in variant_batches:
            _measure_or_skip(emit, config(defuzz=defuzz, batch=batch))
    for integrator in ("rk4",):
        for batch in variant_batches:
            _measure_or_skip(emit, config(integrator=integrator, batch=batch))
    for batch in grad_batches:
        for wrt in grad_wrt:
            _measure_or_skip(emit, config(batch=batch, mode="grad", wrt=wrt))


def section_matrix(emit: Callable, runs: int, min_time: float, horizon: int, batch: int, grad_batch: int) -> None:
    from jaxflex.bench import CONTROLLERS

    config = _config_maker(runs, min_time, horizon)
    for controller in CONTROLLERS:
        for defuzz in ("centroid", "singleton", "smooth") if "fuzzy" in controller else ("centroid",):
            for integrator in ("rk4", "zoh"):
                for dtype in ("float32", "float64"):
                    if defuzz != "centroid" and (integrator, dtype) != ("zoh", "float32"):
                        continue  # the variants once, in the headline setting
                    _measure_or_skip(emit, config(controller=controller, defuzz=defuzz, integrator=integrator, dtype=dtype, batch=batch))
                    if controller != "open_loop" and integrator == "zoh":
                        _measure_or_skip(emit, config(controller=controller, defuzz=defuzz, integrator=integrator, dtype=dtype, batch=grad_batch, mode="grad"))


def section_capacity(emit: Callable, runs: int, min_time: float, horizon: int, batch: int) -> None:
    config = _config_maker(runs, min_time, horizon)
    for controller in ("dfs", "dfs+fuzzy"):
        for capacity in CAPACITIES:
            _measure_or_skip(emit, config(controller=controller, capacity=capacity, batch=batch))


def interleaved_walls(calls: dict[Any, tuple[Callable, tuple]], rounds: int, min_time: float = 0.0) -> dict[Any, list[float]]:
    """Seconds per call of each compiled ``fn(*args)`` in ``calls``, timed in interleaved
    rounds (the host's load then touches every entry alike): one time per round, the mean
    of as many calls as fill ``min_time / rounds`` seconds (one call when 0, and in the
    first round)."""
    import jax
    import numpy as np

    walls: dict[Any, list[float]] = {key: [] for key in calls}
    for _ in range(rounds):
        for key, (fn, args) in calls.items():
            repeat = max(1, int(min_time / rounds / np.median(walls[key]))) if walls[key] else 1
            start = time.perf_counter()
            for _ in range(repeat):
                jax.block_until_ready(fn(*args))
            walls[key].append((time.perf_counter() - start) / repeat)
    return walls


def fit_step_cost(per_device: Any, seconds_per_step: Any) -> tuple[float, float]:
    """Least-squares line ``seconds_per_step = fixed + per_scenario * per_device``; returns
    ``(fixed, per_scenario)`` in seconds. Needs at least two distinct batches."""
    import numpy as np

    per_device, seconds_per_step = np.asarray(per_device, float), np.asarray(seconds_per_step, float)
    if per_device.shape != seconds_per_step.shape or len(np.unique(per_device)) < 2:
        raise ValueError(f"fit_step_cost needs two or more distinct batches with one time each; got {per_device.tolist()} and {seconds_per_step.tolist()}")
    per_scenario, fixed = np.polyfit(per_device, seconds_per_step, 1)
    return float(fixed), float(per_scenario)


def section_cost(emit: Callable, runs: int, min_time: float, horizon: int, batches: tuple[int, ...]) -> None:
    """Interleaved rounds over the batches of one controller at a time (the host's drift
    touches every batch alike), then the line through the medians."""
    import jax
    import numpy as np

    from jaxflex.bench import BenchConfig, make_benchmark

    n_dev = len(jax.devices())
    for controller, defuzz in (("open_loop", "centroid"), ("dfs+fuzzy", "singleton"), ("dfs+fuzzy", "centroid")):
        fns = {}
        for batch in batches:
            fn, args = make_benchmark(BenchConfig(controller=controller, defuzz=defuzz, batch=batch, horizon=horizon))
            jax.block_until_ready(fn(*args))
            fns[batch] = (fn, args)
        walls = interleaved_walls(fns, runs, min_time)
        per_step = [float(np.median(walls[batch])) / horizon for batch in batches]
        label = defuzz if "fuzzy" in controller else None
        for batch, seconds in zip(batches, per_step):
            emit({"kind": "cost", "controller": controller, "defuzz": label, "integrator": "zoh", "dtype": "float32", "batch": batch, "horizon": horizon, "per_device": batch / n_dev, "seconds_per_step": seconds, "steps_per_second": batch / seconds})
        fixed, per_scenario = fit_step_cost([batch / n_dev for batch in batches], per_step)
        emit({"kind": "cost_fit", "controller": controller, "defuzz": label, "n_devices": n_dev, "batches": list(batches), "fixed_us_per_step": fixed * 1e6, "ns_per_scenario_step": per_scenario * 1e9, "limit_steps_per_second": n_dev / per_scenario})


def _unroll_program(program: str, batch: int, unroll: int, horizon: int) -> tuple[Callable, tuple, int]:
    """The jitted ``fn``, its ``args`` and the samples per scenario of one unroll-section program."""
    import jax

    from jaxflex.bench import BenchConfig, make_benchmark
    from jaxflex.montecarlo import MCConfig, _Runner

    if program == "montecarlo chunk":
        runner = _Runner(MCConfig(n_scenarios=batch, chunk=batch, unroll=unroll))
        scenarios = jax.device_put(runner.sample(1), runner.sharding)
        return runner.evaluate, (scenarios,), scenarios.force.shape[-2]
    fn, args = make_benchmark(BenchConfig(batch=batch, horizon=horizon, mode=program.split()[-1], unroll=unroll))
    return fn, args, horizon


def _scaled_difference(a: Any, b: Any) -> float:
    """The largest difference between the leaves of ``a`` and ``b``: ``|a - b|`` over the
    leaf's largest finite ``|a|`` (1 where that is 0, as for flags) where both are finite,
    and inf where one is not finite and the other differs (NaN against inf or a number)."""
    import jax
    import numpy as np

    worst = 0.0
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        finite = np.isfinite(x) & np.isfinite(y)
        if not np.array_equal(x[~finite], y[~finite], equal_nan=True):
            return float("inf")
        scale = np.max(np.abs(x[finite]), initial=0.0) or 1.0
        worst = max(worst, float(np.max(np.abs(x[finite] - y[finite]), initial=0.0)) / scale)
    return worst


def section_unroll(emit: Callable, runs: int, min_time: float, horizon: int, batches: tuple[int, ...], grad_batch: int, unrolls: tuple[int, ...]) -> None:
    """Each program at each batch: its ``unrolls`` compiled, run once (the first call, and the
    output compared with the first unroll's), then timed in interleaved rounds."""
    import jax
    import numpy as np

    for program, program_batches in (("rollout forward", batches), ("rollout grad", (grad_batch,)), ("montecarlo chunk", batches)):
        for batch in program_batches:
            calls, outputs, first, steps = {}, {}, {}, horizon
            for unroll in unrolls:
                fn, args, steps = _unroll_program(program, batch, unroll, horizon)
                start = time.perf_counter()
                outputs[unroll] = jax.device_get(jax.block_until_ready(fn(*args)))
                first[unroll] = time.perf_counter() - start
                calls[unroll] = (fn, args)
            walls = interleaved_walls(calls, runs, min_time)
            base = float(np.median(walls[unrolls[0]]))
            for unroll in unrolls:
                median = float(np.median(walls[unroll]))
                emit({
                    "kind": "unroll", "program": program, "batch": batch, "horizon": steps, "unroll": unroll,
                    "steps_per_second": batch * steps / median, "speedup": base / median, "first_call_s": first[unroll],
                    "max_scaled_difference": _scaled_difference(outputs[unrolls[0]], outputs[unroll]),
                })


# -- ab: before / after the layout changes ---------------------------------------------------


def _module_at(rev: str, path: str, name: str) -> Any:
    """Import ``path`` as it was at git revision ``rev`` under the module name ``name``."""
    import importlib.util
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    src = subprocess.run(["git", "show", f"{rev}:{path}"], capture_output=True, text=True, check=True, cwd=root).stdout
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader=None))
    sys.modules[name] = module
    exec(compile(src, f"{rev}:{path}", "exec"), module.__dict__)  # noqa: S102 - our own history
    return module


def section_ab(emit: Callable, runs: int, horizon: int, batch: int, grad_batch: int, rev: str) -> None:
    import importlib

    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxflex.bench import bench_inputs, bench_plant
    from jaxflex.controllers import DFSParams, combine, dfs
    from jaxflex.scenarios import Scenario

    # the working tree's modules, by name: the package re-exports functions named as the fuzzy module
    new_fuzzy = importlib.import_module("jaxflex.controllers.fuzzy")
    new_rollout = importlib.import_module("jaxflex.rollout")
    old_rollout = _module_at(rev, "jaxflex/rollout.py", "_ab_rollout")
    old_fuzzy = _module_at(rev, "jaxflex/controllers/fuzzy.py", "_ab_fuzzy")
    plant = bench_plant("zoh", jnp.float32)
    variants = {}
    for r_name, r_mod in (("old", old_rollout), ("new", new_rollout)):
        for f_name, f_mod in (("old", old_fuzzy), ("new", new_fuzzy)):
            ctrl = combine(dfs(1e-3), f_mod.fuzzy())
            params = (DFSParams(jnp.float32(55.0), jnp.float32(0.005)), f_mod.fuzzy_params(1.02, 0.30, 1.0, dtype=jnp.float32))
            for mode, b in (("forward", batch), ("grad", grad_batch)):
                if mode == "grad" and r_name != f_name:
                    continue
                x0, force, noise = bench_inputs(b, horizon, jnp.float32)

                def metrics(p, x0, r_mod=r_mod, ctrl=ctrl, force=force, noise=noise):
                    if r_mod is new_rollout:  # a batch in one rollout (a controller built by the old fuzzy module is mapped with vmap)
                        return r_mod.rollout(plant, ctrl, p, Scenario(x0, force, noise), output="metrics")
                    return jax.vmap(lambda x: r_mod.rollout(plant, ctrl, p, Scenario(x, force, noise), output="metrics"))(x0)

                fn = jax.jit(metrics) if mode == "forward" else jax.jit(jax.value_and_grad(lambda p, x0, m=metrics: jnp.mean(m(p, x0).tip_ise)))
                variants[(r_name, f_name, mode)] = (fn, (params, x0), b)
    first = {}
    for key, (fn, args, _) in variants.items():
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        first[key] = time.perf_counter() - start
    walls = interleaved_walls({key: (fn, args) for key, (fn, args, _) in variants.items()}, runs)
    for (r_name, f_name, mode), (_, _, b) in variants.items():
        w = walls[(r_name, f_name, mode)]
        emit({"kind": "ab", "rollout": r_name, "fuzzy": f_name, "rev": rev, "controller": "dfs+fuzzy", "defuzz": "centroid", "integrator": "zoh", "dtype": "float32", "batch": b, "horizon": horizon, "mode": mode, "median_s": float(np.median(w)), "min_s": min(w), "compile_s": first[(r_name, f_name, mode)] - float(np.median(w)), "steps_per_second": b * horizon / float(np.median(w)), "steps_per_second_best": b * horizon / min(w)})


# -- tables ------------------------------------------------------------------------------------


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.3g}"


def _memory_note(meta: dict[str, Any]) -> str:
    """The device memory fields of a result file's meta, for its table header ("" when absent)."""
    notes = []
    if meta.get("peak_device_bytes"):
        notes.append(f" Peak device memory {meta['peak_device_bytes'] / 2**30:.1f} GiB.")
    if meta.get("xla_python_client_mem_fraction"):
        notes.append(f" XLA_PYTHON_CLIENT_MEM_FRACTION={meta['xla_python_client_mem_fraction']}.")
    return "".join(notes)


def _kind_tables(rows: list[dict[str, Any]], tables: tuple[tuple[str, str, Callable], ...]) -> list[str]:
    """One Markdown table per ``(kind, header, line)`` whose kind has rows: the header, then
    ``line(row, rows)`` for each row of that kind, then a blank line."""
    out = []
    for kind, header, line in tables:
        of_kind = [r for r in rows if r["kind"] == kind]
        if of_kind:
            out += [header, *(line(r, rows) for r in of_kind), ""]
    return out


def _grad_ops_line(r: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    scans = " + ".join(str(n) for n in r["jaxpr_grad_scans"])
    return (
        f"| {r['controller']} | {r['defuzz'] or '-'} | {r['n_params']} | {r['jaxpr_forward']} | {scans} | {r['jaxpr_ratio']:.1%} "
        f"| {r['xla_forward']:.0f} | {r['xla_grad']:.0f} | {r['xla_ratio']:.1%} |"
    )


def _ab_line(r: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    label = lambda v: f"{r['rev']}" if v == "old" else "new"  # noqa: E731
    return f"| {label(r['rollout'])} | {label(r['fuzzy'])} | {r['mode']} | {r['batch']} | {_fmt(r['steps_per_second'])} | {_fmt(r['steps_per_second_best'])} | {r['compile_s']:.2f} |"


def _cost_fit_line(r: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    rates = ", ".join(f"{c['batch']}: {_fmt(c['steps_per_second'])}" for c in rows if c["kind"] == "cost" and (c["controller"], c["defuzz"]) == (r["controller"], r["defuzz"]))
    return f"| {r['controller']} | {r['defuzz'] or '-'} | {rates} | {r['fixed_us_per_step']:.2f} µs | {r['ns_per_scenario_step']:.2f} ns | {_fmt(r['limit_steps_per_second'])} |"


def _rollout_line(r: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    from jaxflex.bench import format_spread, mode_label

    capacity = r.get("capacity", 64 if "dfs" in r["controller"] else None)  # rows from before the field: the default
    return (
        f"| {r['controller']} | {r['defuzz'] or '-'} | {capacity or '-'} | {r['integrator']} | {r['dtype']} | {r['batch']} | {r['horizon']} | {mode_label(r)} | "
        f"{_fmt(r['steps_per_second'])} | {_fmt(r['steps_per_second_best'])} | {format_spread(r)} | {r['compile_s']:.2f} | {r['cpu_util']:.2f} |"
    )


# (kind, header, line) of render_tables: the first four before the baselines' two tables
_TABLES: tuple[tuple[str, str, Callable], ...] = (
    (
        "matmul",
        "| matmul n | jnp.dot GFLOP/s (median / best) | NumPy GFLOP/s (median / best) |\n|---:|---:|---:|",
        lambda r, rows: f"| {r['n']} | {r['jax_gflops']:.1f} / {r['jax_gflops_best']:.1f} | {r['numpy_gflops']:.1f} / {r['numpy_gflops_best']:.1f} |",
    ),
    (
        "flops",
        "| controller | defuzz | FLOPs / step | transcendental / step |\n|---|---|---:|---:|",
        lambda r, rows: f"| {r['controller']} | {r['defuzz'] or '-'} | {r['flops_per_step']} | {r['transcendental_per_step']} |",
    ),
    (
        "grad_ops",
        "| controller | defuzz | params | jaxpr: forward | jaxpr: value_and_grad (forward + reverse) | ratio "
        "| XLA per scenario: forward | XLA: value_and_grad | ratio |\n|---|---|---:|---:|---:|---:|---:|---:|---:|",
        _grad_ops_line,
    ),
    (
        "memory",
        "| output | batch | horizon | temp MiB | argument MiB | output MiB |\n|---|---:|---:|---:|---:|---:|",
        lambda r, rows: f"| {r['output']} | {r['batch']} | {r['horizon']} | {r['temp_bytes'] / 2**20:.2f} | {r['argument_bytes'] / 2**20:.2f} | {r['output_bytes'] / 2**20:.2f} |",
    ),
    ("ab", "| rollout.py | fuzzy.py | mode | batch | steps/s (median) | steps/s (best) | compile s |\n|---|---|---|---:|---:|---:|---:|", _ab_line),
    (
        "unroll",
        "| program | batch | horizon | unroll | steps/s (median) | speedup | first call s | max difference / leaf scale |\n|---|---:|---:|---:|---:|---:|---:|---:|",
        lambda r, rows: f"| {r['program']} | {r['batch']} | {r['horizon']} | {r['unroll']} | {_fmt(r['steps_per_second'])} | {r['speedup']:.2f}x | {r['first_call_s']:.1f} | {r['max_scaled_difference']:.1e} |",
    ),
    (
        "cost_fit",
        "| controller | defuzz | steps/s at each batch (median) | fixed cost per step, per device | per scenario-step, per device | rate at any batch at most |\n|---|---|---|---:|---:|---:|",
        _cost_fit_line,
    ),
    (
        "rollout",
        "| controller | defuzz | DFS buffer | integrator | dtype | batch | horizon | mode | steps/s (median) | steps/s (best) | p10-p90 (calls) | compile s | CPU util |\n|---|---|---:|---|---|---:|---:|---|---:|---:|---:|---:|---:|",
        _rollout_line,
    ),
)


def render_tables(paths: list[str]) -> str:
    """Markdown tables from result documents (``--out`` files)."""
    docs = []
    for path in paths:
        with open(path, encoding="utf-8") as f:
            docs.append((os.path.basename(path), json.load(f)))
    out = []
    for name, doc in docs:
        meta, rows = doc["meta"], doc["rows"]
        out.append(f"### {name}\n")
        out.append(
            f"{meta['cpu_model']}, {meta['cpu_count']} cores ({meta['affinity_cores']} usable by the run), "
            f"{meta['n_devices']} JAX device(s) ({meta['device_kind']}), XLA_FLAGS=`{meta['xla_flags'] or '-'}`, "
            f"jax {meta['jax_version']}, numpy {meta['numpy_version']}, load average at start {meta['loadavg_1min']:.2f}, "
            f"{meta['time_utc']}. GPU: {meta.get('gpu', '-')}.{_memory_note(meta)}\n\nCommand: `{meta['command']}`\n"
        )
        for resumed in meta.get("resumed", []):
            out.append(f"Resumed {resumed['time_utc']} (load average {resumed['loadavg_1min']:.2f}): `{resumed['command']}`\n")
        if meta.get("complete") is False:
            out.append(f"**Incomplete run**: sections finished: {', '.join(meta['sections_done']) or 'none'}; `--resume` with the same options runs the rest.\n")
        kinds = {r["kind"] for r in rows}
        out += _kind_tables(rows, _TABLES[:4])
        if kinds & {"baseline", "baseline_check", "rollout_vs_baseline"}:
            out.append("| check | controller | max rel. error vs jaxflex | tolerance |\n|---|---|---:|---:|")
            for r in rows:
                if r["kind"] == "baseline_check":
                    out.append(f"| {r['baseline']} | {r['controller']}{'/' + r['defuzz'] if r['defuzz'] else ''} | {r['max_rel_err']:.1e} | {r['rtol']:.0e} |")
            out.append("")
            out.append("| implementation | dtype | batch | horizon | steps/s (median) | steps/s (best) |\n|---|---|---:|---:|---:|---:|")
            for r in rows:
                if r["kind"] == "baseline":
                    out.append(f"| {r['baseline']} | {r['dtype']} | {r['batch']} | {r['horizon']} | {_fmt(r['steps_per_second'])} | {_fmt(r.get('steps_per_second_best'))} |")
                elif r["kind"] == "rollout_vs_baseline":
                    out.append(f"| jaxflex | {r['dtype']} | {r['batch']} | {r['horizon']} | {_fmt(r['steps_per_second'])} | {_fmt(r['steps_per_second_best'])} |")
            out.append("")
        out += _kind_tables(rows, _TABLES[4:])
        skipped = [r for r in rows if r["kind"] == "skipped"]
        for r in skipped:
            out.append(f"- skipped {r['config']}: {r['reason']}")
        if skipped:
            out.append("")  # a heading right after a list would join it in Markdown
    return "\n".join(out)


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds >= 0; got {text}")
    return value


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1; got {text}")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--section", nargs="+", choices=SECTIONS + ("all",), default=["all"], help="what to run (default all)")
    p.add_argument("--out", default=None, help="also write the rows as one JSON document here at the end; until then they are in OUT.partial, rewritten after every row")
    p.add_argument("--resume", action="store_true", help="continue the interrupted run of --out from OUT.partial: its finished sections are kept, the others run (the same options, machine and JAX)")
    p.add_argument("--tables", nargs="+", default=None, metavar="FILE", help="print Markdown tables of result documents and exit")
    p.add_argument("--runs", type=_count, default=5, help="timed calls per configuration after warm-up (default 5)")
    p.add_argument("--min-time", type=_seconds, default=2.0, help="timed seconds per configuration at least: more calls after --runs until they add up to this (default 2; small batches take milliseconds per call)")
    p.add_argument("--horizon", type=_count, default=1000, help="samples per scenario (default 1000 = 1 s)")
    p.add_argument("--batch", type=_count, default=4096, help="batch of the matrix, memory and baseline sections (default 4096)")
    p.add_argument("--grad-batch", type=_count, default=4096, help="batch of the gradient rows of the matrix (default 4096; the ab section's gradient rows use 1024)")
    p.add_argument("--batches", type=_count, nargs="+", default=list(SWEEP_BATCHES), help="batch sizes of the sweep")
    p.add_argument("--grad-batches", type=_count, nargs="*", default=[1024, 4096, 16384], help="batch sizes of the gradient sweep (none: skip it)")
    p.add_argument("--grad-wrt", nargs="+", choices=("all", "gains"), default=["all"], help="what the sweep's gradient rows differentiate: every controller parameter (all, the default) and/or the gains jaxflex tune tunes (gains: k, tau_s, k1-k3)")
    p.add_argument("--variant-batches", type=_count, nargs="*", default=list(VARIANT_BATCHES), help="batch sizes of the sweep's singleton, smooth and RK4 rows (none: skip them)")
    p.add_argument("--max-steps", type=float, default=MAX_SWEEP_STEPS, help=f"cap on batch * horizon of one sweep call; larger batches get a shorter horizon (default {MAX_SWEEP_STEPS:g})")
    p.add_argument("--short-horizon", type=_count, default=200, help="horizon of the per-step python-control and scikit-fuzzy baselines")
    p.add_argument("--host-devices", type=_count, default=1, help="JAX CPU devices (one per core): the batch is sharded across them")
    p.add_argument("--no-intra-op-threads", action="store_true", help="XLA_FLAGS=--xla_cpu_multi_thread_eigen=false")
    p.add_argument("--cost-batches", type=int, nargs="+", default=list(COST_BATCHES), help="batch sizes of the cost section (two or more)")
    p.add_argument("--ab-rev", default=AB_REV, help=f"git revision of the 'before' modules of the ab section (default {AB_REV})")
    p.add_argument("--unrolls", type=_count, nargs="+", default=list(UNROLLS), help="scan unrolls of the unroll section, the first the reference (default 1 2 8)")
    p.add_argument("--unroll-batches", type=_count, nargs="+", default=[4096], help="batches of the unroll section's forward rollout and Monte Carlo chunk (default 4096)")
    p.add_argument("--quick", action="store_true", help="small sizes: horizon 200, runs 3, sweep to 16384")
    return p


RESUME_MACHINE = ("cpu_model", "cpu_count", "affinity_cores", "device_kind", "n_devices", "xla_flags", "jax_version")  # meta a resumed run must share


def _run_args(args: argparse.Namespace) -> dict[str, Any]:
    """The options that decide what a run measures, as its document records them."""
    return json.loads(json.dumps({k: v for k, v in sorted(vars(args).items()) if k not in ("out", "resume", "tables")}))


def _resumed(path: str, meta: dict[str, Any], run_args: dict[str, Any]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The meta and the finished sections' rows of the result document at ``path``, to go on
    from; ``ValueError`` naming what differs when this run cannot continue it."""
    from jaxflex.fileio import changed_fields

    with open(path, encoding="utf-8") as f:
        try:
            doc = json.load(f)
        except ValueError as e:
            raise ValueError(f"--resume: --out {path} is not a JSON document ({e}): start again in another --out") from None
    before = doc.get("meta") if isinstance(doc, dict) else None
    if not isinstance(before, dict) or not isinstance(doc.get("rows"), list) or "args" not in before:
        raise ValueError(f"--resume: --out {path} is not a document of a resumable run (no recorded options): start again in another --out")
    if before["args"] != run_args:
        raise ValueError(f"--resume: the options differ from those that wrote --out {path} ({changed_fields(before['args'], run_args)}): give the same options, or start again in another --out")
    machine = {k: meta.get(k) for k in RESUME_MACHINE}
    if {k: before.get(k) for k in RESUME_MACHINE} != machine:
        raise ValueError(f"--resume: --out {path} was measured on another machine or JAX setup ({changed_fields(before, machine)}): its rows and this run's would not compare; start again in another --out")
    done = before["sections_done"]
    before.setdefault("resumed", []).append({k: meta[k] for k in ("time_utc", "loadavg_1min", "command")})
    return before, [r for r in doc["rows"] if r.get("section") in done]


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.tables:
        print(render_tables(args.tables))
        return 0
    if args.resume and not args.out:
        _parser().error("--resume needs --out FILE: the result document to continue")
    if len(set(args.cost_batches)) < 2 or min(args.cost_batches) < 1:
        _parser().error(f"--cost-batches needs two or more distinct batch sizes >= 1 (a line through them); got {args.cost_batches}")
    _setup_jax(args)
    if args.quick:
        args.horizon, args.runs, args.short_horizon, args.min_time = 200, 3, 50, 0.5
        args.batches = [b for b in args.batches if b <= 16384]
        args.variant_batches = [b for b in args.variant_batches if b <= 16384]
        args.cost_batches = [b for b in args.cost_batches if b <= 16384] or args.cost_batches
        args.grad_batches = [1024]
    sections = SECTIONS if "all" in args.section else tuple(args.section)
    meta = _meta()
    rows: list[dict[str, Any]] = []
    partial = None if args.out is None else args.out + ".partial"
    source = next((path for path in (partial, args.out) if args.resume and os.path.exists(path)), None)
    if source is not None:
        try:
            meta, rows = _resumed(source, meta, _run_args(args))
        except (OSError, ValueError) as e:
            _parser().error(str(e))
        if meta["complete"]:
            print(f"--out {args.out} is complete: nothing to resume", file=sys.stderr)
            return 0
    else:
        if args.resume:
            print(f"--out {args.out}: no interrupted run to resume ({partial} does not exist), starting the run", file=sys.stderr)
        meta.update(args=_run_args(args), sections_done=[], complete=False)
    emit = Emitter(meta, partial, rows)
    print(json.dumps({"kind": "meta", **_jsonable(meta)}), flush=True)
    for section in SECTIONS:
        if section not in sections or section in meta["sections_done"]:
            continue
        emit.section = section
        if section == "matmul":
            section_matmul(emit, args.runs)
        elif section == "flops":
            section_flops(emit)
        elif section == "memory":
            section_memory(emit, args.batch)
        elif section == "baselines":
            section_baselines(emit, args.runs, args.min_time, args.batch, args.horizon, args.short_horizon)
        elif section == "sweep":
            section_sweep(emit, args.runs, args.min_time, args.horizon, tuple(args.batches), tuple(args.grad_batches), tuple(args.variant_batches), args.max_steps, tuple(args.grad_wrt))
        elif section == "matrix":
            section_matrix(emit, args.runs, args.min_time, args.horizon, args.batch, args.grad_batch)
        elif section == "capacity":
            section_capacity(emit, args.runs, args.min_time, args.horizon, args.batch)
        elif section == "ab":
            section_ab(emit, args.runs, args.horizon, args.batch, 1024, args.ab_rev)
        elif section == "cost":
            section_cost(emit, args.runs, args.min_time, args.horizon, tuple(args.cost_batches))
        elif section == "unroll":
            section_unroll(emit, args.runs, args.min_time, args.horizon, tuple(args.unroll_batches), args.grad_batch, tuple(args.unrolls))
        meta["sections_done"].append(section)
        emit.save()
    meta["loadavg_1min_end"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    meta["peak_device_bytes"] = _peak_device_bytes()
    meta["complete"] = True
    if args.out is not None:
        emit.save(args.out)
        if os.path.exists(partial):
            os.remove(partial)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root
    raise SystemExit(main())
