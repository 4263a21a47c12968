"""How well a trained map tells a view's focal length: the map's coordinates of its own mapping
views, each view's focal length estimated with its pose (P4Pf) as the relocalizer estimates a
query's, against the view's known one.

The relocalizer holds a given focal length against the one the map's coordinates imply, where
the photo's features cannot tell (a shallow view). A map that fits its scene loosely (trained
briefly, or a scene it cannot fit) implies focal lengths well off the truth for right photos,
so its verdict would refuse them. The map therefore carries this measure (`focal_error` in its
metadata: the 90th percentile over FOCAL_CHECK_VIEWS views of |ln(estimated / known focal)|),
and the relocalizer lets the map judge only when it is within the focal tolerance.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from usvc.buffer.buffer_file import TrainingBuffer
from usvc.core.absolute_pose import estimate_focal
from usvc.core.precision import autocast
from usvc.model.head import Head

FOCAL_CHECK_VIEWS = 64  # buffer views measured (all when fewer), picked with the training seed
# The relocalizer's dense RANSAC threshold: 10 px at a 480 px short side (RelocalizeOptions.max_error_px;
# a test keeps the two equal without the train step importing the query step)
FOCAL_CHECK_MAX_ERROR_PX = 10.0
FOCAL_CHECK_SHORT_SIDE = 480
FOCAL_ERROR_CAP = 10.0  # |ln ratio| recorded for a view whose focal length no pose explains


@torch.inference_mode()
def map_focal_error(head: Head, buf: TrainingBuffer, precision: str, device: str = "cpu",
                    seed: int = 0, workers: int | None = None) -> dict[str, float | int]:
    """|ln(estimated / known focal)| of the head's coordinates over up to FOCAL_CHECK_VIEWS views of
    the buffer: {"views", "median", "p90"} (FOCAL_ERROR_CAP for a view P4Pf finds no pose in).
    `workers` views are solved at a time (default: torch's thread count)."""
    views = np.unique(buf.view_index)
    rng = np.random.default_rng([seed, 3])
    picked = np.sort(rng.choice(views, size=min(FOCAL_CHECK_VIEWS, len(views)), replace=False))
    order = np.argsort(buf.view_index, kind="stable")
    starts = np.searchsorted(buf.view_index[order], picked, side="left")
    ends = np.searchsorted(buf.view_index[order], picked, side="right")
    was_training = head.training
    head.eval()
    problems = []
    for v, a, b in zip(picked, starts, ends):
        rows = order[a:b]
        x = torch.from_numpy(buf.features[rows]).to(device=device, dtype=torch.float32)
        with autocast(precision, device):
            xyz = head.forward_flat(x).float().cpu().numpy().astype(np.float64)
        problems.append((buf.pixels[rows].astype(np.float64), xyz, buf.view_K[v]))
    head.train(was_training)

    def error(problem: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
        uv, xyz, K = problem
        # views are centred on their principal point (prepared images are undistorted and centred)
        width, height = int(round(2 * K[0, 2])), int(round(2 * K[1, 2]))
        threshold = FOCAL_CHECK_MAX_ERROR_PX * min(width, height) / FOCAL_CHECK_SHORT_SIDE
        camera = estimate_focal(uv, xyz, width, height, threshold, seed)
        known = float(np.sqrt(K[0, 0] * K[1, 1]))
        return FOCAL_ERROR_CAP if camera is None else min(abs(float(np.log(camera.params[0] / known))),
                                                          FOCAL_ERROR_CAP)

    # Each view's P4Pf is seeded on its own and COLMAP's solver releases the GIL: the views run side
    # by side on the process's threads, with the same result as one after another.
    with ThreadPoolExecutor(max(1, min(workers or torch.get_num_threads(), len(problems) or 1))) as pool:
        err = np.asarray(list(pool.map(error, problems)))
    return {"views": int(len(err)), "median": round(float(np.median(err)), 4),
            "p90": round(float(np.percentile(err, 90)), 4)}
