import pytest

from usvc.core.atomic import atomic_dir, atomic_file


def test_atomic_dir_replaces_only_on_success(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_dir(final) as tmp:
            (tmp / "half.txt").write_text("half")
            raise RuntimeError("killed")
    assert (final / "old.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    with atomic_dir(final) as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in final.iterdir()) == ["new.txt"]


def test_atomic_file_leaves_nothing_on_failure(tmp_path):
    final = tmp_path / "m.json"
    with pytest.raises(ValueError):
        with atomic_file(final) as tmp:
            tmp.write_text("{")
            raise ValueError
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", ["dir", "file"])
def test_a_failed_write_removes_the_folders_it_created_and_only_those(tmp_path, kind):
    write = atomic_dir if kind == "dir" else atomic_file
    kept = tmp_path / "data"
    kept.mkdir()
    (kept / "other").write_text("another scene's")
    with pytest.raises(RuntimeError):
        with write(kept / "scene" / "stage" / "out"):
            raise RuntimeError("failed")
    assert sorted(p.name for p in kept.iterdir()) == ["other"], "no empty data/scene/stage/ left"
    with write(kept / "scene" / "out") as tmp:
        (tmp / "x" if kind == "dir" else tmp).write_text("x")
    assert (kept / "scene" / "out").exists()
    with pytest.raises(RuntimeError):
        with write(kept / "scene" / "more"):
            raise RuntimeError("failed")
    assert (kept / "scene" / "out").exists(), "a folder that holds other work stays"


def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid  # reaped: no process has this id now (unless reused within the test)


def test_a_live_runs_temporary_dir_survives_another_run(tmp_path):
    """Two runs of one stage at once: the second must not delete the first's work as stale."""
    import subprocess
    import sys

    final = tmp_path / "sfm"
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        theirs = tmp_path / f".sfm.tmp-{live.pid}"
        theirs.mkdir()
        (theirs / "work.db").write_text("in progress")
        dead = tmp_path / f".sfm.tmp-{_dead_pid()}"
        dead.mkdir()
        with atomic_dir(final) as tmp:
            (tmp / "out.txt").write_text("done")
        assert (theirs / "work.db").read_text() == "in progress"
        assert not dead.exists(), "a killed run's leftover is removed"
        assert (final / "out.txt").read_text() == "done"
    finally:
        live.kill()
        live.wait()


def test_atomic_file_removes_a_killed_runs_leftover(tmp_path):
    final = tmp_path / "scene.h5"
    left = tmp_path / f".scene.h5.tmp-{_dead_pid()}"
    left.write_bytes(b"half")
    with atomic_file(final) as tmp:
        tmp.write_bytes(b"whole")
    assert final.read_bytes() == b"whole" and not left.exists()
