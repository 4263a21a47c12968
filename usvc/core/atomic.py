"""Write-then-rename, so a failed or killed stage never leaves a half-written artifact."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale(final: Path) -> None:
    """Remove temporary siblings of `final` left by killed runs: only those whose process is gone,
    so a run beside this one (on the same machine) keeps its work."""
    for stale in final.parent.glob(f".{final.name}.tmp-*"):
        pid = stale.name.rsplit("-", 1)[-1]
        if pid.isdigit() and (int(pid) == os.getpid() or _pid_alive(int(pid))):
            continue
        if stale.is_dir():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)


def _make_parents(final: Path) -> list[Path]:
    """Create `final`'s missing parent folders; the ones created, deepest first."""
    missing = []
    for folder in final.parents:
        if folder.exists():
            break
        missing.append(folder)
    final.parent.mkdir(parents=True, exist_ok=True)
    return missing


def _remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders (deepest first) a failed write created, as long as they are empty: a run
    beside this one that wrote into them keeps its work."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


@contextlib.contextmanager
def atomic_dir(final: Path) -> Iterator[Path]:
    """Yield a temporary sibling directory that replaces `final` only if the block succeeds; on
    failure no trace is left, not even the parent folders it had to create."""
    final = Path(final)
    created = _make_parents(final)
    remove_stale(final)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    if tmp.exists():  # this PID's own leftover (a reused PID, or a failed block that could not clean)
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_if_empty(created)
        raise
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)


@contextlib.contextmanager
def atomic_file(final: Path) -> Iterator[Path]:
    """Yield a temporary sibling path that replaces `final` only if the block succeeds (on failure,
    as `atomic_dir`, no trace)."""
    final = Path(final)
    created = _make_parents(final)
    remove_stale(final)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        _remove_if_empty(created)
        raise
    os.replace(tmp, final)
