"""The shared shell of every stage entry point (`stages/<stage>.py`).

A stage names the config groups it reads and a function that runs its step; the shell registers
those groups' schemas (and no others: `usvc.pipeline.config`), answers `--help`, validates the
config, sets the thread pools, writes the artifact folder atomically (a failed or killed stage
leaves nothing half-written), times the step and records its peak memory beside the step's own
figures in `results/<scene>/<stage>.json`, and turns a UsvcError, or a write the disk refuses (full,
read-only, no permission), into one log line and exit 1.

    stage = Stage("keypoints", keypoints=KeypointOptions)

    @stage.main
    def main(cfg, paths, out):   # out: the artifact folder being written
        return run(Inputs(tracks=paths.tracks_file), out, stage.options(cfg, "keypoints"))
"""

from __future__ import annotations

import errno
import functools
import logging
import signal
import sys
import time
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from usvc.core.atomic import WRITE_ERRNOS, WriteError, atomic_dir, final_path, write_reason
from usvc.core.device import device_record, resolve_device
from usvc.core.errors import UsvcError
from usvc.pipeline import threads
from usvc.pipeline.config import group_options, register_configs, validate
from usvc.pipeline.logs import quiet_third_party
from usvc.pipeline.metrics_file import timing_path, write_json
from usvc.pipeline.paths import METRICS_JSON, ScenePaths

log = logging.getLogger("usvc")

NOT_COMPUTED = "NOT_COMPUTED.txt"
StepFn = Callable[[DictConfig, ScenePaths, "Path | None"], "dict[str, Any] | None"]


def is_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def job_dir() -> Path:
    """This job's own directory: where a --multirun job writes instead of the DVC artifact."""
    return Path(HydraConfig.get().runtime.output_dir)


def scene_paths(cfg: DictConfig) -> ScenePaths:
    return ScenePaths(Path(cfg.data_dir), Path(cfg.results_dir), cfg.scene.name)


def peak_memory_mb() -> float:
    """Peak resident memory of this process (ru_maxrss is KiB on Linux)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def skipped_without_rendered_views(out: Path, stage: str, method: str) -> dict[str, Any]:
    """The 3DGS fit and the novel-view renders feed only `method=multiview_gs`: with
    `buffer.rendered_views: false` the stage writes an artifact saying why (NOT_COMPUTED.txt) and
    its record says `computed: false`, in milliseconds instead of minutes."""
    reason = (f"{stage} not computed: buffer.rendered_views is false (method={method}); "
              "method=multiview_gs uses it")
    (out / NOT_COMPUTED).write_text(reason + "\n")
    log.info("%s", reason)
    return {"computed": False, "reason": reason}


class Stage:
    """One pipeline stage: its name, the config groups it reads, the artifact folder it writes."""

    def __init__(self, name: str, artifact: str | None = "", record: str = "", torch_device: bool = False,
                 for_rendered_views: bool = False, **schemas: type) -> None:
        """`artifact`: the ScenePaths folder it writes ("" = the stage's name; None = none: the
        step writes where its options say, e.g. generate); `record`: the name of its
        results/<scene>/<record>.json ("" = the stage's name); `torch_device`: the step runs torch
        on `device=` (resolved before the step, recorded with its timings); `for_rendered_views`:
        the step feeds only the rendered views (`buffer.rendered_views`): without them the shell
        writes `skipped_without_rendered_views` and the step (and torch) is never loaded;
        `schemas`: group -> options dataclass."""
        self.name = name
        self.for_rendered_views = for_rendered_views
        self.artifact = name if artifact == "" else artifact
        self.record = record or name
        self.schemas = register_configs(schemas)
        self.torch_device = torch_device
        self.threads = -1  # the thread count the shell applied (from `threads=`), once it runs
        self.device = "cpu"  # the torch device the shell resolved (from `device=`), once it runs
        self._writes: tuple[Path | None, ...] = ()  # the artifact folder and record files, once it runs

    def options(self, cfg: DictConfig, group: str) -> Any:
        """The options object of one of the groups this stage reads."""
        if group not in self.schemas:
            raise KeyError(f"stage {self.name} does not read config group {group}")
        return group_options(cfg, group)

    def outputs(self, cfg: DictConfig) -> tuple[Path | None, Path]:
        """(artifact folder, record file): the DVC-tracked paths, or this job's own under --multirun."""
        if is_multirun():
            return (None if self.artifact is None else job_dir() / self.artifact), job_dir() / METRICS_JSON
        paths = scene_paths(cfg)
        return (None if self.artifact is None else getattr(paths, self.artifact)), paths.metrics(self.record)

    def _run(self, fn: StepFn, cfg: DictConfig) -> None:
        validate(cfg, self.schemas)
        skipped = self.for_rendered_views and not cfg.buffer.rendered_views
        self.threads = threads.apply(threads.resolve(cfg.threads), torch_pool=self.torch_device and not skipped)
        log.debug("threads: %d", self.threads)
        verbose = log.isEnabledFor(logging.DEBUG) or ("sfm" in self.schemas and bool(cfg.sfm.verbose))
        quiet_third_party(verbose=verbose)
        log.debug("config:\n%s", OmegaConf.to_yaml(cfg))
        ran_on = {}
        # A skipped stage runs no torch, yet a device asked for by name is still checked (a machine
        # without it stops here as at any torch stage); `auto` and `cpu` need no torch to check.
        if self.torch_device and (not skipped or str(cfg.device) not in ("auto", "cpu")):
            self.device = resolve_device(cfg.device)
            ran_on = device_record(self.device)
            log.debug("device: %s (%s)", self.device, ran_on["device_name"])
        out, record = self.outputs(cfg)
        self._writes = (out, record, timing_path(record))
        t0 = time.perf_counter()
        with atomic_dir(out) if out is not None else nullcontext(None) as tmp:
            if skipped:
                stats = skipped_without_rendered_views(tmp, self.name, cfg.method)
            else:
                stats = fn(cfg, scene_paths(cfg), tmp) or {}
            # Inside the block: a record that cannot be written (a read-only results/) leaves no
            # artifact either, so the two never disagree.
            write_json(record, {**stats, **ran_on, "seconds": time.perf_counter() - t0,
                                "peak_memory_mb": peak_memory_mb()})

    def write_failure(self, err: OSError) -> str | None:
        """The one line for a write the disk or the folder refused (full, a file-size limit, a quota,
        read-only, no permission), naming the artifact folder or record it was writing, never a
        temporary path; None for any other OSError (a traceback: a bug)."""
        if err.errno not in WRITE_ERRNOS:
            return None
        written = [p for p in self._writes if p is not None]
        if not err.filename:
            where = f" {written[0]}" if written else ""
            return f"cannot write{where}: {write_reason(err)}, nothing written"
        path = Path(err.filename)
        if final_path(path) != path:  # in an atomic block's temporary sibling: named by its artifact
            return f"{WriteError(path, err)}, nothing written"
        # A folder on the way to an artifact or record (mkdir data/<scene>): named by it.
        target = next((p for p in written if path == p or path in p.parents), None)
        if target is None:
            if err.errno in (errno.EACCES, errno.EPERM):  # reading an input, or writing elsewhere
                return f"cannot access {path}: {err.strerror}"
            target = path
        return f"cannot write {target}: {write_reason(err)}, nothing written"

    def main(self, fn: StepFn) -> Callable[[], None]:
        """The stage's entry point: `--help` prints the options it reads; otherwise Hydra composes
        the config and the step runs. A UsvcError, or a write the disk refuses (`write_failure`), is
        one log line and exit status 1 (Ctrl-C: 130)."""
        import hydra

        @hydra.main(version_base=None, config_path=str(Path(__file__).resolve().parents[2] / "conf"),
                    config_name="config")
        @functools.wraps(fn)
        def composed(cfg: DictConfig) -> None:
            # A file-size limit then fails the write (EFBIG, below) instead of killing the process.
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            try:
                self._run(fn, cfg)
            except WriteError as err:
                log.error("%s failed: %s, nothing written", self.name, err)
                sys.exit(1)
            except UsvcError as err:
                log.error("%s failed: %s", self.name, err)
                sys.exit(1)
            except OSError as err:
                line = self.write_failure(err)
                if line is None:
                    raise
                log.error("%s failed: %s", self.name, line)
                sys.exit(1)
            except KeyboardInterrupt:  # artifacts are written atomically, so nothing half-written stays
                log.error("%s interrupted, nothing written", self.name)
                sys.exit(130)

        def entry() -> None:
            args = sys.argv[1:]
            if "--help" in args or "-h" in args:
                from usvc.pipeline.stage_help import stage_help

                print(stage_help(self.name, [a for a in args if a not in ("--help", "-h")], self.schemas))
                return
            composed()

        return entry
