"""The relocalize step: every query image of the scene through the map -> poses.txt, queries.h5
and queries.json (per-query records)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from usvc.core.artifact_names import POSES_TXT, QUERIES_H5
from usvc.core.errors import UsvcError
from usvc.core.poses_file import write_poses_txt
from usvc.core.scene import Frame
from usvc.core.scene_file import read_scene_h5
from usvc.model.map_file import read_map_header
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.pose_estimate import PoseEstimate
from usvc.relocalize.queries_file import refinement_summary, write_queries
from usvc.relocalize.relocalizer import Relocalizer

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    scene: Path  # the prepared scene (prepared/scene.h5): the query images and their cameras
    map: Path  # the scene's map (map/map.pt)
    landmarks: Path  # the SfM landmarks (landmarks/landmarks.h5), read when relocalize.refine=features


def run(inputs: Inputs, out: Path, options: RelocalizeOptions, *, encoder_weights: str | None, seed: int,
        scene: str, device: str = "cpu", workers: int = 1) -> dict:
    """Relocalize the queries of `scene` (the network on `device`, `workers` photos at a time) into
    `out`; returns the step's figures and timings."""
    frames = read_scene_h5(inputs.scene).split("test")
    mapped = read_map_header(inputs.map)["metadata"].get("scene")
    if scene != mapped:
        raise UsvcError(f"{inputs.map} is a map of scene {mapped!r}, not of {scene!r}: "
                        "rerun the train stage for this scene")
    relocalizer = Relocalizer(inputs.map, encoder_weights, options, device=device, seed=seed,
                              landmarks=inputs.landmarks if options.refine == "features" else None)
    results = relocalize_frames(relocalizer, frames, workers)
    stats = write_results(out, frames, results)
    log.info("relocalize (%s): %d queries, %d failed, %.0f ms/query", relocalizer.precision,
             stats["queries"], stats["failed"], stats["ms_per_query"])
    return {**stats, "precision": relocalizer.precision, "map_precision": relocalizer.metadata.get("precision", "fp32"),
            "query_workers": workers, "query_sift": str(relocalizer.sift)}


def relocalize_frames(relocalizer: Relocalizer, frames: list[Frame], workers: int = 1) -> list[PoseEstimate]:
    """Every frame's answer, in order, `workers` photos at a time (`Relocalizer.localize_many`)."""
    if not frames:
        raise UsvcError("the scene has no query images to relocalize")
    answers = relocalizer.localize_many(((f.image_path, f.camera) for f in frames), workers)
    return list(tqdm(answers, total=len(frames), desc="relocalize", unit="query"))


def _fallback_summary(results: list[PoseEstimate]) -> dict[str, Any]:
    ran = [r.seconds["fallback"] for r in results if "fallback" in r.seconds]
    return {"fallback_runs": len(ran), "ms_fallback": float(np.mean(ran) * 1000) if ran else 0.0}


def write_results(out_dir: Path, frames: list[Frame], results: list[PoseEstimate]) -> dict[str, Any]:
    """poses.txt (successful queries only), queries.h5 and queries.json; returns summary figures."""
    ok = [i for i, r in enumerate(results) if r.success]
    write_poses_txt(out_dir / POSES_TXT, [frames[i].name for i in ok],
                    np.array([results[i].R for i in ok]).reshape(-1, 3, 3),
                    np.array([results[i].t for i in ok]).reshape(-1, 3))
    write_queries(out_dir / QUERIES_H5, [f.name for f in frames], [r.success for r in results],
                  [r.inliers for r in results], [r.cells for r in results],
                  [r.refine_iterations for r in results], [r.refine_kept for r in results],
                  [r.initial_R for r in results], [r.initial_t for r in results])
    # Timings are not part of the artifact (two runs that give the same poses give the same bytes);
    # the stage reports them in relocalize.timing.json.
    records = {f.name: {k: v for k, v in r.to_json().items() if k != "seconds"} for f, r in zip(frames, results)}
    (out_dir / "queries.json").write_text(json.dumps(records, indent=1) + "\n")
    total = np.array([r.seconds["total"] for r in results])
    refined = [results[i] for i in ok]  # refinement only runs where the dense solve succeeded
    return {"queries": len(frames), "failed": len(frames) - len(ok),
            "rejected": sum(bool(r.rejected) for r in results),  # low confidence or contradicted intrinsics
            "ms_per_query": float(total.mean() * 1000),
            "ms_network": float(np.mean([r.seconds["network"] for r in results]) * 1000),
            "ms_pnp": float(np.mean([r.seconds["pnp"] for r in results]) * 1000),
            "ms_refine": float(np.mean([r.seconds.get("refine", 0.0) for r in results]) * 1000),
            "median_inliers": float(np.median([r.inliers for r in results])),
            "query_seconds": {f.name: r.seconds for f, r in zip(frames, results)},
            # which evidence gave the answers: guided / global (features), keypoints, dense (the learned pose)
            "answer_paths": {p: sum(r.refine_path == p for r in refined)
                             for p in sorted({r.refine_path for r in refined})},
            "median_feature_inliers": float(np.median([r.feature_inliers for r in refined])) if refined else 0.0,
            # SIFT + PnP's matching (the fallback): how often it ran, and what it cost where it ran
            **_fallback_summary(results),
            **refinement_summary([r.refine_kept for r in refined], [r.refine_iterations for r in refined])}
