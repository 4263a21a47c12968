"""The prepare step: import a scene from its source layout, pose it by SfM when it has no poses,
undistort and resize its images to the working resolution -> prepared/ (scene.h5 + images)."""

from __future__ import annotations

from pathlib import Path

from usvc.prepare.importers import load_scene
from usvc.prepare.importers.photos import skipped_entries
from usvc.prepare.options import SceneOptions
from usvc.prepare.working_images import prepare_scene
from usvc.sfm.options import SfmOptions


def run(scene: SceneOptions, out: Path, sfm: SfmOptions, *, threads: int) -> dict:
    """Write the prepared scene into `out`; `scene` says where the source is (the step's input),
    `sfm` how to pose a scene without poses (feature extraction on `threads` threads)."""
    loaded = load_scene(scene.format, scene.path, scene.name, scene.split, scene.split_n, scene.metric_scale,
                        scene.exif_focal)
    stats = prepare_scene(loaded, out, scene.working_width, scene.undistort_fov, sfm, threads=threads)
    if scene.format == "images":  # what the photo folder held besides photos (logged by the importer too)
        stats["skipped"] = skipped_entries(loaded.root)
    return stats
