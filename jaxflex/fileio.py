"""Atomic file writes: a reader never sees a half-written result, and a failed write leaves
the previous file untouched.

Temporary files and staging folders are named ``.tmp-*`` and locked (``flock``) by the process
writing them while it lives. A process killed outright (SIGKILL) cannot remove its own, so
every write first sweeps those of its folder that no living process holds.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import math
import os
import pathlib
import shutil
import tempfile
import time
import tomllib
from typing import Any, Callable, Iterable, Iterator, Mapping

import jax.numpy as jnp
import numpy as np

try:
    import fcntl
except ImportError:  # not POSIX: no locks, so the leftovers of killed runs are kept
    fcntl = None

TEMP_PREFIX = ".tmp-"
RUN_LOCK = ".jaxflex-run.lock"
"""The empty file a resumable run holds locked in its folder while it runs (:func:`run_lock`)."""
_HELD_RUN_LOCKS: set[str] = set()  # the folders whose run lock this process holds
# A temporary entry is locked right after it is made; one younger than this may still be in
# that gap, so it is never swept.
_SWEEP_MIN_AGE_S = 10.0


def _lock(fd: int) -> bool:
    """Take an exclusive lock on ``fd`` without waiting: False if another process holds it."""
    if fcntl is None:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # held elsewhere (BlockingIOError), or a file system without locks
        return False
    return True


def sweep_stale(folder: str | os.PathLike) -> None:
    """Remove the ``.tmp-*`` files and folders in ``folder`` that no living process holds (those
    of runs that were killed), older than a few seconds. Entries a process holds, or that
    cannot be opened, are left alone; without ``fcntl`` (not POSIX) nothing is removed.
    """
    if fcntl is None:
        return
    try:
        entries = [entry for entry in os.scandir(os.fspath(folder)) if entry.name.startswith(TEMP_PREFIX)]
    except OSError:
        return
    for entry in entries:
        try:
            if entry.is_symlink() or time.time() - entry.stat(follow_symlinks=False).st_mtime < _SWEEP_MIN_AGE_S:
                continue
            fd = os.open(entry.path, os.O_RDONLY)
        except OSError:
            continue
        try:
            if not _lock(fd):
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.remove(entry.path)
        except OSError:
            continue
        finally:
            os.close(fd)


def check_path(name: str, path: Any, what: str = "file") -> str:
    """``path`` as a str; ValueError naming ``name`` unless it is a non-empty str or
    os.PathLike (``what`` says what it names: a file, a folder)."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise ValueError(f"{name} must be a {what}'s path (a non-empty str or os.PathLike); got {path!r}")
    return os.fspath(path)


@contextlib.contextmanager
def run_lock(folder: str | os.PathLike, name: str = "out_dir") -> Iterator[None]:
    """Hold ``folder``'s run lock (an ``flock`` on ``RUN_LOCK``, made if missing and left in
    place) while the block runs. A second run into the same folder at the same time is
    refused by ``name``: it would pass the folder's checks before the first wrote anything,
    then interleave its chunks, checkpoints and figures with the first's. A block inside
    another of the same process on the same folder holds it already (``run_tune`` around
    ``tune``). Without ``fcntl`` (not POSIX), or on a file system without locks, nothing is
    held.
    """
    folder = check_path(name, folder, "folder")
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{name} {folder!r} is a file, not a folder")
    os.makedirs(folder, exist_ok=True)
    key = os.path.realpath(folder)
    if fcntl is None or key in _HELD_RUN_LOCKS:
        yield
        return
    fd = os.open(os.path.join(folder, RUN_LOCK), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"{name} {folder} is in use by another run still going: wait for it to end, or choose another folder") from None
        except OSError:  # a file system without locks
            pass
        _HELD_RUN_LOCKS.add(key)
        try:
            yield
        finally:
            _HELD_RUN_LOCKS.discard(key)
    finally:
        os.close(fd)


def remove_if_empty(folder: str) -> None:
    """Remove ``folder`` (which this run created) when a failed or interrupted run wrote no
    file in it, so that no empty result folder is left behind; a folder holding any file (a
    checkpoint to resume from, finished results) is kept. The run lock counts for none, but a
    folder whose lock another run holds is kept: two runs started at once into a new folder
    both found it new, and the one refused removed the other's folder and lock, which let a
    third run in beside it."""
    lock = os.path.join(folder, RUN_LOCK)
    try:
        fd = os.open(lock, os.O_RDWR)
    except FileNotFoundError:
        fd = None
    except OSError:  # no folder at all, or one this process cannot read
        return
    try:
        if fd is not None and fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return  # another run's
            except OSError:  # a file system without locks
                pass
        if any(name != RUN_LOCK for _, _, files in os.walk(folder) for name in files):
            return
        with contextlib.suppress(OSError):
            os.remove(lock)
        for root, _, _ in sorted(os.walk(folder), key=lambda entry: -len(entry[0])):
            try:
                os.rmdir(root)
            except OSError:
                return
    finally:
        if fd is not None:
            os.close(fd)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call ``write(tmp_path)`` on a temporary file beside ``path``, then rename it over ``path``
    once its data is on disk (``fsync``).

    The file gets the permissions a plain ``open(path, "w")`` would give it: those of the file
    it replaces, or else the default under the process umask (a temporary file is created
    readable by its owner only).
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    sweep_stale(folder)
    fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=os.path.splitext(path)[1], dir=folder)
    try:
        _lock(fd)  # held until the file is renamed or removed: no sweep takes it meanwhile
        write(tmp)
        os.chmod(tmp, _mode_for(path))
        os.fsync(fd)  # on disk before the rename: after a power loss the file is the old or the new one, never empty
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
        os.close(fd)


@contextlib.contextmanager
def replace_outputs(folder: str | os.PathLike, owned: Iterable[str], last: str | None = None) -> Iterator[str]:
    """A staging folder for a run's files: what is written there replaces ``folder``'s files
    when the block ends, in one pass of renames (``last``, say results.json, after the
    others), and then the files named in ``owned`` that this run did not write are removed
    (a figure of an earlier run with other options). An exception in the block (Ctrl-C
    included) leaves ``folder`` as it was; only the final pass, a few renames, is not one
    step.
    """
    folder = os.fspath(folder)
    os.makedirs(folder, exist_ok=True)
    sweep_stale(folder)
    stage = tempfile.mkdtemp(prefix=TEMP_PREFIX, dir=folder)
    fd = None
    try:
        if fcntl is not None:  # a folder cannot be opened on Windows
            fd = os.open(stage, os.O_RDONLY)
            _lock(fd)
        yield stage
        written = sorted(os.listdir(stage), key=lambda name: name == last)
        for name in written:
            os.chmod(os.path.join(stage, name), _mode_for(os.path.join(folder, name)))
            os.replace(os.path.join(stage, name), os.path.join(folder, name))
        for name in set(owned) - set(written):
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(folder, name))
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if fd is not None:
            os.close(fd)


def _mode_for(path: str) -> int:
    """The permission bits of an existing ``path``, or 0o666 less the process umask."""
    try:
        return os.stat(path).st_mode & 0o777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) atomically."""

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)

    atomic_write(path, write)


def to_jsonable(value: Any, *, finite: bool = True, exact: bool = False) -> Any:
    """NumPy/JAX scalars and arrays to plain JSON values; non-finite floats become None
    (``finite=False``: kept, for files only Python reads back, as ``Infinity`` and ``NaN``).
    A narrow float is written ``shortest``; ``exact=True`` widens it to float64 instead, for a
    fingerprint, in which a float32 55.000008 and a float64 55.000008 must differ."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v, finite=finite, exact=exact) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v, finite=finite, exact=exact) for v in value]
    if hasattr(value, "tolist"):
        return to_jsonable(np.asarray(value).tolist() if exact else shortest(value), finite=finite)
    if isinstance(value, float) and finite:
        return value if math.isfinite(value) else None
    return value


def shortest(value: Any) -> Any:
    """A NumPy/JAX scalar or array as Python values (``tolist``), each float narrower than
    float64 (float32, float16, bfloat16) as the shortest decimal that reads back to it in its
    own dtype: a float32 55 + 2 ulp is 55.000008, not the 55.00000762939453 of its float64
    widening, so that a file shows the digits the run computed and no more."""
    array = np.asarray(value)
    if not (jnp.issubdtype(array.dtype, jnp.floating) and jnp.finfo(array.dtype).bits < 64):  # bfloat16 too, whose kind is "V"
        return array.tolist()
    narrow = array.dtype.type

    def digits(x: Any) -> float:  # the fewest significant digits that read back to x
        if array.dtype.kind == "f":  # NumPy's own floats: its shortest round-trip form, whatever the print options
            return float(np.format_float_scientific(x, unique=True))
        x = float(x)
        return x if not math.isfinite(x) else next(float(f"{x:.{p}g}") for p in range(1, 18) if narrow(float(f"{x:.{p}g}")) == narrow(x))

    return np.array([digits(x) for x in array.ravel()]).reshape(array.shape).tolist()


def digest(fields: Mapping[str, Any]) -> str:
    """A run's fingerprint: a short hash of its JSON-able configuration ``fields`` (key order
    aside), recorded in its folder so that a resume with another configuration is refused."""
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def program() -> str:
    """The program a resumable run records in its fingerprint, so that a resume by another one
    is refused instead of mixing two programs' results in one summary: a hash of the source
    of ``jaxflex`` and ``tuning``, and the versions of jax and jaxlib, whose numerics may
    change between releases."""
    import jax
    import jaxlib

    source = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent.parent
    for package in ("jaxflex", "tuning"):
        for path in sorted((root / package).rglob("*.py")):
            source.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return f"jaxflex source {source.hexdigest()[:12]}, jax {jax.__version__}, jaxlib {jaxlib.__version__}"


def changed_fields(before: Any, now: Mapping[str, Any]) -> str:
    """What a refused resume names: ``"changed: seed: 0 -> 3, scenarios.horizon_s: 0.4 -> 0.5"``,
    each key of ``now`` whose value differs from the one recorded in ``before`` (a folder's
    configuration, as read back) with both values, nested tables by dotted path; or ``"the
    configuration changed"`` when no key both share differs. A key one side lacks (a record
    written by an older version) is no change named. A changed ``program`` (``program()``)
    gets a hint, since no option can match it."""

    def differences(before: Any, now: Any, path: str) -> list[str]:
        if isinstance(before, Mapping) and isinstance(now, Mapping):
            return [d for k in sorted(now) if k in before for d in differences(before[k], now[k], f"{path}{k}.")]
        return [] if before == now else [f"{path[:-1]}: {before!r} -> {now!r}"]

    named = differences(before if isinstance(before, Mapping) else {}, now, "")
    if not named:
        return "the configuration changed"
    upgraded = any(d.startswith("program: ") for d in named)  # no option undoes that one
    hint = "; no option matches another program: start again in another --out, or resume with the program that wrote it" if upgraded else ""
    return f"changed: {', '.join(named)}{hint}"


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON atomically (non-finite numbers as null)."""
    write_text(path, json.dumps(to_jsonable(data), indent=2, allow_nan=False) + "\n")


def read_toml(path: str | os.PathLike, option: str = "--config") -> dict[str, Any]:
    """Read a TOML file into a dict.

    Raises:
      ValueError: naming ``option`` (the command-line option that gave ``path``) when the
        file cannot be read or is not valid TOML.
    """
    path = check_path(option, path)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except OSError as err:
        raise ValueError(f"{option}: cannot read {path}: {err.strerror or err}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:  # TOML is UTF-8
        if _is_json(path):
            raise ValueError(f"{option}: {path} is JSON, not TOML (a tuned.json from `jaxflex tune` goes to --params of "
                             "reproduce or montecarlo, the arm it was tuned for with it; `jaxflex calibrate` writes the arm for --config "
                             "as calibrated.toml, beside its calibration.json)") from None
        raise ValueError(f"{option}: {path} is not valid TOML: {err}") from None


def _is_json(path: str | os.PathLike) -> bool:
    try:
        with open(path, "rb") as f:
            json.load(f)
    except (OSError, ValueError):
        return False
    return True


class UnknownKeys(ValueError):
    """Unknown keys of a table (``unknown config key(s) ['x']; accepted: [...]``). The
    library does not know the file a table came from; the command line, which does, names
    it with ``located``."""

    def __init__(self, what: str, unknown: Any, accepted: Any, qualifier: str = ""):
        self.what, self.unknown, self.accepted, self.qualifier = what, sorted(unknown), sorted(accepted), qualifier
        super().__init__(self.located(None))

    def located(self, path: str | os.PathLike | None) -> str:
        """The message, saying that the keys are in ``path`` (None: no file)."""
        where = f" in {path}" if path is not None else ""
        return f"unknown {self.what} {self.unknown}{self.qualifier}{where}; accepted: {self.accepted}"


def check_keys(values: Any, accepted: Any, what: str) -> None:
    """Refuse a config table that is not a table, or has unknown keys (``UnknownKeys``), by
    name, listing the accepted ones."""
    if not isinstance(values, Mapping):
        raise ValueError(f"{what} must be a table of keys (accepted: {sorted(accepted)}); got {values!r}")
    unknown = set(values) - set(accepted)
    if unknown:
        raise UnknownKeys(f"{what} key(s)", unknown, accepted)
