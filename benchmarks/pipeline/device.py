"""Every stage of a scene on one device, end to end, as `dvc repro` runs them: one command that
measures the GPU path (or the CPU's).

For each scene it runs `python -m stages.<stage> scene=<scene> device=<device>` from `generate`
(the bundled scene) or `prepare` through `metrics`, each stage in its own process, into a work
folder (`--work`, default a temporary one) so that the checkout's artifacts stay as they are.
Then it trains the map a second time with the same seed and says whether the two maps are the
same bits, and it times the head's training steps alone at larger batches (data already on the
device). It writes `results/benchmarks/pipeline_device_<scene>_<device>.json` (after every stage,
with `complete: false` until the end, so that a run cut off still says what it measured):

- per stage: wall seconds of its process (imports included), the seconds and device the stage
  recorded itself (`<stage>.timing.json`: device, device_name);
- train: iterations, samples per second, precision; the repeat's seconds and `same_map_twice`;
- relocalize: ms per query; metrics: the (5cm,5deg)/(2cm,2deg)/(1cm,1deg) shares and medians;
- the whole run's seconds (what `dvc repro` of the scene costs from scratch on this machine);
- `head_throughput`: samples per second of `train_head` at each `--batch-sizes` value;
- `step_profile`: where a training step's time goes (`train profile`: kernels and operators a
  step, the operators with the most device time), with the step captured as a CUDA graph and not.

    python -m benchmarks.pipeline device --device cuda                   # the bundled scene
    python -m benchmarks.pipeline device --device cuda --scene mini --scene office
    python -m benchmarks.pipeline device --device cpu -- train.iterations=200   # a quick check here
    python -m benchmarks.pipeline device --device cuda --scene office --work W --from sfm --no-repeat
        # W/office/data/office/prepared (and W/office/results/office/prepared.json) made elsewhere

A real scene needs its raw data where its config points (`data/raw/<scene>`, see the README).
Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from benchmarks._report import report_name, write_report
from benchmarks.pipeline._stages import read_json, run_stage, timing_record
from benchmarks.train.step_profile import device_or_exit, profile_scene
from usvc.core.artifact_names import MAP_PT
from usvc.pipeline.paths import ScenePaths

STAGES = ("generate", "prepare", "sfm", "gaussians", "keypoints", "render", "buffer", "train", "landmarks",
          "relocalize", "metrics")
METRICS = ("acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "acc_rel_5cm_5deg", "acc_rel_2cm_2deg",
           "acc_rel_1cm_1deg", "median_trans_cm", "median_trans_rel_cm", "median_rot_deg", "n_queries", "n_failed")


def _md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def head_throughput(data: Path, scene: str, device: str, overrides: list[str], batch_sizes: list[int],
                    iterations: int) -> list[dict]:
    """Samples per second of the training steps alone (buffer already read), per batch size."""
    import usvc  # noqa: F401  (OpenMP's wait policy before torch)
    from usvc.buffer.buffer_file import read_buffer
    from usvc.pipeline.config import compose_for_script, group_options
    from usvc.sfm.tracks_file import read_median_depth
    from usvc.train.trainer import train_head

    cfg = compose_for_script(scene, overrides)
    train, model = group_options(cfg, "train"), group_options(cfg, "model")
    paths = ScenePaths(data, data.parent / "results", scene)
    buf = read_buffer(paths.buffer_file)
    depth = read_median_depth(paths.tracks_file)
    rows = []
    for batch in batch_sizes:
        opts = replace(train, iterations=iterations, batch_size=batch, validate_every=0)
        _, summary = train_head(buf, depth, opts, head_width=model.head_width, head_blocks=model.head_blocks,
                                seed=0, device=device)
        rows.append({"batch_size": batch, "iterations": iterations, "precision": summary["precision"],
                     "seconds": round(summary["train_seconds"], 2),
                     "samples_per_second": round(summary["samples_per_second"])})
        print(f"  head alone, batch {batch}: {summary['samples_per_second'] / 1e6:.2f} M samples/s", flush=True)
    return rows


def measure_scene(scene: str, device: str, work: Path, overrides: list[str], env: dict[str, str],
                  batch_sizes: list[int], head_iterations: int, first: str = STAGES[0], repeat: bool = True,
                  setting: str | None = None, profile_iterations: int = 0, name: str | None = None) -> dict:
    """`device`: where torch runs (resolved); `setting`: the device setting the stages get, as a
    user would give it (default: `device`; `auto` as `dvc repro` runs with the default config);
    `name`: the report written after every stage (none: no report until the end)."""
    data, results = work / "data", work / "results"
    common = [f"device={setting or device}", f"data_dir={data}", f"results_dir={results}",
              f"hydra.run.dir={work / 'logs'}"]
    if scene == "mini":
        common.append(f"scene.path={data / 'raw' / scene}")
    stages = [s for s in STAGES[STAGES.index(first):] if s != "generate" or scene == "mini"]
    rows = []
    t0 = time.perf_counter()
    for stage in stages:
        seconds = run_stage(stage, scene, [*common, *overrides], env)["seconds"]
        record = timing_record(results / scene, stage)
        row = {"stage": stage, "wall_seconds": round(seconds, 2), "stage_seconds": record.get("seconds"),
               "device": record.get("device"), "device_name": record.get("device_name"),
               "peak_memory_mb": record.get("peak_memory_mb")}
        if stage == "train":  # the steps alone, and whether they ran as one CUDA graph
            row |= {k: record.get(k) for k in ("train_seconds", "samples_per_second")}
            row["cuda_graph"] = read_json(ScenePaths(data, results, scene).metrics("train")).get("cuda_graph")
        rows.append(row)
        print(f"{scene:>8} {stage:>10}: {seconds:7.1f} s  {row['device'] or ''}", flush=True)
        if name:  # so far, in case the run is cut off: the finished report replaces it
            write_report(name, {"scene": scene, "device": device, "complete": False, "stages": rows})
    total = time.perf_counter() - t0
    paths = ScenePaths(data, results, scene)
    train = {**read_json(paths.metrics("train")), **timing_record(results / scene, "train")}
    reloc = {**read_json(paths.metrics("relocalize")), **timing_record(results / scene, "relocalize")}
    metrics = read_json(paths.metrics("metrics"))
    map_file = paths.map / MAP_PT
    digest = _md5(map_file)
    repeat_seconds = run_stage("train", scene, [*common, *overrides], env)["seconds"] if repeat else None
    result = {
        "scene": scene, "device": device, "complete": True, "overrides": overrides,
        "device_name": next((r["device_name"] for r in rows if r["stage"] == "train"), None),
        "total_seconds": round(total, 1), "stages": rows,
        "train": {k: train.get(k) for k in ("iterations", "samples_seen", "precision", "train_seconds",
                                            "samples_per_second", "final_loss", "final_reproj_median_px",
                                            "cuda_graph")},
        "first_stage": stages[0], "train_repeat_wall_seconds": repeat_seconds,
        "same_map_twice": _md5(map_file) == digest if repeat else None,
        "relocalize": {k: reloc.get(k) for k in ("ms_per_query", "ms_network", "ms_refine", "ms_pnp", "ms_fallback",
                                                 "queries", "answer_paths", "fallback_runs", "query_sift")},
        "metrics": {k: metrics[k] for k in METRICS if k in metrics},
    }
    if batch_sizes:
        result["head_throughput"] = head_throughput(data, scene, device, overrides,
                                                    batch_sizes, head_iterations)
    if profile_iterations:
        result["step_profile"] = profile_scene(data, scene, device, overrides, profile_iterations)
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="auto",
                        help="auto | cpu | cuda | cuda:N, given to every stage as is (auto: as dvc repro runs "
                             "with the default config); the report is named for the device it resolves to")
    parser.add_argument("--scene", action="append", help="scene to run (repeatable; default: mini)")
    parser.add_argument("--work", type=Path, help="work folder (default: a temporary one, removed afterwards)")
    parser.add_argument("--batch-sizes", type=int, nargs="*", default=[2048, 8192, 32768],
                        help="batch sizes at which to time the head's steps alone (none: skip)")
    parser.add_argument("--head-iterations", type=int, default=300)
    parser.add_argument("--profile-iterations", type=int, default=60,
                        help="training steps profiled after the stages (as `train profile`; 0: skip)")
    parser.add_argument("--from", dest="first", choices=STAGES, default=STAGES[0],
                        help="first stage to run; the earlier stages' outputs must be in --work already")
    parser.add_argument("--no-repeat", action="store_true", help="skip training the map a second time")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every stage (after --)")


def run(args: argparse.Namespace) -> None:
    device = device_or_exit(args.device)
    if args.first not in STAGES[:2] and args.work is None:
        raise SystemExit(f"--from {args.first} needs --work: the folder that holds the earlier stages' outputs")
    env = dict(os.environ)
    reports = []
    with tempfile.TemporaryDirectory(prefix="usvc-device-") as tmp:
        for scene in args.scene or ["mini"]:
            work = (args.work or Path(tmp)) / scene
            work.mkdir(parents=True, exist_ok=True)
            name = report_name(args, scene, device.replace(":", ""))
            result = measure_scene(scene, device, work, args.overrides, env, args.batch_sizes, args.head_iterations,
                                   args.first, not args.no_repeat, setting=args.device,
                                   profile_iterations=args.profile_iterations, name=name)
            reports.append(write_report(name, result))
            print(json.dumps({k: result[k] for k in ("scene", "device_name", "total_seconds", "same_map_twice",
                                                      "metrics")}, indent=1))
    print("reports:", *map(str, reports))

