"""One timed run of `query before-after`: the default query step of one tree, in a process of its own.

Run as a script by `before_after.py`, with the tree first on PYTHONPATH (so that `usvc` is that
tree's) and a working directory outside every tree: it localizes every query photo of the scene
with the scene's own map (given intrinsics, `relocalize.refine=features`), --passes times after 2
warm-up photos, and writes the seconds and the answers (pose, refusal) as JSON to the last argument.
The query photos come from this checkout's `benchmarks/_photos.py`, loaded by its path, whatever
the tree holds.

    python benchmarks/query/_revision_run.py TREE SCENE_DIR SIZE PASSES EXTRACTOR FINAL OUT
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

PHOTOS = Path(__file__).resolve().parents[1] / "_photos.py"


def _query_photos():
    spec = importlib.util.spec_from_file_location("_benchmark_photos", PHOTOS)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.query_photos


def main(tree: Path, scene_dir: Path, size: str, passes: int, extractor: str, final: str, out: Path) -> None:
    import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
    import numpy as np
    import torch

    from usvc.pipeline.paths import ScenePaths
    from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer

    if not Path(usvc.__file__).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"usvc came from {usvc.__file__}, not from {tree}")
    paths = ScenePaths.of_scene_dir(scene_dir)
    photos = _query_photos()(scene_dir, None if size == "own" else tuple(int(v) for v in size.split("x")))
    settings = {"refine": "features", "features_extractor": extractor}
    if final != "default":  # a tree from before the last pass existed ends with the guided passes
        fields = getattr(RelocalizeOptions, "__dataclass_fields__", {})
        if "features_final" in fields:
            settings["features_final"] = final
        elif final != "guided":
            raise SystemExit(f"--final {final}: {tree} has no relocalize.features_final")
    reloc = Relocalizer(paths.map_file, options=RelocalizeOptions(**settings), device="cpu")
    for rgb, intr in photos[:2]:
        reloc.localize(rgb, intr)
    seconds, answers = [], []
    for p in range(passes):
        for rgb, intr in photos:
            est = reloc.localize(rgb, intr)
            seconds.append(est.seconds["total"])
            if p == 0:
                answers.append({"R": est.R.tolist(), "t": est.t.tolist(), "rejected": est.rejected})
    out.write_text(json.dumps({"threads": torch.get_num_threads(), "queries": len(photos),
                               "median_ms": 1000 * float(np.median(seconds)), "answers": answers}))


if __name__ == "__main__":
    tree, scene_dir, size, passes, extractor, final, out = sys.argv[1:8]
    main(Path(tree), Path(scene_dir), size, int(passes), extractor, final, Path(out))
