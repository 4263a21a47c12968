"""Relocalize every query image of a prepared scene and write poses.txt + per-query records."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from usvc.core.artifact_names import POSES_TXT, QUERIES_H5
from usvc.core.errors import UsvcError
from usvc.core.poses_file import write_poses_txt
from usvc.core.scene import Frame
from usvc.relocalize.queries_file import refinement_summary, write_queries
from usvc.relocalize.pose_estimate import PoseEstimate
from usvc.relocalize.relocalizer import Relocalizer

log = logging.getLogger(__name__)


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

