"""Stage-aware sweep: rerun only the stages an override changes, on the upstream DVC artifacts.

    python -m tools.sweep --multirun scene=mini keypoints.tau=1.0,1.5,2.0
    python -m tools.sweep --multirun relocalize.refine_radius_px=4,8,16

Per job (its Hydra output dir): dvc.yaml says which stage is the first one any of the job's
overrides changes (usvc.pipeline.plan); the stages before it are reused from data/<scene>/
(`dvc repro`-ed first when the scene is in params.yaml), linked into <job>/data/<scene>/, and that
stage and every later one run as subprocesses with data_dir/results_dir inside the job. The job's
metrics.json collects the headline numbers; after --multirun, SweepSummary prints one row per job.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml
from hydra.core.hydra_config import HydraConfig

from usvc.core.errors import UsvcError
from usvc.pipeline.config import group_schemas
from usvc.pipeline.metrics_file import read_metrics
from usvc.pipeline.plan import StagePlan, first_affected_stage, load_plan, split_plan
from usvc.pipeline.paths import ScenePaths
from usvc.pipeline.stage import Stage, job_dir

log = logging.getLogger("usvc")
# Every group typed: an override of any stage's option is checked before a job starts. The job's
# record (the shell writes what `main` returns) is <job>/metrics.json.
stage = Stage("sweep", artifact=None, **group_schemas())

ROOT = Path(__file__).resolve().parents[1]  # where dvc.yaml, params.yaml and conf/ live
LOG_TAIL_LINES = 20
# What each rerun stage adds to the job's metrics.json, besides the metrics stage's own numbers.
STAGE_METRICS: dict[str, tuple[str, ...]] = {
    "train": ("train_seconds", "map_megabytes"),
    "relocalize": ("ms_per_query",),
    "keypoints": ("kept",),
}
NOT_HEADLINE = ("seconds", "peak_memory_mb")  # the metrics stage's own cost


def hydra_quote(value: str) -> str:
    """A Hydra override value that stays one string whatever it holds (job dirs have '=' and ',')."""
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def dvc_scenes(root: Path) -> list[str]:
    params = root / "params.yaml"
    return list((yaml.safe_load(params.read_text()) or {}).get("scenes") or []) if params.exists() else []


def _tail(path: Path, n: int = LOG_TAIL_LINES) -> str:
    lines = path.read_text(errors="replace").splitlines() if path.exists() else []
    return "\n".join(lines[-n:])


def ensure_upstream(upstream: tuple[StagePlan, ...], scene: str, source: Path, job: Path) -> None:
    """Bring the upstream artifacts up to date (DVC scenes) or require them (others)."""
    if not upstream:
        return
    listed = scene in dvc_scenes(ROOT)
    default_data = source.resolve() == (ROOT / "data").resolve()
    if listed and default_data:
        targets = [st.target(scene) for st in upstream]
        repro_log = job / "dvc_repro.log"
        t0 = time.perf_counter()
        with repro_log.open("w") as fh:
            proc = subprocess.run([sys.executable, "-m", "dvc", "--wait-for-lock", "repro", *targets], cwd=ROOT,
                                  stdout=fh, stderr=subprocess.STDOUT)
        if proc.returncode != 0:
            raise UsvcError(f"`dvc repro {' '.join(targets)}` failed (exit {proc.returncode}); "
                            f"log {repro_log}:\n{_tail(repro_log)}")
        log.info("sweep: upstream %s up to date (dvc repro, %.1f s)", " ".join(targets), time.perf_counter() - t0)
    for st in upstream:
        for artifact in st.artifacts:
            if not (source / scene / artifact).is_dir():
                how = f"`python -m {st.module} scene={scene}" + ("" if default_data else f" data_dir={source}") + "`"
                if default_data and not listed:
                    how += f", or list {scene} in params.yaml scenes and `dvc repro {st.target(scene)}`"
                raise UsvcError(f"upstream artifact {source / scene / artifact} is missing: run stage {st.name} "
                                f"first ({how})")


def link_upstream(upstream: tuple[StagePlan, ...], scene: str, source: Path, job_data: Path) -> list[Path]:
    """<job>/data/<scene>/<artifact> -> the reused artifact (absolute), for every upstream stage."""
    links = []
    (job_data / scene).mkdir(parents=True, exist_ok=True)
    for st in upstream:
        for artifact in st.artifacts:
            link = job_data / scene / artifact
            if link.is_symlink():
                link.unlink()
            link.symlink_to((source / scene / artifact).resolve(), target_is_directory=True)
            links.append(link)
    return links


def run_stage(st: StagePlan, overrides: list[str], job: Path) -> float:
    logs = job / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    log_file = logs / f"{st.name}.log"
    cmd = [sys.executable, "-m", st.module, *overrides, f"data_dir={hydra_quote(str(job / 'data'))}",
           f"results_dir={hydra_quote(str(job / 'results'))}",
           f"hydra.run.dir={hydra_quote(str(logs / st.name))}"]
    t0 = time.perf_counter()
    with log_file.open("w") as fh:
        fh.write(" ".join(cmd) + "\n")
        fh.flush()
        proc = subprocess.run(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise UsvcError(f"stage {st.name} failed (exit {proc.returncode}) after {seconds:.1f} s; "
                        f"log {log_file}:\n{_tail(log_file)}")
    log.info("sweep: %-10s %7.1f s", st.name, seconds)
    return seconds


def job_metrics(paths: ScenePaths, rerun: tuple[StagePlan, ...], first: str) -> dict[str, Any]:
    """Headline numbers of the job: the metrics stage's scalars, plus the rerun stages' costs."""
    out: dict[str, Any] = {}
    final = paths.metrics("metrics")
    if final.exists():
        out.update({k: v for k, v in read_metrics(final).items()
                    if isinstance(v, (int, float, str)) and k not in NOT_HEADLINE})
    for st in rerun:
        path = paths.metrics(st.name)
        if st.name in STAGE_METRICS and path.exists():
            values = read_metrics(path)
            out.update({k: values[k] for k in STAGE_METRICS[st.name] if k in values})
    out["first_stage"] = first
    return out


@stage.main
def main(cfg, paths, out) -> dict[str, Any]:
    job = job_dir().resolve()
    scene = cfg.scene.name
    overrides = list(HydraConfig.get().overrides.task)
    plan = load_plan(ROOT / "dvc.yaml")
    generated = bool(cfg.scene.generated)
    first = first_affected_stage(overrides, plan, generated=generated)
    upstream, rerun = split_plan(plan, first, generated=generated)
    source = Path(cfg.data_dir) if Path(cfg.data_dir).is_absolute() else ROOT / cfg.data_dir
    log.info("sweep %s: %s -> rerun %s on %s", scene, " ".join(overrides), ", ".join(st.name for st in rerun),
             ", ".join(st.target(scene) for st in upstream) or "nothing upstream")

    job.mkdir(parents=True, exist_ok=True)
    ensure_upstream(upstream, scene, source, job)
    link_upstream(upstream, scene, source, job / "data")
    forwarded = [o for o in overrides if o.split("=", 1)[0].lstrip("~+") not in ("data_dir", "results_dir")]
    if any(not st.per_scene for st in rerun):  # generate writes the raw scene: into the job, not the repo
        forwarded.append(f"scene.path={hydra_quote(str(job / 'data' / 'raw' / scene))}")
    for st in rerun:
        run_stage(st, forwarded, job)

    metrics = job_metrics(ScenePaths(job / "data", job / "results", scene), rerun, first)
    log.info("sweep %s: %s", job, ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                             for k, v in metrics.items() if k.startswith(("acc_", "median_rot"))))
    return metrics


if __name__ == "__main__":
    main()
