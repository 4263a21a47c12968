"""A pretraining corpus from real captures: a scene's mapping images with its SfM tracks as labels.

The synthetic corpus has exact depth for every pixel; a real capture has only its SfM points, so
each observation's 3D point is written into the pixels around its keypoint and every other pixel
stays NaN (no label). The contrastive objective then pulls together the cells of two photos that
observe one track, and pushes apart cells that observe far-apart points: the features learn what
a frozen scene-coordinate encoder needs on real photos, viewpoint-stable and distinctive.

Only mapping images are used (the SfM tracks never contain queries), and `holdout_every` withholds
the same mapping images the buffer withholds, so a validation split stays unseen. Coordinates are
rescaled so the median scene depth is `REFERENCE_DEPTH` (the synthetic rooms' scale), which keeps
the loss's radii meaningful for scenes in arbitrary units.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from usvc.buffer.build import holdout_split
from usvc.core.artifact_names import SCENE_H5, TRACKS_H5
from usvc.core.errors import UsvcError
from usvc.core.images import read_image_bgr
from usvc.core.scene_file import read_scene_h5
from usvc.model.preprocess import luma01
from usvc.pretrain.pretrain_data import CorpusScene
from usvc.sfm.tracks_file import read_median_depth, read_tracks

log = logging.getLogger(__name__)

REFERENCE_DEPTH = 2.5  # scene units after rescaling: about the synthetic rooms' median depth
LABEL_RADIUS_PX = 4  # an observation labels the (2r+1)^2 pixels around its keypoint
PARTNERS = 8  # a photo is paired with one of the (up to) 8 photos sharing the most tracks with it


def real_corpus_scene(scene_dir: Path, holdout_every: int = 0) -> CorpusScene:
    """Mapping images of a prepared scene (`<scene_dir>/prepared`, `<scene_dir>/sfm/tracks.h5`)."""
    scene_dir = Path(scene_dir)
    tracks_path = scene_dir / "sfm" / TRACKS_H5
    if not tracks_path.is_file():
        raise UsvcError(f"{tracks_path}: no SfM tracks; run the scene's sfm stage first")
    scene = read_scene_h5(scene_dir / "prepared" / SCENE_H5)
    tracks = read_tracks(tracks_path)
    mapping, _ = holdout_split(scene.split("train"), holdout_every)
    index = {name: k for k, name in enumerate(tracks.image_names)}
    frames = [f for f in mapping if f.name in index]
    if len(frames) < 2:
        raise UsvcError(f"{scene_dir}: fewer than two mapping images with SfM observations")
    scale = REFERENCE_DEPTH / read_median_depth(tracks_path)
    point_of_obs = tracks.point_of_obs()
    sees = np.zeros((len(frames), len(tracks.xyz)), dtype=np.float32)  # frame x point incidence
    grays, labels = [], []
    for k, f in enumerate(frames):
        gray = luma01(read_image_bgr(f.image_path), rgb=False)
        h, w = gray.shape
        xyz = np.full((h, w, 3), np.nan, dtype=np.float16)
        rows = np.flatnonzero(tracks.obs_image == index[f.name])
        # COLMAP uv has the top-left pixel centre at (0.5, 0.5).
        px = np.rint(tracks.obs_uv[rows] - 0.5).astype(int)
        pts = ((tracks.xyz[point_of_obs[rows]] - tracks.xyz.mean(0)) * scale).astype(np.float16)
        r = LABEL_RADIUS_PX
        for (x, y), p in zip(px, pts):
            xyz[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] = p
        grays.append(gray)
        labels.append(xyz)
        sees[k, point_of_obs[rows]] = 1.0
    shared = sees @ sees.T  # tracks two frames have in common
    np.fill_diagonal(shared, 0.0)
    partners = []
    for row in shared:
        best = np.argsort(-row, kind="stable")[:PARTNERS]
        partners.append(best[row[best] > 0])  # never itself, never a photo sharing no track
    if not any(len(p) for p in partners):
        raise UsvcError(f"{scene_dir}: no two mapping images share an SfM track")
    log.info("real corpus %s: %d mapping images, %d tracks, scale x%.4g", scene_dir, len(frames),
             len(tracks.xyz), scale)
    return CorpusScene(seed=-1, gray=np.stack(grays), xyz=np.stack(labels), center=np.zeros(3),
                       partners=partners)
