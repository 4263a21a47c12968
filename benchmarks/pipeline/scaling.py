"""How the cost of a map grows with the number of mapping photos: every stage on the generated
room at several sizes (or on a real scene), seconds, peak memory and bytes per stage, the query's
time, and the accuracy of the final and of the learned pose.

For each size N the miniature room is generated with N mapping frames (`n_map_sequences` arcs of
N / n_map_sequences frames each, the same 20 queries at 320 x 240) as the scene `room<N>`
(data/raw/room<N>, data/room<N>, results/room<N>), and each stage runs in a process of its own,
as `dvc repro` runs it (`python -m stages.<stage> scene=mini scene.name=room<N> ...`). With
`--scene NAME` a configured scene (its photos in place) is measured instead, once. Once every size
is built, one query at a time is timed on each (`--query-rounds` rounds, the sizes alternated: the
machine's speed drifts over the minutes a size's stages take).

    python -m benchmarks.pipeline scaling --frames 60 240 960 3840
    python -m benchmarks.pipeline scaling --frames 60 240 -- train.iterations=200
    python -m benchmarks.pipeline scaling --scene office

Writes `results/benchmarks/pipeline_scaling[_<scene>].json` (<scene> with --scene): per size, every
stage's wall seconds (interpreter start included) and peak resident memory (what the stage records
about itself), bytes on disk of the map and of the landmarks, the median and mean seconds a query
in the relocalize stage (two queries side by side, its `query_workers`) and the median of one query
at a time (`query_latency_ms`: `benchmarks.query speed`, photo in and pose out, with its parts, the
median over the rounds; `query_latency_rounds_ms` each round's),
the share of queries answered by the learned pose
without the fallback, and the metrics (`acc_*` of the final answer, `initial_acc_*` of the learned
pose, with the training fit). With more than one size, a PNG of the same name beside it plots seconds per
stage, query milliseconds, bytes and peak memory against the number of photos, log-log. Run it on
an otherwise idle machine; `--keep` keeps each size's data/ and results/ folders (removed otherwise).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._report import REPORT_DIR, ROOT, report_name, write_report
from usvc.pipeline.paths import ScenePaths

STAGES = ("prepare", "sfm", "gaussians", "keypoints", "render", "buffer", "train", "landmarks", "relocalize",
          "metrics")
SEQUENCES = 2  # the room's mapping arcs (conf/generate: n_map_sequences)


def run_stage(stage: str, args: list[str], env: dict[str, str], checkout: Path) -> float:
    """One stage in a child process; its wall seconds. A failed stage stops the benchmark with its last line."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", f"stages.{stage}", *args], cwd=checkout, env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"stage {stage} ({' '.join(args)}) failed (exit {proc.returncode}): {tail[0]}")
    return time.perf_counter() - t0


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else 0


def _median(values: list[float]) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return s[len(s) // 2] if len(s) % 2 else 0.5 * (s[len(s) // 2 - 1] + s[len(s) // 2])


def query_figures(paths: ScenePaths) -> dict:
    """Seconds a query (the relocalize stage's own per-query timings) and the share of queries
    answered without the fallback (SIFT + PnP's evidence)."""
    timing = _json(paths.results_dir / paths.scene / "relocalize.timing.json")
    record = _json(paths.metrics("relocalize"))
    seconds = [s["total"] for s in (timing.get("query_seconds") or {}).values() if isinstance(s, dict) and "total" in s]
    out: dict = {"queries": record.get("queries")}
    if seconds:
        out |= {"query_ms_median": round(1000 * _median(seconds), 1),
                "query_ms_mean": round(1000 * sum(seconds) / len(seconds), 1)}
    if record.get("queries"):
        out["share_without_fallback"] = round(1 - record.get("fallback_runs", 0) / record["queries"], 4)
    return out


def query_latency(scene_dir: Path, env: dict[str, str], checkout: Path) -> dict:
    """One query at a time on the scene's own map, photo in and pose out (`benchmarks.query speed
    --refine features`, in a process of its own, on the stages' threads): the median milliseconds
    of the whole query and of its parts over the queries, after two warm-up ones. The relocalize
    stage's own timings are of two queries side by side (its `query_workers`): throughput, not the
    wait of one photo."""
    with tempfile.TemporaryDirectory() as reports:
        proc = subprocess.run([sys.executable, "-m", "benchmarks.query", "speed", "--scene-dir", str(scene_dir),
                               "--refine", "features"], cwd=checkout,  # its usvc, these benchmarks where it has none
                              env={**env, "USVC_BENCHMARK_DIR": reports,
                                   "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))},
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if proc.returncode != 0:
            tail = proc.stderr.strip().splitlines()[-1:] or ["(no output)"]
            raise SystemExit(f"query latency of {scene_dir} failed (exit {proc.returncode}): {tail[0]}")
        report = _json(next(Path(reports).glob("*.json")))
    return {k: round(1000 * v, 1) for k, v in report["seconds_median"]["features"].items()}


def measure(scene_args: list[str], name: str, overrides: list[str], threads: int, checkout: Path) -> dict:
    """Every stage of one scene, in order: seconds, peak memory, bytes, query figures and metrics."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    paths = ScenePaths(checkout / "data", checkout / "results", name)
    args = [*scene_args, f"threads={threads}", *overrides]
    stages = {}
    for stage in STAGES:
        seconds = run_stage(stage, args, env, checkout)
        record = "prepared" if stage == "prepare" else stage
        timing = _json(paths.results_dir / name / f"{record}.timing.json")
        peak = timing.get("peak_memory_mb")
        stages[stage] = {"seconds": round(seconds, 2),
                         "peak_memory_mb": round(peak, 1) if isinstance(peak, (int, float)) else None}
        print(f"  {name} {stage:>10} {seconds:7.1f} s", flush=True)
    metrics = _json(paths.metrics("metrics"))
    train = _json(paths.metrics("train"))
    sfm = _json(paths.metrics("sfm"))
    return {
        "scene": name,
        "mapping_frames": _json(paths.metrics("prepared")).get("train"),
        "stages": stages,
        "mapping_seconds": round(sum(s["seconds"] for k, s in stages.items() if k not in ("relocalize", "metrics")), 1),
        "peak_memory_mb": max((s["peak_memory_mb"] or 0 for s in stages.values()), default=None),
        "map_bytes": _bytes(paths.map_file),
        "landmarks_bytes": _bytes(paths.landmarks),
        "sfm_points": sfm.get("points"),
        "sfm_mean_track_length": sfm.get("mean_track_length"),
        "train_steps": train.get("iterations") or train.get("steps"),
        "train_fit": {k: v for k, v in train.items() if "reprojection" in k or "median_px" in k or k.endswith("_px")},
        **query_figures(paths),
        "metrics": {k: v for k, v in metrics.items() if k.startswith(("acc_", "initial_acc_", "median_", "initial_median_"))
                    or k in ("n_queries", "n_failed")},
    }


def query_rounds(rows: list[dict], checkout: Path, threads: int, rounds: int) -> None:
    """`query_latency` of every measured size, `rounds` times with the sizes alternated (the
    machine's speed drifts by a fifth over the minutes one size's stages take, so a size measured
    right after its own stages is compared with another measured at another time): each row's
    `query_latency_ms` is the median over the rounds of each part's figure, `query_latency_rounds_ms`
    the rounds' totals."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    figures: list[list[dict]] = [[] for _ in rows]
    for round_ in range(rounds):
        for row, seen in zip(rows, figures):
            scene_dir = ScenePaths(checkout / "data", checkout / "results", row["scene"]).scene_dir
            seen.append(query_latency(scene_dir, env, checkout))
            print(f"  {row['scene']} query round {round_ + 1}: {seen[-1]['total']} ms", flush=True)
    for row, seen in zip(rows, figures):
        row["query_latency_ms"] = {k: round(float(_median([f[k] for f in seen])), 1) for k in seen[0]}
        row["query_latency_rounds_ms"] = [f["total"] for f in seen]


def plot(rows: list[dict], out: Path) -> None:
    """Seconds per stage, query ms, bytes and peak memory against mapping photos, log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["mapping_frames"] for r in rows]
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    for stage in STAGES:
        axes[0].plot(n, [max(r["stages"][stage]["seconds"], 1e-2) for r in rows], marker="o", label=stage)
    axes[0].set_title("seconds per stage")
    axes[0].legend(fontsize=7)
    axes[1].plot(n, [r.get("query_ms_median") or float("nan") for r in rows], marker="o", label="stage, median")
    axes[1].plot(n, [r.get("query_ms_mean") or float("nan") for r in rows], marker="o", label="stage, mean")
    axes[1].plot(n, [(r.get("query_latency_ms") or {}).get("total") or float("nan") for r in rows], marker="o",
                 label="one at a time, median")
    axes[1].set_title("ms a query")
    axes[1].legend(fontsize=7)
    axes[2].plot(n, [r["map_bytes"] / 1e6 for r in rows], marker="o", label="map")
    axes[2].plot(n, [r["landmarks_bytes"] / 1e6 for r in rows], marker="o", label="landmarks")
    axes[2].set_title("MB on disk")
    axes[2].legend(fontsize=7)
    axes[3].plot(n, [r["peak_memory_mb"] for r in rows], marker="o")
    axes[3].set_title("peak memory of a stage, MB")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("mapping photos")
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, nargs="+", default=[60, 240, 960, 3840],
                        help="mapping frames of the generated room, one run per value (even numbers)")
    parser.add_argument("--scene", help="measure this configured scene (conf/scene/NAME.yaml) instead of the room")
    parser.add_argument("--threads", type=int, default=2, help="the stages' threads (and OMP_NUM_THREADS)")
    parser.add_argument("--keep", action="store_true", help="keep each generated size's data/ and results/")
    parser.add_argument("--query-rounds", type=int, default=3,
                        help="rounds of one-at-a-time queries over the sizes, alternated, after every size is built")
    parser.add_argument("--checkout", type=Path, default=ROOT,
                        help="the checkout whose stages run and whose data/ and results/ they write (default: this one)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every stage (after --)")


def run(args: argparse.Namespace) -> None:
    checkout = args.checkout.resolve()
    rows, generated = [], []
    try:
        if args.scene:
            rows.append(measure([f"scene={args.scene}"], args.scene, args.overrides, args.threads, checkout))
        for frames in [] if args.scene else args.frames:
            if frames < 2 * SEQUENCES or frames % SEQUENCES:
                args.parser.error(f"--frames {frames}: a multiple of {SEQUENCES}, at least {2 * SEQUENCES}")
            scene = f"room{frames}"
            scene_args = ["scene=mini", f"scene.name={scene}", f"scene.path=data/raw/{scene}"]
            env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
            generated.append(scene)
            t0 = time.perf_counter()
            run_stage("generate", [*scene_args, f"generate.frames_per_map_sequence={frames // SEQUENCES}",
                                   *[o for o in args.overrides if o.startswith("generate.")]], env, checkout)
            generate_s = time.perf_counter() - t0
            print(f"  {scene}   generate {generate_s:7.1f} s", flush=True)
            row = measure(scene_args, scene, [o for o in args.overrides if not o.startswith("generate.")],
                          args.threads, checkout)
            row["generate_seconds"] = round(generate_s, 2)
            rows.append(row)
        query_rounds(rows, checkout, args.threads, args.query_rounds)
    finally:
        for scene in [] if args.keep else generated:
            for folder in (checkout / "data" / "raw" / scene, checkout / "data" / scene, checkout / "results" / scene):
                shutil.rmtree(folder, ignore_errors=True)
    name = report_name(args, args.scene)
    result = {"sizes": rows, "threads": args.threads, "query_rounds": args.query_rounds, "overrides": args.overrides}
    path = write_report(name, result)
    if len(rows) > 1:
        plot(rows, REPORT_DIR / f"{name}.png")
    for r in rows:
        print(f"{r['scene']}: {r['mapping_frames']} photos, mapping {r['mapping_seconds']} s, query "
              f"{r['query_latency_ms']['total']} ms one at a time ({r.get('query_ms_median')} ms in the stage), "
              f"map+landmarks {(r['map_bytes'] + r['landmarks_bytes']) / 1e6:.1f} MB, peak {r['peak_memory_mb']} MB, "
              f"acc {r['metrics'].get('acc_5cm_5deg')}")
    print(f"-> {path}")
