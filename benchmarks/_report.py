"""Where every benchmark leaves its figures: `results/benchmarks/<name>.json`, one naming rule.

A report's name is `<family>_<subcommand>[_<scene>][_<variant>...]` (`report_name`): the family
and subcommand that wrote it (`python -m benchmarks.query speed` -> `query_speed`, a subcommand's
hyphens as underscores), the scene it measured when it measured one (several: `office+bird+mini`),
then the variants its arguments make (a size, a device, a precision, `--final images`), then the
run's own `--variant LABEL` when given: `query_speed_mini_640x480_cuda`,
`accuracy_baseline_sift_office_stage_model`, `pipeline_scaling_keyframes_240`.

`write_report(name, result)` writes one benchmark run's dict of figures, keys in the order the
subcommand built them, with two fields added: `command`, the command line that produced it
(`python -m benchmarks.<family> <subcommand> <args>`), and `context`, what the figures depend on
besides the arguments (torch version and threads, CPU counts, thread environment, commit). The file
is written to a temporary sibling and renamed into place, so a failed or killed run never leaves a
half-written report (a previous report of the same name stays as it was).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import tempfile
from argparse import Namespace
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# USVC_BENCHMARK_DIR redirects every report (the smoke tests write into a temporary folder).
REPORT_DIR = Path(os.environ.get("USVC_BENCHMARK_DIR") or ROOT / "results" / "benchmarks")
RESERVED = ("command", "context")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]*")


def command_line(argv: Sequence[str] | None = None) -> str:
    """`python -m benchmarks.<family> <subcommand> <args>`, shell-quoted, from `argv` (default:
    sys.argv, whose first item is then the family's `__main__.py`)."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]) if argv else Path("?")
    module = script.parent.name if script.name == "__main__.py" else script.stem
    return shlex.join(["python", "-m", f"benchmarks.{module}", *argv[1:]])


def report_name(args: Namespace, scene: str | None = None, *variants: object) -> str:
    """`<family>_<subcommand>[_<scene>][_<variant>...]` for a subcommand's parsed `args` (the
    dispatcher sets `family` and `subcommand`; `--variant` comes last). Empty parts are left out."""
    parts = [args.family, args.subcommand.replace("-", "_"), scene, *variants, getattr(args, "variant", None)]
    return "_".join(str(p) for p in parts if p not in (None, ""))


def _commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10,
                             check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None


def context() -> dict:
    """What a benchmark's figures depend on besides its arguments."""
    import torch  # the benchmarks import it anyway; here only for its version and thread count

    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        affinity = os.cpu_count()
    return {"torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "cpu_count": os.cpu_count(), "cpus_available": affinity,
            "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "unset"),
            "MKL_NUM_THREADS": os.environ.get("MKL_NUM_THREADS", "unset"),
            "cpu": platform.processor() or platform.machine(), "python": platform.python_version(),
            "commit": _commit(),
            "written_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def _plain(value):
    """numpy scalars and arrays as their Python values; anything else stays a TypeError."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def write_out(path: Path, text: str) -> None:
    """A subcommand's own copy of its figures (its --out), into `path`'s folder, made if it is missing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def write_report(name: str, result: dict, *, argv: Sequence[str] | None = None,
                 directory: Path | None = None) -> Path:
    """Write `result` to <directory>/<name>.json (default results/benchmarks), atomically.

    `name`: `report_name(args, ...)`. The file holds `command` (from `argv`, default sys.argv),
    then `result`'s keys in their order, then `context`. Returns the path written.
    """
    if not _NAME.fullmatch(name):
        raise ValueError(f"report name {name!r}: letters, digits and _ . + - only")
    clash = [k for k in RESERVED if k in result]
    if clash:
        raise ValueError(f"result may not hold {clash}: write_report adds them")
    report = {"command": command_line(argv), **result, "context": context()}
    text = json.dumps(report, indent=1, default=_plain) + "\n"  # fails before anything is written
    out = Path(directory or REPORT_DIR) / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        os.fchmod(fd, 0o644)  # mkstemp's 0600 would hide the report from the rest of the group
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def scene_of(path: Path, container: str | None = None) -> str:
    """The scene folder's name for a path in it: data/<scene>/<container>/... -> <scene>; without
    `container`, `path` is the scene folder itself. A path with no `container` part: its stem."""
    path = Path(os.path.abspath(path))
    if container is None:
        return path.name
    for parent in (path, *path.parents):
        if parent.name == container:
            return parent.parent.name
    return path.stem
