"""The shared shell of every stage entry point: validate config, run, report errors in one line."""

from __future__ import annotations

import errno
import functools
import logging
import signal
import sys
from collections.abc import Callable
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from usvc.core.atomic import atomic_dir
from usvc.core.errors import UsvcError
from usvc.pipeline import threads
from usvc.pipeline.config import validate
from usvc.pipeline.logs import quiet_third_party
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.paths import ScenePaths

log = logging.getLogger("usvc")


def is_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def job_dir() -> Path:
    """This job's own directory: where a --multirun job writes instead of the DVC artifact."""
    return Path(HydraConfig.get().runtime.output_dir)


def scene_paths(cfg: DictConfig) -> ScenePaths:
    return ScenePaths(Path(cfg.data_dir), Path(cfg.results_dir), cfg.scene.name)


def stage_main(fn: Callable[[DictConfig], None]) -> Callable[[DictConfig], None]:
    """Validate, run, and turn a UsvcError into one log line and exit status 1 (Ctrl-C: one line, 130)."""

    @functools.wraps(fn)
    def wrapper(cfg: DictConfig) -> None:
        # A file-size limit then fails the write (EFBIG, below) instead of killing the process.
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        try:
            validate(cfg)
            log.debug("threads: %d", threads.apply(threads.resolve(cfg.threads)))
            quiet_third_party(verbose=log.isEnabledFor(logging.DEBUG) or bool(cfg.sfm.verbose))
            log.debug("config:\n%s", OmegaConf.to_yaml(cfg))
            fn(cfg)
        except UsvcError as err:
            log.error("%s failed: %s", Path(sys.argv[0]).stem, err)
            sys.exit(1)
        except OSError as err:
            if err.errno not in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
                raise
            where = f" writing {err.filename}" if err.filename else ""
            log.error("%s failed: %s%s (disk full or a file-size limit), nothing written",
                      Path(sys.argv[0]).stem, err.strerror, where)
            sys.exit(1)
        except KeyboardInterrupt:  # artifacts are written atomically, so nothing half-written stays
            log.error("%s interrupted, nothing written", Path(sys.argv[0]).stem)
            sys.exit(130)

    return wrapper


def stage_outputs(cfg: DictConfig, stage: str, artifact: str | None = None) -> tuple[Path, Path]:
    """(artifact dir, metrics file): the DVC-tracked paths, or this job's own under --multirun.

    `artifact` names the ScenePaths directory when it differs from the stage (train -> map).
    """
    name = artifact or stage
    if is_multirun():
        return job_dir() / name, job_dir() / "metrics.json"
    paths = scene_paths(cfg)
    return getattr(paths, name), paths.metrics(stage)


def peak_memory_mb() -> float:
    """Peak resident memory of this process (ru_maxrss is KiB on Linux)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


NOT_COMPUTED = "NOT_COMPUTED.txt"


def skip_unless_rendered_views(cfg: DictConfig, stage: str) -> bool:
    """The 3DGS fit and the novel-view renders feed only `method=multiview_gs`: with
    `buffer.rendered_views: false` the stage writes an empty artifact saying why, and its metrics
    say `computed: false`, in milliseconds instead of minutes. Returns True when it skipped."""
    if cfg.buffer.rendered_views:
        return False
    reason = (f"{stage} not computed: buffer.rendered_views is false (method={cfg.method}); "
              "method=multiview_gs uses it")
    out, metrics_path = stage_outputs(cfg, stage)
    with atomic_dir(out) as tmp:
        (tmp / NOT_COMPUTED).write_text(reason + "\n")
    write_json(metrics_path, {"computed": False, "reason": reason})
    log.info("%s", reason)
    return True
