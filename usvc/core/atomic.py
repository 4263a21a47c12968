"""Write-then-rename, so a failed or killed stage never leaves a half-written artifact."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

from usvc.core.errors import UsvcError

# What a write can fail with that is the disk's or the folder's fault, not the program's: named in one
# line (the folder and the reason) by the stages, never a traceback.
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})
_TMP_NAME = re.compile(r"\.(.+)\.tmp-\d+")  # the temporary sibling of `name`: .name.tmp-<pid>


def final_path(path: str | Path) -> Path:
    """What a path inside an atomic block's temporary sibling will be: the artifact it belongs to
    (data/mini/.prepared.tmp-42/images/0.png -> data/mini/prepared); other paths as they are."""
    path = Path(path)
    for i, part in enumerate(path.parts):
        match = _TMP_NAME.fullmatch(part)
        if match:
            return Path(*path.parts[:i], match.group(1))
    return path


def write_reason(err: OSError) -> str:
    """The reason a write failed, in words (a file-size limit reads as "File too large")."""
    reason = err.strerror or os.strerror(err.errno or 0) or type(err).__name__
    return reason + (" (disk full or a file-size limit)" if err.errno == errno.EFBIG else "")


class WriteError(UsvcError):
    """A write the disk refused (full, read-only, a quota, no permission): names the destination, never
    the temporary path it was written to, and the reason."""

    def __init__(self, path: str | Path, err: OSError, what: str = "", where: str | Path | None = None) -> None:
        """`path`: the file being written (a temporary one is named by its artifact); `what`: what it
        is ("image"); `where`: the folder to name instead (e.g. a temporary work folder, in words)."""
        self.error, self.errno, self.reason = err, err.errno, write_reason(err)
        path = Path(path)
        folder = final_path(path)
        if where is not None:
            target = f"{what + ' ' if what else ''}{path.name} in {where}"
        elif folder != path:
            inside = path.relative_to(folder.parent / path.parts[len(folder.parts) - 1])
            target = f"{what + ' ' if what else ''}{inside} in {folder}" if str(inside) != "." else str(folder)
        else:
            target = f"{what + ' ' if what else ''}{path}"
        self.target = target
        super().__init__(f"cannot write {target}: {self.reason}")


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
