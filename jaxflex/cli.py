"""``jaxflex <command>``: the command-line edge (argparse lives only here)."""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import re
import signal
import sys
import tempfile
import threading
import time
from typing import Any, Sequence

from jaxflex import checks, fileio
from jaxflex.beam import HUBS, MAX_MODES
from jaxflex.controllers.registry import NAMES


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {value}")
    return value


def _modes(text: str) -> int:
    """``--modes``: refused here beyond ``MAX_MODES``, by its option (the core's message named
    ``n_modes``, which was not typed)."""
    value = _positive_int(text)
    if value > MAX_MODES:
        raise argparse.ArgumentTypeError(f"expected an integer from 1 to {MAX_MODES}; got {value}")
    return value


def _host_port(text: str) -> str:
    """``--coordinator``'s HOST:PORT, checked before JAX sees it: JAX indexes past a missing
    port (an IndexError) and its gRPC server aborts the process on a port that is not a number."""
    host, sep, port = text.rpartition(":")
    bracketed = host.startswith("[") and host.endswith("]")
    well_formed = ":" in host[1:-1] if bracketed else (host != "" and ":" not in host and "[" not in host and "]" not in host)
    if not sep or not well_formed or any(c.isspace() for c in host) or not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with a port from 1 to 65535 (an IPv6 host in brackets: [::1]:1234); got {text!r}")
    return text


# More CPU devices than cores only add overhead, and with hundreds XLA's collectives (the
# tuner's gradient sum) stall and abort the process.
CPU_DEVICES_PER_CORE = 8


def _cpu_devices(text: str) -> int:
    from jaxflex.bench import usable_cores

    value = _positive_int(text)
    limit = CPU_DEVICES_PER_CORE * usable_cores()
    if value > limit:
        raise argparse.ArgumentTypeError(f"expected an integer from 1 to {limit} ({CPU_DEVICES_PER_CORE} per core this process may use); got {value}")
    return value


_CPU_DEVICES_HELP = (
    f"JAX CPU devices the batch is sharded over, at most {CPU_DEVICES_PER_CORE} per core (default: one per core this process may use; "
    "1: a single device whose kernels XLA splits across cores). Faster runs on a multi-core CPU "
    "(benchmarks/README.md); no effect on an accelerator"
)


def _use_cpu_devices(count: int | None) -> None:
    """Give JAX ``count`` CPU devices (``None``: one per usable core) before its first computation.

    XLA runs the kernels of one device one after another and splits each across cores; a
    device per core, each running its own shard of the batch, keeps both cores busy (more
    forward throughput on the 2-core benchmark machine: benchmarks/README.md). ``None`` leaves a device count
    set in ``XLA_FLAGS`` alone (an explicit ``count`` overrides it), and leaves JAX as it is if it is already running in this
    process (``main`` called from a program).

    Raises:
      ValueError: for an explicit ``count`` when JAX is already running with another one.
    """
    import jax

    from jaxflex.bench import usable_cores

    if count is None and "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    try:
        jax.config.update("jax_num_cpu_devices", count or usable_cores())
    except RuntimeError:  # JAX has started; its CPU device count is fixed for this process
        running = len(jax.devices("cpu"))
        if count is not None and count != running:
            raise ValueError(f"--cpu-devices {count}: JAX already runs in this process with {running} CPU device(s); pass it before JAX's first computation") from None


def _sources(typed: dict[str, str | None], values: Any = None, path: str | None = None) -> dict[str, str | None]:
    """Where each of the library's parameter names got its value: the option in ``typed``
    that was given for it, else the key of the config file ``path`` (read as ``values``) that
    set it (``dt`` of a ``[scenarios]`` table -> ``[scenarios] dt of FILE``), else None."""
    from collections.abc import Mapping

    found: dict[str, str | None] = {}
    if path and isinstance(values, Mapping):
        for key, value in values.items():
            if isinstance(value, Mapping):
                found.update({name: f"[{key}] {sub} of {path}" for sub in value for name in (sub, f"{key} {sub}")})  # "dt must", "beam length_m must"
            found[key] = f"{key} of {path}"
    return {**found, **{name: option for name, option in typed.items() if option is not None}}


@contextlib.contextmanager
def _as_typed(options: dict[str, str | None]):
    """Within: a refusal whose message starts with one of the library's parameter names in
    ``options`` names where the value came from instead (``learning_rate must ...`` ->
    ``--lr must ...``, ``n_modes must ...`` -> ``n_modes of FILE must ...``: ``_sources``).
    ``options`` maps a name to that source, or to None where the value came from neither an
    option nor the config (a default), whose refusal keeps the library's name. Wrap only the
    call that takes those values."""
    try:
        yield
    except fileio.UnknownKeys:  # names keys, not a value: "unknown config key(s) ['unknown']" read "unknown of FILE config key(s)"
        raise
    except ValueError as err:
        message = str(err)
        for name, option in sorted(options.items(), key=lambda item: -len(item[0])):  # "beam length_m" before "beam"
            if option is not None and message.startswith(name + " "):
                raise ValueError(option + message[len(name):]) from None
        raise


def _parser() -> argparse.ArgumentParser:
    from jaxflex import __version__

    parser = argparse.ArgumentParser(prog="jaxflex", description="Differentiable simulator and tuner for vibration control of flexible manipulators.")
    parser.add_argument("--version", action="version", version=f"jaxflex {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="reproduce the paper: three runs, figures, report.md, results.json")
    rep.add_argument("--out", default="results", help="output folder (default: ./results)")
    rep.add_argument("--modes", type=_modes, default=2, help="number of assumed modes, 1-7: the paper's RK4 at 1 ms amplifies the 8th (default: 2, as the paper)")
    rep.add_argument("--x64", action="store_true", help="simulate in float64 (default float32)")
    rep.add_argument("--params", default=None, help="tuned.json from `jaxflex tune`: show its gains beside the paper's")

    tun = sub.add_parser("tune", help="tune DFS and/or fuzzy parameters by gradient descent over sampled scenarios")
    tun.add_argument("--controller", choices=("dfs", "fuzzy", "dfs+fuzzy"), default=None, help="controller to tune (default dfs)")
    tun.add_argument("--scenarios", type=_positive_int, default=None, help="training scenarios (default 256)")
    tun.add_argument("--heldout", type=_positive_int, default=None, help="held-out validation scenarios (default 64)")
    tun.add_argument("--steps", type=_positive_int, default=None, help="optimiser steps (default 200)")
    tun.add_argument("--seed", type=int, default=None, help="PRNG seed of the scenarios (default 0)")
    tun.add_argument("--lr", type=float, default=None, help="Adam learning rate on the unconstrained parameters (default 0.05)")
    tun.add_argument("--config", default=None, help="TOML file: top-level TuneConfig keys and [scenarios], [objective], [initial] and [beam] (your arm) tables")
    tun.add_argument("--out", default="tuned", help="output folder (default ./tuned)")
    tun.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz")
    tun.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    tun.add_argument("--x64", action="store_true", help="tune in float64 (default float32)")
    tun.add_argument("--cpu-devices", type=_cpu_devices, default=None, help=_CPU_DEVICES_HELP)

    stab = sub.add_parser("stability", help="DFS stability: critical delays, rightmost root, sampled-loop spectral radius, (k, tau) chart")
    stab.add_argument("--k", type=float, default=55.0, help="DFS gain (N*m/rad; default 55, the paper's)")
    stab.add_argument("--tau", type=float, default=None, help="DFS delay (s), a whole number of samples of dt (default 0.005, the paper's)")
    stab.add_argument("--modes", type=_modes, default=None, help="number of assumed modes, 1-100 (default: the config's n_modes, else 2)")
    stab.add_argument("--dt", type=float, default=None, help="sample time of the sampled loop (s; default: the config's [scenarios] dt, else 0.001)")
    stab.add_argument("--tau-max", type=float, default=None, help="largest delay of the (k, tau) chart (s), from --tau to 160 samples of dt (default: the largest of 8 tau, 40 ms and 20 samples, at most 160 samples)")
    stab.add_argument("--out", default="stability", help="output folder (default ./stability)")
    stab.add_argument("--config", default=None, help="TOML file (a tune or montecarlo config serves): its [beam] table is the arm (default the paper's), its n_modes and [scenarios] dt the defaults of --modes and --dt; a top-level key neither tune nor montecarlo accepts is refused, the other keys are not read")
    stab.add_argument("--x64", action="store_true", help="accepted for symmetry; the analysis always runs in float64")

    cal = sub.add_parser("calibrate", help="fit the arm's constants to measured natural frequencies (and damping ratios), or to a free-vibration record; writes a config for the other commands")
    measured = cal.add_mutually_exclusive_group(required=True)
    measured.add_argument("--freqs", type=float, nargs="+", metavar="HZ", help="measured natural frequencies of flexible modes 1, 2, ... (Hz, ascending)")
    measured.add_argument("--record", metavar="CSV", help="a free-vibration record instead: time (s) in the first column, one channel per further column (any units), an optional header line; its modes' frequencies and damping ratios are found and fitted")
    cal.add_argument("--record-modes", type=_positive_int, default=None, metavar="N", help="with --record: the number of flexible modes to find in it (default 2)")
    cal.add_argument("--start", type=float, default=None, metavar="S", help="with --record: the time (s) the free decay starts, after the excitation has ended (default: the record's first sample)")
    cal.add_argument("--end", type=float, default=None, metavar="S", help="with --record: the time (s) to use the record up to (default: its last sample)")
    cal.add_argument("--damping", type=float, nargs="+", default=None, metavar="RATIO", help="measured damping ratios of modes 1, 2, ... (each in (0, 1); at most one per frequency); with --record they come from the record")
    cal.add_argument("--fit", nargs="+", default=None, metavar="FIELD", help="[beam] fields to fit, at most one per frequency (default: youngs_modulus_pa and, with the hub free and two or more frequencies, hub_inertia_kg_m2)")
    cal.add_argument("--hub", choices=HUBS, default="free", help="how the arm was held when measured: free (motor unpowered; default) or clamped (hub held still)")
    cal.add_argument("--modes", type=_modes, default=None, help="assumed modes of the model, 1-100 (default: the config's n_modes, else max(2, number of frequencies))")
    cal.add_argument("--config", default=None, help="TOML file (a tune or montecarlo config serves): its [beam] table is the starting arm (default the paper's), its n_modes the default of --modes")
    cal.add_argument("--out", default="calibration", help="output folder (default ./calibration)")

    bench = sub.add_parser("bench", help="quick benchmark of vectorised closed-loop rollouts (under two minutes); prints a table")
    bench.add_argument("--json", default=None, help="write one JSON object per configuration (JSON Lines) to this file")
    bench.add_argument("--full", action="store_true", help="add the batch sweep and float64 (several minutes)")
    bench.add_argument("--cpu-devices", type=_cpu_devices, default=None, help=_CPU_DEVICES_HELP)

    mc = sub.add_parser("montecarlo", help="batched Monte Carlo over sampled scenarios: statistics, histograms, percentile bands")
    mc.add_argument("--controller", choices=NAMES, default=None, help="controller (default dfs+fuzzy, or --params' own; with --resume, the folder's)")
    mc.add_argument("--params", default=None, help="tuned.json from `jaxflex tune` (default: the paper's gains)")
    mc.add_argument("--scenarios", type=_positive_int, default=None, help="number of scenarios N (default 10000; with --resume, the folder's)")
    mc.add_argument("--chunk", type=_positive_int, default=None, help="scenarios per chunk; memory grows with it (default 4096; with --resume, the folder's)")
    mc.add_argument("--seed", type=int, default=None, help="PRNG seed (default 0; with --resume, the folder's)")
    mc.add_argument("--unroll", type=_positive_int, default=None, help="samples per compiled loop iteration, 1-64 (default 1; with --resume, the folder's); on a GPU 8 runs a chunk about 3x as fast after 5-6 s more compiling, which pays in runs of millions of scenarios; slower on a CPU")
    mc.add_argument("--config", default=None, help="TOML file: MCConfig keys (percentiles, n_modes, ...) and [scenarios] and [beam] (your arm) tables")
    mc.add_argument("--out", default="montecarlo", help="output folder (default ./montecarlo)")
    mc.add_argument("--resume", action="store_true", help="continue a run in OUT, skipping the chunks already written")
    mc.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    mc.add_argument("--x64", action="store_true", help="simulate in float64 (default float32)")
    mc.add_argument("--cpu-devices", type=_cpu_devices, default=None, help=_CPU_DEVICES_HELP)
    mc.add_argument("--distributed", action="store_true", help="call jax.distributed.initialize() first (multi-host; see the README)")
    mc.add_argument("--coordinator", type=_host_port, default=None, help="with --distributed: coordinator host:port (default: detected, e.g. SLURM or Open MPI)")
    mc.add_argument("--num-processes", type=_positive_int, default=None, help="with --distributed: number of processes")
    mc.add_argument("--process-id", type=int, default=None, help="with --distributed: this process's index, 0-based")
    # A negative number in exponent form is a value ("--k -1e3"), not an unknown option:
    # argparse before Python 3.13 knew only -1 and -1.5 ("--k: expected one argument"); this
    # is its pattern from 3.13 on. No option here starts with "-" and a digit.
    for each in (parser, *sub.choices.values()):
        each._negative_number_matcher = re.compile(r"-\.?\d")
    for command_parser in sub.choices.values():  # main reports an unknown option with its command's usage
        command_parser.set_defaults(command_parser=command_parser)
    return parser


_RESUME_HINT = {
    "tune": "; the same command with --resume continues from the last checkpoint",
    "montecarlo": "; the same command with --resume continues from the chunks written",
}


_NO_PROGRESS_HELP = "log lines instead of a progress bar (the default when stderr is not a terminal)"


def _progress_bar(args: argparse.Namespace) -> bool:
    """A progress bar only on a terminal: redirected to a file, its redraws made 22 KB of a
    200-step tune's log; there the log lines of --no-progress are written instead."""
    return not args.no_progress and sys.stderr.isatty()


def _say_recorded(command: str, said: Sequence[str], out: str) -> None:
    """Tell which options a --resume took from the run in ``out`` (``said``: "--steps 400")."""
    print(f"{command}: --resume: {', '.join(said[:-1]) + ' and ' if len(said) > 1 else ''}{said[-1]}, as the run in {out} recorded", file=sys.stderr)


def _resume_marker(command: str) -> str:
    """The file a run of ``command`` leaves to resume from (imported late: the module is
    loaded by then)."""
    if command == "tune":
        from tuning.tuner import CHECKPOINT

        return CHECKPOINT
    from jaxflex.montecarlo import META

    return META


class _Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's time limit, ``kill``, ``docker stop``), raised where the run is
    so that it ends as after Ctrl-C: temporary files removed, the resume hint printed."""


# The signal (SIGINT or SIGTERM) whose exception ``main`` has yet to catch. A signal that lands
# while JAX's garbage-collection callback runs is raised inside that callback, where Python
# prints the exception and drops it, and the run went on to the end (about 2 % of signals in
# a tune). The runs' loops call ``_raise_pending`` after each step or chunk, and ``main``
# once the command is done, so that a dropped one is raised again there.
_pending_signal: list[int] = []


def _interruption(signum: int) -> KeyboardInterrupt:
    return _Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_signal(signum: int, frame: Any) -> None:
    if signum == signal.SIGTERM:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends the process at once
    _pending_signal[:] = [signum]
    raise _interruption(signum)


def _raise_pending(*_: Any) -> None:
    """Raise the interruption of a signal whose exception was dropped (see above)."""
    if _pending_signal:
        raise _interruption(_pending_signal[0])


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``jaxflex`` console script.

    Returns 0 on success, 2 for bad input (one line on stderr naming what is wrong, no
    traceback), 130 when interrupted (Ctrl-C) and 143 when terminated (SIGTERM, handled as
    Ctrl-C is while ``main`` runs in the main thread).
    """
    args, unknown = _parser().parse_known_args(argv)
    if unknown:  # argparse would report it with the top-level usage, which lists no command's options
        args.command_parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    out = getattr(args, "out", None)
    new_out = bool(out) and not os.path.lexists(out)
    handles_signals = threading.current_thread() is threading.main_thread()  # signal.signal works there only
    # SIGINT only where Python's default handler has it: a process started with it ignored
    # (nohup, a background job) keeps ignoring it.
    signums = [s for s in (signal.SIGINT, signal.SIGTERM) if s != signal.SIGINT or signal.getsignal(s) is signal.default_int_handler]
    previous = {signum: signal.signal(signum, _on_signal) for signum in signums} if handles_signals else {}
    _pending_signal.clear()
    try:
        status = _run(args)
        _raise_pending()  # one dropped after the runs' last check: their files are complete, but the user asked to stop
        return status
    except (ValueError, OSError) as err:
        config = getattr(args, "config", None)
        # A config's unknown keys name its file, as range refusals do (_sources): only a
        # config's tables are checked for unknown keys (tuned.json's refusals name it already).
        message = err.located(config) if config and isinstance(err, fileio.UnknownKeys) else str(err)
        if isinstance(err, OSError) and err.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)) and (err.filename or out):  # a full disk said only "[Errno 28] No space left on device"
            message = f"cannot write {err.filename or f'into {out}'}: {err.strerror}"
            if args.command in _RESUME_HINT and out and os.path.exists(os.path.join(out, _resume_marker(args.command))):
                message += f"; what was written is kept: free space, then{_RESUME_HINT[args.command][1:]}"
        print(f"jaxflex {args.command}: error: {message}", file=sys.stderr)
        return 2
    except RuntimeError as err:  # jax.errors.JaxRuntimeError, a RuntimeError
        if "RESOURCE_EXHAUSTED" not in str(err):
            raise
        first = str(err).strip().splitlines()[0]
        batch = {"tune": "--scenarios, --heldout", "montecarlo": "--chunk, --scenarios"}.get(args.command)
        hint = f"; lower the batch ({batch}) or the horizon (horizon_s)" if batch else ""
        print(f"jaxflex {args.command}: error: out of memory ({first}){hint}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        hint = _RESUME_HINT.get(args.command, "")
        if hint and not os.path.exists(os.path.join(out, _resume_marker(args.command))):
            hint = "; nothing was written to resume from: run it again without --resume"
        terminated = isinstance(err, _Terminated)
        print(f"jaxflex {args.command}: {'terminated (SIGTERM)' if terminated else 'interrupted'}{hint}", file=sys.stderr)
        return 143 if terminated else 130
    finally:
        _pending_signal.clear()
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        if new_out:
            fileio.remove_if_empty(out)


def console() -> None:
    """The ``jaxflex`` console script: ``main()``'s status as the exit status. After Ctrl-C
    or SIGTERM the process ends at once, once its message is out: XLA may still be compiling on another
    thread, and the interpreter's shutdown around it crashed (a segmentation fault in 3 of 7
    interrupts during a tune's compilation). Every file was already written or left as it was.
    After any other status Ctrl-C is ignored while the interpreter shuts down (a moment)."""
    code = main()
    if code in (130, 143):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    # The command is done and its files are written: a Ctrl-C now, during the interpreter's
    # shutdown, printed a KeyboardInterrupt traceback from JAX's exit callback.
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


def _check_out(path: str) -> None:
    """Refuse an ``--out`` that cannot be a folder before any work is done."""
    if not path:
        raise ValueError("--out must name a folder; got ''")
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"--out {path!r} is a file, not a folder")
    # Made now, so that a path that cannot be a folder is refused before the work (main()
    # removes it again when the run leaves it empty).
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {path!r}: cannot make the folder ({err.strerror or err})") from None
    # A folder that exists but takes no files (read-only) would fail only when the results are
    # written, after the work: a file is made and removed now instead.
    try:
        fd, probe = tempfile.mkstemp(prefix=fileio.TEMP_PREFIX, dir=path)
        os.close(fd)
        os.remove(probe)
    except OSError as err:
        raise ValueError(f"--out {path!r}: cannot write in the folder ({err.strerror or err})") from None


def _run(args: argparse.Namespace) -> int:
    if hasattr(args, "cpu_devices"):  # bench, montecarlo and tune, before JAX's first computation
        _use_cpu_devices(args.cpu_devices)
    if getattr(args, "x64", False):
        import jax

        jax.config.update("jax_enable_x64", True)
    if hasattr(args, "out"):
        _check_out(args.out)
    if args.command == "reproduce":
        from jaxflex.beam import BeamParams, check_n_modes
        from jaxflex.report import DT, reproduce

        start = time.perf_counter()

        def progress(msg: str) -> None:
            _raise_pending()  # before each stage, and before the files replace the old ones
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

        print(_model_line(BeamParams(), check_n_modes(args.modes), DT), file=sys.stderr)
        results = reproduce(args.out, n_modes=args.modes, progress=progress, params_file=args.params)
        print(_reproduce_summary(results))
        tuned = results.get("tuned")
        if tuned:
            print(_tuned_line(tuned))
        if tuned and tuned["tuned_for"]:
            model = results["model"]
            print(f"note: {args.params} was tuned for {', '.join(tuned['tuned_for'])}; its gains ran here on the paper's arm, {model['n_modes']} modes, {model['integrator'].upper()} at {model['dt_s'] * 1e3:g} ms (see report.md)")
        if tuned and tuned["kept_start"]:
            from jaxflex.report import KEPT_START

            print(f"note: {args.params}: {KEPT_START}")
        if tuned and tuned["run"]["diverged"]:
            print(f"note: the tuned {tuned['controller']} gains of {args.params} diverge on the paper scenario (see report.md)")
        print(f"wrote {args.out}/results.json, {args.out}/report.md and figures in {args.out}/ ({time.perf_counter() - start:.1f} s)")
        return 0
    if args.command == "tune":
        return _tune(args)
    if args.command == "montecarlo":
        return _montecarlo(args)
    if args.command == "stability":
        return _stability(args)
    if args.command == "calibrate":
        return _calibrate(args)
    if args.command == "bench":
        from jaxflex.bench import run_bench

        if args.json is not None:
            _check_out_file("--json", args.json)
        run_bench(args.json, quick=not args.full)
        return 0
    return 2  # pragma: no cover - argparse enforces the choices


def _check_out_file(option: str, path: str) -> None:
    """Refuse an output file that cannot be written before the work that fills it is done."""
    folder = os.path.dirname(os.path.abspath(path))
    if not path or os.path.isdir(path):
        raise ValueError(f"{option} must name a file; got {path!r}")
    if not os.path.isdir(folder) or not os.access(folder, os.W_OK):
        raise ValueError(f"{option} {path!r}: its folder {folder} does not exist or is not writable")


def _tuned_line(tuned: dict) -> str:
    """What ``jaxflex reproduce --params`` adds to its printout: report.md's comparison of the
    tuned gains with the paper's (``report.tuned_comparison``) on one line."""
    from jaxflex.report import tuned_comparison

    paper, ours = tuned_comparison(tuned)
    return (f"tuned {tuned['controller']} ({tuned['file']}): {ours.gains} (paper: {paper.gains}); "
            f"q1 settling {ours.q1_settling} against {paper.q1_settling}, tip ISE {ours.tip_ise} against {paper.tip_ise} (m^2 s) with the paper's gains")


def _reproduce_summary(results: dict) -> str:
    """The two lines ``jaxflex reproduce`` prints: frequencies and dB reductions beside the paper's.

    One value per simulated mode; ``n/a`` where a run diverged (``results.json`` holds null).
    """
    from jaxflex.report import PAPER, format_value, moved_peaks

    def values(xs: Sequence[float | None]) -> str:
        return ", ".join(format_value(x, ".1f") for x in xs)

    def modes(count: int) -> str:
        return "mode 1" if count == 1 else "modes " + ", ".join(str(i + 1) for i in range(count))

    freqs = ", ".join(f"{f:.2f}" for f in results["model"]["natural_frequencies_hz"])
    paper_freqs = ", ".join(f"{f:g}" for f in PAPER["natural_frequencies_hz"])
    db = results["vibration_reduction_db"]
    names = {"dfs": "DFS", "fuzzy": "fuzzy"}
    ours = "; ".join(f"{name} {values(db[run])}" for run, name in names.items())
    paper = "; ".join(f"{name} {values(PAPER[run]['reduction_db'])}" for run, name in names.items())
    moved = "".join(f"\nnote: {sentence} (report.md)" for sentence in moved_peaks(results))  # 68.0 dB read beside a peak moved to 17.6 Hz
    return (
        f"model natural frequencies: {freqs} Hz (paper: {paper_freqs} Hz)\n"
        f"vibration reduction (dB, {results['psd']['name']}) at {modes(len(db['dfs']))}: {ours} "
        f"(paper, {modes(len(PAPER['dfs']['reduction_db']))}: {paper}){moved}"
    )


def _first_modes(count: int) -> str:
    """``"mode 1"`` or ``"modes 1-N"``."""
    return "mode 1" if count == 1 else f"modes 1-{count}"


def _damped(ratio: float) -> str:
    """How a damping ratio of 0.5 or more damps a mode."""
    return "heavily" if ratio < 1 else "critically" if ratio == 1 else "past critically (overdamped)"


def _model_line(arm, n_modes: int, dt: float) -> str:
    """The model a command is about to run, so that a unit slip in ``[beam]`` shows before
    the run: its flexible frequencies, their damping (a damping_ratio of 1 meant as 1 % is
    100 %), the sample time, and the modes above Nyquist. A first mode at or above Nyquist is
    refused: the controller could not see the vibration it is to damp (dt = 1 meant as 1 ms
    ran a Monte Carlo whose every run diverged)."""
    import numpy as np

    from jaxflex.beam import modal_damping_ratios, natural_frequencies_hz, rayleigh_coefficients
    from jaxflex.plant import check_dt

    check_dt(dt)
    freqs = np.asarray(natural_frequencies_hz(arm, n_modes), float)
    nyquist = 0.5 / dt
    if freqs[0] >= nyquist:
        raise ValueError(f"dt must be below {0.5 / freqs[0]:.3g} s, for the arm's first flexible mode, {freqs[0]:.4g} Hz, to lie below the Nyquist frequency "
                         f"0.5 / dt, or the controller cannot see the vibration it is to damp; got {dt:g} s (Nyquist {nyquist:.4g} Hz; dt is in seconds: 1 ms is 0.001, "
                         "and is set by a --config's [scenarios] dt, or stability's --dt. Or the arm's values are off: a thickness in mm raises its frequencies)")
    alpha, beta = (float(c) for c in rayleigh_coefficients(arm))
    ratios = ", ".join(f"{z:.4g}" for z in np.asarray(modal_damping_ratios(arm, freqs), float))
    given = f"damping_ratio = {float(arm.damping_ratio):g} of the 2-mode model" if arm.rayleigh_alpha is None else f"Rayleigh alpha = {alpha:g} 1/s, beta = {beta:g} s"
    damping = f"damping ratio{'s' if n_modes > 1 else ''} {ratios} in flexible {_first_modes(n_modes)} ({given})"
    line = f"model: {n_modes} mode(s) at {', '.join(f'{f:.4g}' for f in freqs)} Hz with {damping}, sampled every {dt:g} s (Nyquist {nyquist:.4g} Hz)"
    above = freqs[freqs > nyquist]
    if above.size:
        line += f"; {above.size} mode(s) above Nyquist alias in what the controller measures"
    ratio = float(arm.damping_ratio)
    if arm.rayleigh_alpha is None and ratio >= 0.5:
        line += f"; a damping_ratio of {ratio:g} damps the modes {_damped(ratio)} (1 % is 0.01)"
    return line


def _scenario_notes(arm, n_modes: int, spec, given: dict, config: str | None) -> list[str]:
    """What in a run's scenarios looks like a unit slip, said before the run: a horizon shorter
    than a period of mode 1 (a modulus of 200 meant in GPa gave 0.0007 Hz, and tune ran on), and initial
    deflections that are not small against the arm (q0_std_m = 1 meant as 1 mm: tune trained on
    tips at 2 m of a 0.9 m arm, which montecarlo counts as diverged)."""
    import numpy as np

    from jaxflex.beam import natural_frequencies_hz

    def named(key: str, unit: str) -> str:  # where the value came from: the config's [scenarios] or the default
        return f"[scenarios] {key} = {getattr(spec, key):g} {unit} of {config}" if key in given else f"{key} = {getattr(spec, key):g} {unit} (the default)"

    f1 = float(np.asarray(natural_frequencies_hz(arm, n_modes))[0])
    length = float(arm.length_m)
    notes = []
    if 1 / f1 > spec.horizon_s:
        notes.append(f"mode 1's period, {1 / f1:.3g} s, is longer than the horizon, {named('horizon_s', 's')}, so a run sees less than one cycle of it "
                     "(or the arm's values are off: a modulus in GPa or a length in mm lowers its frequencies)")
    for key, unit, scale in (("q0_std_m", "m", spec.q0_std_m), ("qdot0_std_m_s", "m/s", spec.qdot0_std_m_s / (2 * np.pi * f1))):
        if scale > 0.1 * length:
            how = "" if key == "q0_std_m" else f", over mode 1's angular frequency (2 pi x {f1:.4g} Hz),"
            notes.append(f"{named(key, unit)} gives initial modal deflections{how} of {scale / length:.0%} of the arm's length, {length:g} m: "
                         "the model is linear, for deflections small against the length, and montecarlo counts a tip beyond the length as diverged (SI units: 1 mm is 0.001)")
    return notes


def _tune(args: argparse.Namespace) -> int:
    from tuning.run import run_tune
    from tuning.tuner import TuneConfig, recorded_steps

    values = fileio.read_toml(args.config) if args.config else {}
    if args.resume and args.steps is None and "steps" not in values and (recorded := recorded_steps(args.out)) is not None:
        args.steps = recorded  # the run's own target: the default 200 ended a run started for 400 halfway, with a final-looking tuned.json
        _say_recorded("tune", [f"--steps {recorded}"], args.out)
    given = {"controller": args.controller, "n_scenarios": args.scenarios, "n_heldout": args.heldout, "steps": args.steps, "seed": args.seed, "learning_rate": args.lr}
    options = {"n_scenarios": "--scenarios", "n_heldout": "--heldout", "learning_rate": "--lr"}
    with _as_typed(_sources({name: options.get(name, f"--{name}") if value is not None else None for name, value in given.items()}, values, args.config)):
        config = TuneConfig.from_mapping(
            values,
            controller=args.controller,
            n_scenarios=args.scenarios,
            n_heldout=args.heldout,
            steps=args.steps,
            seed=args.seed,
            learning_rate=args.lr,
        )
    with _as_typed(_sources({}, values, args.config)):  # a dt of 1 meant as 1 ms: "[scenarios] dt of FILE must be below ..."
        print(_model_line(config.beam, config.n_modes, config.scenarios.dt), file=sys.stderr)
    for note in _scenario_notes(config.beam, config.n_modes, config.scenarios, values.get("scenarios", {}), args.config):
        print(f"note: {note}", file=sys.stderr)
    summary = run_tune(config, args.out, resume=args.resume, progress=_progress_bar(args), on_step=_raise_pending)
    obj = summary["objective"]
    def gains(named: dict) -> str:  # 6 digits, as a line to read: tuned.json has the float32 run's 55.000008
        return ", ".join(f"{name} = {value:.6g}" for name, value in named.items())

    print(f"tuned {summary['controller']}: {gains(summary['params'])} (paper: {gains(summary['paper_params'])})")
    print(f"objective, training   {obj['train']['before']:.4g} -> {obj['train']['after']:.4g}")
    print(f"objective, held-out   {obj['heldout']['before']:.4g} -> {obj['heldout']['after']:.4g}")
    stopped = f", stopped early: {config.patience} validations in a row without a better held-out objective" if summary["stopped_early"] else ""
    print(f"updates {summary['steps_run']} of {config.steps}{stopped}; the tuned gains are the point after {summary['best_step']} update{'s' * (summary['best_step'] != 1)}")
    if summary["best_step"] == 0 and summary["steps_run"] > 0:
        print(f"note: no update improved the held-out objective, so the starting gains are kept; more training scenarios (now {config.n_scenarios}) or a lower learning_rate (now {config.learning_rate:g}) may help", file=sys.stderr)
    if "stability" in summary:
        st = summary["stability"]
        part = " of the DFS part alone (the fuzzy part is nonlinear)" if summary["controller"] == "dfs+fuzzy" else ""
        verdict = "stable" if st["stable"] else "UNSTABLE: the loop grows at these gains"
        paper = "cannot run at this dt and capacity" if st["paper_spectral_radius"] is None else _radius(st["paper_spectral_radius"])
        print(f"sampled-loop spectral radius{part} {_radius(st['spectral_radius'])}, {verdict} (decay rate {st['decay_rate_per_s']:.3g} 1/s; paper gains {paper})")
    print(f"wrote {os.path.join(args.out, 'tuned.json')}, history.csv and figures")
    return 0


def _montecarlo(args: argparse.Namespace) -> int:
    import dataclasses
    from collections.abc import Mapping

    distributed = {"--coordinator": args.coordinator, "--num-processes": args.num_processes, "--process-id": args.process_id}
    if not args.distributed and any(v is not None for v in distributed.values()):
        given = [k for k, v in distributed.items() if v is not None]
        raise ValueError(f"{', '.join(given)} only appl{'ies' if len(given) == 1 else 'y'} with --distributed")
    if args.process_id is not None and args.process_id < 0:
        raise ValueError(f"--process-id must be an integer >= 0; got {args.process_id}")
    if args.process_id is not None and args.num_processes is not None and args.process_id >= args.num_processes:
        raise ValueError(f"--process-id must be below --num-processes ({args.num_processes}): 0 to {args.num_processes - 1}; got {args.process_id}")
    if args.distributed:
        import jax

        try:
            jax.distributed.initialize(coordinator_address=args.coordinator, num_processes=args.num_processes, process_id=args.process_id)
        except ValueError as err:  # JAX's words name its own arguments, not the options
            raise ValueError(f"--distributed: {err} Pass --coordinator HOST:PORT, --num-processes and --process-id, or run under a cluster "
                             "JAX detects (SLURM, Open MPI)") from None
    from jaxflex.beam import params_from_mapping
    from jaxflex.controllers.registry import PARAMETERS
    from jaxflex.montecarlo import MCConfig, recorded_settings, run_montecarlo
    from jaxflex.report import KEPT_START, format_value, load_tuned
    from jaxflex.scenarios import ScenarioSpec
    from tuning.tuner import TuneConfig

    values = fileio.read_toml(args.config) if args.config else {}
    accepted = {f.name for f in dataclasses.fields(MCConfig)}
    if isinstance(values, Mapping) and (unknown := set(values) - accepted) and unknown <= {f.name for f in dataclasses.fields(TuneConfig)}:
        raise ValueError(f"--config: {args.config} is a tune config: montecarlo does not read {sorted(unknown)}. Pass the tuned.json the run wrote as "
                         f"--params (it carries the arm, model and sample time), and a --config with montecarlo's keys only: {sorted(accepted)}")
    fileio.check_keys(values, accepted, "config")
    typed_scenarios = dict(values["scenarios"]) if isinstance(values.get("scenarios"), Mapping) else {}  # the config's own, before the defaults join them
    options = {"controller": "--controller", "n_scenarios": "--scenarios", "chunk": "--chunk", "seed": "--seed", "unroll": "--unroll"}
    sources = _sources({name: option if getattr(args, option[2:]) is not None else None for name, option in options.items()}, values, args.config)
    tuned = load_tuned(args.params) if args.params else None
    with _as_typed(sources):
        if "scenarios" in values or tuned is not None:
            table = values.get("scenarios", {})
            if tuned is not None and isinstance(table, Mapping):
                table = {"dt": tuned.dt, **table}  # the sample time it was tuned at
            values["scenarios"] = ScenarioSpec.from_mapping({"horizon_s": 3.0, **table} if isinstance(table, Mapping) else table)
        if "beam" in values:
            values["beam"] = params_from_mapping(values["beam"])
    if isinstance(values.get("percentiles"), list):
        values["percentiles"] = tuple(values["percentiles"])
    if tuned is not None and "params" in values:
        raise ValueError(f"--params {args.params} and [params] in {args.config} both set the controller's parameters: give one of them")
    if tuned is not None:
        controller = args.controller or values.get("controller", tuned.name)
        if controller != tuned.name:
            raise ValueError(f"--params {args.params} holds tuned {tuned.name} parameters; the controller asked for is {controller}")
        values["controller"] = tuned.name
        values["params"] = tuned.named
        # The controller as it was tuned (a config file's own values take precedence).
        for key, value in tuned.options.items():
            values.setdefault(key, value)
        values.setdefault("beam", tuned.beam)  # the arm it was tuned for, and the model of it
        values.setdefault("n_modes", tuned.n_modes)
        values.setdefault("method", tuned.method)
        if tuned.kept_start:
            print(f"note: {args.params}: {KEPT_START}", file=sys.stderr)
    recorded = recorded_settings(args.out) if args.resume else {}
    if args.resume:  # what neither the options nor the config set: the folder's
        option = {"n_scenarios": "scenarios", "chunk": "chunk", "unroll": "unroll", "controller": "controller", "seed": "seed"}  # each key's argument
        taken = {key: value for key, value in recorded.items() if key not in values and getattr(args, option[key]) is None}
        values.update(taken)
        defaults = {f.name: f.default for f in dataclasses.fields(MCConfig)}
        if said := [f"--{option[key]} {value}" for key, value in taken.items() if value != defaults.get(key)]:  # "--unroll 1, as recorded" was every resume's
            _say_recorded("montecarlo", said, args.out)
    overrides = {"controller": args.controller, "n_scenarios": args.scenarios, "chunk": args.chunk, "seed": args.seed, "unroll": args.unroll}
    values.update({k: v for k, v in overrides.items() if v is not None})
    with _as_typed(sources):
        config = MCConfig(**values)
    if unused := sorted(set(values.get("params", {})) - set(PARAMETERS[config.controller])):
        print(f"note: {config.controller} does not use [params] {', '.join(unused)} of {args.config} (it reads {', '.join(PARAMETERS[config.controller]) or 'none'})", file=sys.stderr)
    if "k" in PARAMETERS[config.controller] and (k := config.params.get("k", 0.0)) < 0:  # the analysis takes either sign; tune's k stays positive
        print(f"note: {f'k = {k:g} of {args.params}' if tuned is not None else f'[params] k = {k:g} of {args.config}'} is negative, the opposite sign to the paper's 55: for delays short against "
              "the modes' periods it feeds energy into the arm (jaxflex stability --k shows where such a loop is stable)", file=sys.stderr)
    if tuned is not None and (differences := tuned.differences(config.beam, config.n_modes, config.scenarios.dt, config.method)):
        print(f"note: {args.params} was tuned for {', '.join(differences)}; --config sets what runs here", file=sys.stderr)
    with _as_typed(sources):
        print(_model_line(config.beam, config.n_modes, config.scenarios.dt), file=sys.stderr)
    for note in _scenario_notes(config.beam, config.n_modes, config.scenarios, typed_scenarios, args.config):
        print(f"note: {note}", file=sys.stderr)
    summary = run_montecarlo(config, args.out, resume=args.resume, progress=_progress_bar(args), on_chunk=_raise_pending)
    if config.n_scenarios < recorded.get("n_scenarios", 0):  # said once the run took the count: a count below the folder's chunk is refused
        given = "--scenarios" if args.scenarios is not None else f"n_scenarios of {args.config}"
        print(f"note: --resume: {given} asked for {config.n_scenarios} scenarios, where the run in {args.out} had recorded {recorded['n_scenarios']}: "
              f"the summary covers the first {config.n_scenarios}, and the folder now records {config.n_scenarios}", file=sys.stderr)
    tip = summary["metrics"]["peak_tip_deflection_m"]
    spread = ", ".join(f"p{p:g} {format_value(tip[f'p{p:g}'], '.4g')}" for p in summary["percentiles"])
    print(f"{summary['n_scenarios']} scenarios on {summary['devices']} device(s): diverged fraction {summary['diverged_fraction']:.4g} (blew up, or the tip beyond the arm's {config.beam.length_m:g} m length)")
    print(f"peak tip deflection (m): mean {format_value(tip['mean'], '.4g')}, {spread}")
    settling = summary["metrics"]["settling_time_s"]
    if settling["nonfinite"]:
        # not diverged is not settled: an unstable loop that grows slowly diverges in no run
        print(f"note: {settling['nonfinite']} of the {settling['count'] + settling['nonfinite']} runs that did not diverge had not settled by the end "
              f"of the {config.scenarios.horizon_s:g} s horizon (settling time +inf, left out of its statistics; their other metrics are in theirs, "
              f"and a loop growing away from the mode frequencies reads there as a large dB reduction: each run's row is in {os.path.join(args.out, 'chunks')})", file=sys.stderr)
    print(f"wrote {os.path.join(args.out, 'summary.json')} and figures")
    return 0


def _radius(r: float) -> str:
    """A spectral radius with the 8 decimals that tell 0.99065454 from 1 apart, or 4 digits
    when it is large (RK4's step on a stiff arm gave 3531649110.40803719)."""
    return f"{r:.8f}" if r < 10 else f"{r:.4g}"


def _arm_config(path: str | None):
    """A config file's values, its arm (``[beam]``; the paper's without one) and its
    ``n_modes`` (None without one), for the commands that read only the arm and a few keys of
    a tune or montecarlo config."""
    import dataclasses

    from jaxflex.beam import MAX_MODES, params_from_mapping
    from jaxflex.montecarlo import MCConfig
    from tuning.tuner import TuneConfig

    values = fileio.read_toml(path) if path else {}
    # A tune or montecarlo config serves: the keys of either are accepted, a misspelt one is
    # refused (it silently left the paper's arm in place).
    fileio.check_keys(values, {f.name for f in dataclasses.fields(TuneConfig)} | {f.name for f in dataclasses.fields(MCConfig)}, "config")
    n_modes = checks.integer(f"n_modes of {path}", values["n_modes"], high=MAX_MODES) if "n_modes" in values else None
    with _as_typed(_sources({}, values, path)):
        return values, params_from_mapping(values.get("beam", {})), n_modes


def _calibrate(args: argparse.Namespace) -> int:
    from jaxflex import plotting
    from jaxflex.plant import check_method
    from jaxflex.scenarios import ScenarioSpec
    from tuning.calibrate import calibrate, to_toml

    values, arm, config_modes = _arm_config(args.config)
    # the config's sample time and integrator go into calibrated.toml, which is to replace it
    with _as_typed(_sources({}, values, args.config)):
        config_dt = ScenarioSpec.from_mapping(values["scenarios"]).dt if "scenarios" in values and "dt" in values["scenarios"] else None
        config_method = check_method(values["method"]) if "method" in values else None
    if args.record is None and (args.start, args.end, args.record_modes) != (None, None, None):
        raise ValueError("--start, --end and --record-modes apply to --record only")
    modes, record = _identify(args) if args.record is not None else (None, None)
    freqs, damping = (args.freqs, args.damping) if modes is None else (modes.frequencies_hz, modes.damping)
    # the arm the fit starts from and keeps the other fields of, so that a unit slip in [beam],
    # or the paper's arm taken for want of a --config, shows (it was named nowhere)
    fields = ", ".join(f"{name} {float(value):g}" for name, value in arm._asdict().items() if value is not None)
    whose = f"the arm of {args.config}" if values.get("beam") else "the paper's arm (give yours in the [beam] table of a --config)"
    print(f"starting from {whose}: {fields}", file=sys.stderr)
    try:
        result = calibrate(freqs, arm, args.fit, args.modes if args.modes is not None else config_modes, args.hub, damping)
    except ValueError as err:
        # A message that starts with the core's name of a parameter names its option here.
        first, _, rest = str(err).partition(" ")
        modes = "--modes" if args.modes is not None or config_modes is None else f"n_modes of {args.config}"
        options = {"measured_hz": "--freqs", "damping": "--damping", "n_modes": modes, "fit": "--fit"}
        raise ValueError(f"{options[first]} {rest}" if first in options else str(err)) from None
    print("mode  measured (Hz)  model before  model calibrated  error")
    for i, (m, b, a, error) in enumerate(zip(result.measured_hz, result.before_hz, result.after_hz, result.error_after_percent)):
        print(f"{i + 1:>4}  {m:>13.6g}  {b:>12.6g}  {a:>16.6g}  {0.0 if abs(error) < 5e-5 else error:+.4f} %")
    for name, start, sensitivity in zip(result.fit, result.start, result.sensitivity):
        value = float(getattr(result.beam, name))
        print(f"{name}: {start:.6g} -> {value:.6g} (x{value / start:.4g}; {sensitivity:.3g} % per 1 % error in the frequencies)")
    if result.measured_damping.size:
        shown = ", ".join(f"{z:.4g}" for z in result.after_damping)
        measured = ", ".join(f"{z:.4g}" for z in result.measured_damping)
        n_d, n_f = result.measured_damping.size, result.after_damping.size  # n_d <= n_f: damping need not be measured in every mode
        measured_in = "" if n_d == n_f else f" in {_first_modes(n_d)}"
        print(f"damping ratio{'s' if n_f > 1 else ''}: measured {measured}{measured_in}; model {shown} in {_first_modes(n_f)}")
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    run_dt = config_dt if config_dt is not None else ScenarioSpec().dt
    if result.after_hz[0] >= 0.5 / run_dt:  # tune, montecarlo and stability refuse it as it stands
        print(f"note: the calibrated arm's mode 1, {result.after_hz[0]:.4g} Hz, is at or above the Nyquist frequency of dt = {run_dt:g} s"
              f"{'' if config_dt is not None else ' (the default)'}: give calibrated.toml a [scenarios] dt below {0.5 / result.after_hz[0]:.3g} s "
              "for tune, montecarlo and stability", file=sys.stderr)
    owned = ("calibrated.toml", "calibration.json", "calibration.png", "identification.png")
    with fileio.replace_outputs(args.out, owned, last="calibration.json") as stage:
        fileio.write_text(os.path.join(stage, "calibrated.toml"), to_toml(result, config_dt, config_method))
        title = f"Calibration, hub {result.hub}, {result.n_modes} modes: fitted {', '.join(result.fit)}"
        plotting.save(plotting.calibration(result.measured_hz, result.before_hz, result.after_hz, title, result.measured_damping, result.after_damping), os.path.join(stage, "calibration.png"))
        summary = result.as_dict()
        if modes is not None:
            summary["identified"] = {"record": os.path.abspath(args.record), **modes.as_dict()}
            t, y, names = record
            title = f"{os.path.basename(args.record)}: " + ", ".join(f"{f:.4g} Hz (damping {100 * z:.3g} %)" for f, z in zip(modes.frequencies_hz, modes.damping))
            plotting.save(plotting.identification(t, y, modes.times, modes.reconstruction, names, title, period_s=1 / float(min(modes.frequencies_hz))), os.path.join(stage, "identification.png"))
        fileio.write_json(os.path.join(stage, "calibration.json"), summary)
        _raise_pending()  # a Ctrl-C dropped while drawing stops the run before the files replace the old ones
    shown = "calibration.json, calibration.png" + (" and identification.png" if modes is not None else "")
    print(f"wrote {os.path.join(args.out, 'calibrated.toml')} (pass it as --config to tune, montecarlo or stability), {shown}")
    return 0


def _identify(args: argparse.Namespace) -> tuple[Any, tuple[Any, Any, list[str]]]:
    """The modes of ``--record`` (``tuning.identify.Modes``), printed, and the record
    (``read_record``'s times, channels and names)."""
    from tuning.identify import MAX_ROWS, identify_modes, read_record

    if args.damping is not None:
        raise ValueError("--damping: with --record the damping ratios come from the record; give one or the other")
    t, y, names = read_record(args.record, "--record")
    n_modes = 2 if args.record_modes is None else args.record_modes
    try:
        modes = identify_modes(t, y, n_modes, start_s=args.start, end_s=args.end)
    except ValueError as err:
        # the core's names of the options, the options' names here
        message = re.sub(r"\b(n_modes|start_s|end_s)\b", lambda m: {"n_modes": "--record-modes", "start_s": "--start", "end_s": "--end"}[m[1]], str(err))
        # and its channels by their columns' names (it said "channel(s) [3] of y")
        message = re.sub(r"channel\(s\) \[([\d, ]+)\] of y", lambda m: "channel(s) " + ", ".join(repr(names[int(i) - 1]) for i in m[1].split(",")), message)
        raise ValueError(message if message.startswith("--") else f"--record {args.record}: {message}") from None
    print(f"{args.record}: {len(names)} channel(s), {modes.end_s - modes.start_s:.6g} s from {modes.start_s:.10g} s at dt = {modes.dt:g} s; "
          f"the model of {modes.order} poles leaves {100 * modes.residual:.3g} % of its modes' RMS")
    for i, (f, z) in enumerate(zip(modes.frequencies_hz, modes.damping)):
        print(f"  mode {i + 1}: {f:.6g} Hz, damping ratio {z:.4g}")
    if modes.residual > 0.1:
        print(f"note: the model leaves {100 * modes.residual:.3g} % of the record unexplained: check that the window starts after the "
              "excitation has ended (--start); see identification.png", file=sys.stderr)
    if modes.rise is not None:
        factor, channel, onset, peak = modes.rise
        print(f"note: channel {names[channel]!r} rises {factor:.3g}x in the window (its RMS over a quarter period of mode 1, from the window's first, "
              f"{modes.start_s:.10g} s, to about {onset:.10g} s; its peak at {peak:.10g} s): a free decay does not grow, so the window may start "
              "before the response (at rest, or in the excitation), which the model fits with a spurious, heavily damped mode; if so, give a --start "
              "just after the excitation has ended. Modes that nearly cancel at the start rise too: the other channels and identification.png tell", file=sys.stderr)
    if modes.lag_span_s * modes.frequencies_hz[0] < 1:
        if round(modes.lag_span_s / modes.dt) < MAX_ROWS:  # the lags are a third of a short window, not capped
            print(f"note: the window ({modes.end_s - modes.start_s:.3g} s) is so short that the model's lags (a third of it) span {modes.lag_span_s:.3g} s, "
                  "less than a period of mode 1: its modes are poorly resolved; widen it (--start, --end) to 3 periods of mode 1 or more", file=sys.stderr)
        else:
            print(f"note: the record is sampled so fast that the model's lags span {modes.lag_span_s:.3g} s, less than a period of mode 1: "
                  "its modes are poorly resolved; low-pass filter it and keep every k-th sample, at several samples per period of the highest mode", file=sys.stderr)
    return modes, (t, y, names)


def _progress_line(msg: str) -> None:
    _raise_pending()  # before each stage, and before the files replace the old ones
    print(msg, file=sys.stderr, flush=True)


def _moved(first: float | None, first_more: float | None) -> bool:
    """Whether the first destabilising delay differs by more than 1 % with more modes (None: none)."""
    if first is None or first_more is None:
        return first is not first_more
    return abs(first_more - first) > 0.01 * first


def _root(root: dict) -> str:
    """A characteristic root from stability.json, in rad/s: ``-9.335 /s`` or ``28.22 ± 289.8j /s``."""
    imag = abs(root["imag"])
    return f"{root['real']:.4g}{f' ± {imag:.4g}j' if imag else ''} /s"


def _stability(args: argparse.Namespace) -> int:
    from jaxflex.analysis.stability import delay_steps_of
    from jaxflex.beam import natural_frequencies_hz
    from jaxflex.scenarios import ScenarioSpec
    from jaxflex.stability_report import run

    values, arm, config_modes = _arm_config(args.config)
    # tau comes from --tau or its default here (never from --config): a refusal names the option
    typed = _sources({"k": "--k", "tau_s": "--tau" if args.tau is not None else "--tau (default 0.005 s)", "tau_max_s": "--tau-max" if args.tau_max is not None else None,
                      "dt": "--dt" if args.dt is not None else None, "n_modes": "--modes" if args.modes is not None else None}, values, args.config)
    with _as_typed(_sources({}, values, args.config)):  # the config's values alone, beside a typed --dt
        scenarios = ScenarioSpec.from_mapping(values.get("scenarios", {}))
    n_modes = args.modes if args.modes is not None else config_modes or 2
    dt = args.dt if args.dt is not None else scenarios.dt
    with _as_typed(typed):  # --dt 0 was refused as "dt"
        print(_model_line(arm, n_modes, dt), file=sys.stderr)
    if args.tau is None:
        args.tau = 0.005
        try:
            delay_steps_of(args.tau, dt)
        except ValueError:
            raise ValueError(f"--tau: its default, the paper's 0.005 s, is {args.tau / dt:g} samples of dt = {dt:g} s; pass --tau, a whole number of samples of dt") from None
    with _as_typed(typed):
        result = run(args.out, k=args.k, tau_s=args.tau, n_modes=n_modes, dt=dt, tau_max_s=args.tau_max, beam_params=arm, progress=_progress_line)
    first, sampled, root = result["first_destabilising_delay_s"], result["first_destabilising_delay_sampled_s"], result["rightmost_root"]
    rk4 = result["spectral_radius_rk4"]
    arm_name = f"the arm of {args.config}" if values.get("beam") else "the paper's arm"
    whose_rk4 = {None: "the default of tune and montecarlo", "rk4": f"the method of {args.config}"}.get(values.get("method"), f"which {args.config} does not use")
    print(f"{arm_name}, k = {args.k:g}, tau = {args.tau:g} s, {n_modes} modes, dt = {dt:g} s: sampled-loop spectral radius {_radius(result['spectral_radius'])} "
          f"({'stable' if result['stable_sampled'] else 'UNSTABLE'}; sampled by RK4, {whose_rk4}: {_radius(rk4)}, {'stable' if rk4 < 1 else 'UNSTABLE'}), "
          f"first destabilising delay {'none' if first is None else f'{first:g} s'} (continuous loop; sampled loop: "
          f"{'none up to ' + format(result['first_destabilising_delay_sampled_tau_max_s'], 'g') + ' s' if sampled is None else f'{sampled:g} s'}), "
          f"continuous loop's rightmost root {_root(root)} ({'stable' if result['stable_continuous'] else 'UNSTABLE'})")
    more = result["first_destabilising_delay_more_modes"]
    if more["error"] is not None:
        print(f"note: the first destabilising delay was not rechecked with {more['n_modes']} modes: {more['error']}", file=sys.stderr)
    elif _moved(first, more["s"]):
        freq = next((c["freq_hz"] for c in result["crossings"] if first is not None and first in c["tau_s"]), None)
        top = float(natural_frequencies_hz(arm, n_modes)[-1])
        above = f", above the model's top mode, {top:.4g} Hz" if freq is not None and freq > top else ""
        where = "" if freq is None else f" (its crossing is at {freq:.4g} Hz{above})"
        print(f"note: with {more['n_modes']} modes the continuous loop's first destabilising delay is {'none' if more['s'] is None else format(more['s'], 'g') + ' s'} against "
              f"{'none' if first is None else format(first, 'g') + ' s'} with {n_modes}{where}: it moves with the modes the model leaves out; "
              f"--modes {more['n_modes']} analyses the larger model", file=sys.stderr)
    if not root["converged"]:
        print(f"note: the continuous loop's rightmost root moved by {root['change_from_half_n_cheb']:.3g} rad/s between {root['n_cheb'] // 2} and "
              f"{root['n_cheb']} Chebyshev intervals, the most tried: its real part, and stable_continuous in stability.json, are not settled "
              "(the delay spans many periods of the arm's highest modes; the crossings' first destabilising delay does not depend on it)", file=sys.stderr)
    print(f"wrote {os.path.join(args.out, 'stability.json')} and {os.path.join(args.out, 'stability_chart.png')}")
    return 0


if __name__ == "__main__":
    console()
