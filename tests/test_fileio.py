"""jaxflex.fileio: atomic writes and their temporaries, the staged outputs of a run, run
locks and config keys, checked against the file system and the process state."""

import os
import stat
import time

import pytest

from jaxflex import fileio


def test_new_file_write_leaves_the_process_umask_as_it_was(tmp_path):
    """_mode_for reads the umask by setting it; it must put it back (the umask is
    process-wide: every later file this process makes would otherwise be world-writable)."""
    old = os.umask(0o027)
    try:
        fileio.write_text(tmp_path / "new.md", "x")  # a new file: _mode_for reads the umask
        now = os.umask(0o027)
    finally:
        os.umask(old)
    assert now == 0o027
    plain = tmp_path / "plain.txt"
    old = os.umask(0o027)
    try:
        fileio.write_text(tmp_path / "new2.md", "x")
        plain.write_text("p")  # a plain write made after it follows the umask too
    finally:
        os.umask(old)
    assert stat.S_IMODE(plain.stat().st_mode) == 0o640


@pytest.mark.skipif(fileio.fcntl is None, reason="POSIX locks")
def test_atomic_writes_temporary_is_held_against_a_concurrent_sweep(tmp_path):
    """The temporary file being written is locked, so that a sweep by another writer
    (here: sweep_stale, which opens it anew: flock is per open file, so it conflicts as
    another process's would) does not delete it even when it is older than the sweep's
    minimum age (a slow write: a long savefig)."""
    seen = {}

    def slow_write(tmp):
        with open(tmp, "w") as f:
            f.write("data")
        past = time.time() - 3600
        os.utime(tmp, (past, past))
        fileio.sweep_stale(os.path.dirname(tmp))  # another writer's sweep, mid-write
        seen["survived"] = os.path.exists(tmp)

    fileio.atomic_write(tmp_path / "out.txt", slow_write)
    assert seen["survived"]
    assert (tmp_path / "out.txt").read_text() == "data"


@pytest.mark.skipif(fileio.fcntl is None, reason="POSIX locks")
def test_replace_outputs_stage_is_held_against_a_concurrent_sweep(tmp_path):
    """The staging folder of replace_outputs is locked while the run writes into it: another
    writer's sweep leaves it, even when it is older than the sweep's minimum age (figures
    drawn for minutes), and the outputs arrive."""
    with fileio.replace_outputs(tmp_path, ["r.json"]) as stage:
        with open(os.path.join(stage, "r.json"), "w") as f:
            f.write("{}")
        past = time.time() - 3600
        os.utime(stage, (past, past))
        fileio.sweep_stale(tmp_path)  # another writer's sweep, mid-run
        assert os.path.isdir(stage)
    assert (tmp_path / "r.json").read_text() == "{}"


def test_sweep_leaves_old_files_that_are_not_temporaries(tmp_path):
    """The sweep removes only .tmp-* entries: an old user file (not held by anyone) in the
    folder written into is kept."""
    mine = tmp_path / "notes.txt"
    mine.write_text("the user's")
    sub = tmp_path / "data"
    sub.mkdir()
    past = time.time() - 3600
    for p in (mine, sub):
        os.utime(p, (past, past))
    fileio.write_text(tmp_path / "new.md", "x")
    with fileio.replace_outputs(tmp_path, []) as stage:
        open(os.path.join(stage, "r.json"), "w").write("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "new.md", "notes.txt", "r.json"]
    assert mine.read_text() == "the user's"


@pytest.mark.skipif(fileio.fcntl is None, reason="POSIX locks")
def test_replace_outputs_alone_sweeps_a_killed_runs_temporaries(tmp_path):
    """Replace_outputs sweeps the folder itself (a run whose files all go through the
    stage, written with plain open, makes no atomic_write that would sweep for it)."""
    dead_file = tmp_path / ".tmp-dead.json"
    dead_file.write_text("half")
    dead_dir = tmp_path / ".tmp-deadstage"
    dead_dir.mkdir()
    (dead_dir / "a.png").write_text("half")
    past = time.time() - 3600
    for p in (dead_file, dead_dir):
        os.utime(p, (past, past))
    with fileio.replace_outputs(tmp_path, ["r.json"]) as stage:
        with open(os.path.join(stage, "r.json"), "w") as f:
            f.write("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


@pytest.mark.skipif(fileio.fcntl is None, reason="POSIX locks")
def test_run_lock_inside_itself_through_a_symlinked_spelling(tmp_path):
    """The same folder reached through a symbolic link (os.path.samefile) is the same
    run's folder: a nested run_lock through it is taken again, not refused as another run."""
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    assert os.path.samefile(real, link)
    with fileio.run_lock(real):
        with fileio.run_lock(link):
            pass


def test_check_keys_refuses_a_value_that_is_not_a_table():
    """A config value that is not a table (a string, a list) is refused as such, not
    taken apart into characters/items and reported as unknown keys."""
    for bad in ("seed", ["seed"]):
        with pytest.raises(ValueError, match="must be a table of keys") as refused:
            fileio.check_keys(bad, ["seed"], "config")
        assert not isinstance(refused.value, fileio.UnknownKeys)


@pytest.mark.parametrize("write", [lambda p: fileio.write_text(p, "new"), lambda p: fileio.write_json(p, {"new": 2})])
def test_a_write_interrupted_before_its_rename_leaves_the_earlier_file(tmp_path, monkeypatch, write):
    """write_text and write_json (bench_rollout's OUT.partial, rewritten after every row)
    replace the file in one step: a Ctrl-C before the rename leaves the earlier file whole,
    and no temporary beside it."""
    path = tmp_path / "run.json.partial"
    path.write_text('{"old": 1}')

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(fileio.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write(path)
    monkeypatch.undo()
    assert path.read_text() == '{"old": 1}' and os.listdir(tmp_path) == ["run.json.partial"]


def test_write_text_writes_utf8_whatever_the_text(tmp_path):
    """Write_text writes UTF-8 (reports hold ±, °, µ, ≥): the bytes on disk are the UTF-8
    encoding of the text."""
    text = "gain ± 5 %, 13.3 Hz ≥ f₁, µm, 90°\n"
    fileio.write_text(tmp_path / "r.md", text)
    assert (tmp_path / "r.md").read_bytes() == text.encode("utf-8")
