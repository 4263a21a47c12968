"""How many threads a stage uses: one setting (`threads`) for torch, OpenCV, COLMAP and BLAS.

`threads: auto` gives each job an equal share of the cores this process may use (its CPU
affinity, capped by a cgroup CPU quota), counting the jobs that run side by side on those
cores: usvc stages and `usvc` commands (as DVC queue workers and Hydra's launchers, submitit's
included, start them) and test runners, never the current process's own ancestors, and never
jobs pinned to other cores (a cluster scheduler's cpusets already keep those apart). Threads that outnumber the cores fight:
two default-threaded torch processes on 2 cores ran about 20x slower each, not 2x.

The share is decided once, when a job starts; a job that starts later sees the earlier ones.
A number (`threads=1`) is used as given; with `auto`, an OMP_NUM_THREADS the user exported is
a ceiling. Importing this module loads nothing heavy.

OpenMP threads that wait at a barrier spin by default; when another program takes one of the
cores, the spinning thread steals time from the one it waits for and a 2-thread stage ran 21x
slower. `set_wait_policy` (called when the `usvc` package is imported, so before torch or numpy
load in every stage, the CLI and the API) makes them sleep instead (OMP_WAIT_POLICY=PASSIVE),
unless the user set a policy.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from usvc.core.cores import cores_available

ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
# Set beside the thread variables usvc exports, so that a child process (a Hydra/submitit job, a
# test's subprocess) tells usvc's own export from a ceiling the user chose.
EXPORT_MARK = "USVC_EXPORTED_THREADS"
# What the user exported before usvc set anything: with `auto`, OMP_NUM_THREADS stays a ceiling.
_USER_OMP = ("" if os.environ.get(EXPORT_MARK) and os.environ.get(EXPORT_MARK) == os.environ.get("OMP_NUM_THREADS")
             else os.environ.get("OMP_NUM_THREADS", ""))
_JOB_MARKERS = ("-m stages.", "/usvc ", "-m usvc.cli", "pytest", "-m submitit.core._submit")


# OpenMP (libgomp, Intel's runtime) reads these when it loads: they must be set before torch is imported.
WAIT_POLICY = {"OMP_WAIT_POLICY": "PASSIVE"}


def set_wait_policy() -> dict[str, str]:
    """Export WAIT_POLICY for the variables the user left unset; returns what this call set."""
    set_now = {k: v for k, v in WAIT_POLICY.items() if k not in os.environ}
    os.environ.update(set_now)
    return set_now


def _ancestors(pid: int) -> set[int]:
    seen: set[int] = set()
    while pid > 1 and pid not in seen:
        seen.add(pid)
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            pid = int(stat.rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            break
    return seen


def parse_cpu_list(text: str) -> set[int]:
    """'0-3,8,10-11' (the kernel's Cpus_allowed_list) -> {0, 1, 2, 3, 8, 10, 11}."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        if part:
            lo, _, hi = part.partition("-")
            cpus.update(range(int(lo), int(hi or lo) + 1))
    return cpus


def _allowed_cpus(pid: int) -> set[int] | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("Cpus_allowed_list:"):
                return parse_cpu_list(line.split(":", 1)[1])
    except (OSError, ValueError):
        pass
    return None


def other_jobs() -> set[int]:
    """PIDs of the other usvc stages, `usvc` commands and test runs alive now that may run on this
    process's cores (Linux /proc; elsewhere none). The current process's ancestors (a pytest or
    DVC that started it) are not counted, nor are jobs whose CPU affinity shares no core with ours."""
    proc = Path("/proc")
    if not proc.is_dir():
        return set()
    mine = _ancestors(os.getpid())
    my_cpus = _allowed_cpus(os.getpid())
    found: set[int] = set()
    for entry in proc.iterdir():
        if not entry.name.isdigit() or int(entry.name) in mine:
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if "python" in cmdline and any(marker in cmdline + " " for marker in _JOB_MARKERS):
            theirs = _allowed_cpus(int(entry.name)) if my_cpus else None
            if theirs is None or theirs & my_cpus:
                found.add(int(entry.name))
    return found


def jobs_side_by_side() -> int:
    """This job plus the others alive now (see `other_jobs`)."""
    return 1 + len(other_jobs())


def resolve(setting: str | int) -> int:
    """`auto` -> cores / jobs side by side (at least 1, at most the user's OMP_NUM_THREADS);
    a positive number -> itself."""
    text = str(setting).strip().lower()
    if text == "auto":
        n = max(1, cores_available() // jobs_side_by_side())
        return min(n, int(_USER_OMP)) if _USER_OMP.isdigit() and int(_USER_OMP) > 0 else n
    if text.isdigit() and int(text) > 0:
        return int(text)
    raise ValueError(f"threads={setting!r} must be 'auto' or a positive number")


def query_workers(setting: str | int, threads: int) -> int:
    """Photos localized at a time: `auto` -> `threads` (one thread each: the relocalize stage's
    photos keep the cores busy, where one photo's own work leaves some idle); a positive number ->
    itself."""
    text = str(setting).strip().lower()
    if text == "auto":
        return max(1, threads)
    if text.isdigit() and int(text) > 0:
        return int(text)
    raise ValueError(f"query_workers={setting!r} must be 'auto' or a positive number (photos localized at a time)")


def setting_from_argv(argv: list[str], default: str = "auto") -> str:
    """The `threads=` override of a Hydra command line, before Hydra has composed anything."""
    for arg in argv:
        if arg.lstrip("+").startswith("threads="):
            return arg.split("=", 1)[1]
    return default


def export_to_env(n: int) -> None:
    """For libraries that read their thread count when they load (OpenMP, MKL, OpenBLAS) and for
    child processes. A value the user exported is kept; one a parent usvc process exported (marked
    by EXPORT_MARK) is replaced by this process's own share."""
    inherited = os.environ.get(EXPORT_MARK)
    for var in ENV_VARS:
        if var not in os.environ or (inherited is not None and os.environ[var] == inherited):
            os.environ[var] = str(n)
    if not _USER_OMP:
        os.environ[EXPORT_MARK] = str(n)


def apply(n: int, torch_pool: bool = True) -> int:
    """Set OpenCV's thread pool and torch's to `n` (COLMAP takes it through its options). Without
    `torch_pool` torch's is set only where torch is loaded already: a step that runs no torch
    does not pay for importing it (about 2 s of every such stage's start)."""
    import cv2

    cv2.setNumThreads(n)
    if torch_pool or "torch" in sys.modules:
        import torch

        torch.set_num_threads(n)
    return n
