"""Relocalize every query image of a prepared scene and write poses.txt + per-query records."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm import tqdm

from usvc.core.errors import UsvcError
from usvc.core.h5io import write_h5
from usvc.core.pose_errors import write_poses_txt
from usvc.core.scene import Frame
from usvc.metrics.evaluate import refinement_summary
from usvc.relocalize.relocalizer import PoseEstimate, Relocalizer

log = logging.getLogger(__name__)


def relocalize_frames(relocalizer: Relocalizer, frames: list[Frame]) -> list[PoseEstimate]:
    if not frames:
        raise UsvcError("the scene has no query images to relocalize")
    results = []
    for frame in tqdm(frames, desc="relocalize", unit="query"):
        results.append(relocalizer.localize(frame.image_path, frame.camera))
    return results


def write_results(out_dir: Path, frames: list[Frame], results: list[PoseEstimate]) -> dict[str, Any]:
    """poses.txt (successful queries only), queries.h5 and queries.json; returns summary figures."""
    ok = [i for i, r in enumerate(results) if r.success]
    write_poses_txt(out_dir / "poses.txt", [frames[i].name for i in ok],
                    np.array([results[i].R for i in ok]).reshape(-1, 3, 3),
                    np.array([results[i].t for i in ok]).reshape(-1, 3))
    with write_h5(out_dir / "queries.h5") as h5:
        h5.create_dataset("name", data=np.array([f.name for f in frames], dtype=object), dtype=h5py.string_dtype())
        h5["success"] = np.array([r.success for r in results])
        h5["inliers"] = np.array([r.inliers for r in results], dtype=np.int64)
        h5["cells"] = np.array([r.cells for r in results], dtype=np.int64)
        # Refinement records: the dense RANSAC pose before refinement (NaN where it failed), so the
        # metrics stage can score "refinement off" from the same run.
        h5["refine_iterations"] = np.array([r.refine_iterations for r in results], dtype=np.int64)
        h5["refine_kept"] = np.array([r.refine_kept for r in results], dtype=bool)
        h5["initial_R"] = np.array([r.initial_R if r.success else np.full((3, 3), np.nan) for r in results],
                                   dtype=np.float64).reshape(-1, 3, 3)
        h5["initial_t"] = np.array([r.initial_t if r.success else np.full(3, np.nan) for r in results],
                                   dtype=np.float64).reshape(-1, 3)
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
            **refinement_summary([r.refine_kept for r in refined], [r.refine_iterations for r in refined])}

