"""The relocalize step: every query image of the scene through the map -> poses.txt, queries.h5
and queries.json (per-query records)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from usvc.core.errors import UsvcError
from usvc.core.scene_file import read_scene_h5
from usvc.model.map_file import read_map_header
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.relocalize_scene import relocalize_frames, write_results
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
