"""Why a map is (in)accurate: how well its head fits the views it trained on, how well it generalises
to views it never saw, how far its coordinates at SfM keypoints are from the triangulated points, and
how distinctive the encoder's features are on this scene.

- **Reprojection per view**: every 8x8 cell's predicted scene coordinate projected with the view's
  true pose; the median over cells of the pixel distance to the cell centre (ACE's training error,
  but on the whole image, unaugmented). Cells predicted behind the camera count as `BEHIND_PX`.
- **Keypoint 3D error**: the predicted coordinate at each SfM observation of the view (bilinear
  between cells) against its triangulated point, as a fraction of the median scene depth.
- **Track-retrieval probe**: for every observation of every track, is its nearest neighbour
  (cosine of the encoder's feature there, over the observations in *other* images) an observation
  of the same track? A scene-independent encoder that describes real photos well scores high.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from usvc.buffer.keypoint_obs import sample_features
from usvc.core.scene import Camera
from usvc.model.encoder import Encoder, cell_centers
from usvc.model.preprocess import normalise
from usvc.sfm.tracks_file import Tracks

BEHIND_PX = 1000.0  # reprojection error charged to a coordinate predicted behind the camera


@dataclass(frozen=True)
class ViewFit:
    median_px: float  # median reprojection over the view's cells
    inlier_10px: float  # fraction of cells within 10 px
    keypoint_err_rel: float  # median keypoint 3D error / median depth; NaN without observations
    keypoints: int


def reprojection_px(coords: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(h, w, 3) world coordinates of the cells -> (h, w) pixel error against the cell centres."""
    h, w, _ = coords.shape
    cam = coords.reshape(-1, 3) @ R.T + t
    z = cam[:, 2]
    uv = cam @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uv[:, :2] / uv[:, 2:]
    centres = cell_centers(h, w, "colmap").reshape(2, -1).T.numpy().astype(np.float64)
    err = np.linalg.norm(uv - centres, axis=1)
    err = np.where((z > 0) & np.isfinite(err), np.minimum(err, BEHIND_PX), BEHIND_PX)
    return err.reshape(h, w)


def keypoint_errors(coords: np.ndarray, uv: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Distance between the bilinear prediction at each keypoint (COLMAP pixels) and its 3D point."""
    if len(uv) == 0:
        return np.empty(0)
    grid = torch.from_numpy(np.ascontiguousarray(coords.transpose(2, 0, 1))).float()
    pred = sample_features(grid, uv.astype(np.float32)).double().numpy()
    return np.linalg.norm(pred - xyz, axis=1)


def view_fit(coords: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, uv: np.ndarray, xyz: np.ndarray,
             median_depth: float) -> ViewFit:
    err = reprojection_px(coords, R, t, K)
    kp = keypoint_errors(coords, uv, xyz)
    return ViewFit(float(np.median(err)), float(np.mean(err < 10.0)),
                   float(np.median(kp) / median_depth) if len(kp) else float("nan"), int(len(kp)))


def view_fit_at(coords: np.ndarray, image_size: tuple[int, int], camera: Camera, R: np.ndarray, t: np.ndarray,
                uv: np.ndarray, xyz: np.ndarray, median_depth: float) -> ViewFit:
    """`view_fit` of coordinates predicted on the image resized to ``image_size`` (width, height), a
    map's working resolution: the camera and the observations (COLMAP pixels, which scale exactly)
    are scaled to that size, so errors are in working-image pixels."""
    w, h = image_size
    scaled = camera.scaled(w, h)
    return view_fit(coords, R, t, scaled.K, np.asarray(uv, np.float64) * [w / camera.width, h / camera.height],
                    xyz, median_depth)


def observations_of(tracks: Tracks, image_name: str) -> tuple[np.ndarray, np.ndarray]:
    """(uv, xyz) of every SfM observation in one image (empty if the image has none)."""
    if image_name not in tracks.image_names:
        return np.empty((0, 2)), np.empty((0, 3))
    idx = tracks.image_names.index(image_name)
    sel = np.asarray(tracks.obs_image) == idx
    return np.asarray(tracks.obs_uv, np.float64)[sel], np.asarray(tracks.xyz, np.float64)[tracks.point_of_obs()[sel]]


@torch.inference_mode()
def track_retrieval(encoder: Encoder, images: dict[str, np.ndarray], tracks: Tracks, max_obs: int = 20000,
                    seed: int = 0) -> dict[str, float]:
    """The probe: fraction of observations whose nearest other-image observation is of the same track.

    ``images`` maps image names to gray [0, 1] images at the tracks' resolution. Observations are
    subsampled to ``max_obs`` (seeded) to bound the pairwise similarity computation.
    """
    encoder = encoder.eval()
    point = tracks.point_of_obs()
    image = np.asarray(tracks.obs_image)
    keep = np.isin(np.asarray(tracks.image_names)[image], list(images)) & (tracks.track_length[point] >= 2)
    idx = np.flatnonzero(keep)
    if len(idx) > max_obs:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_obs, replace=False))
    feats = torch.empty((len(idx), 0))
    parts = []
    for m, name in enumerate(tracks.image_names):
        sel = idx[image[idx] == m]
        if len(sel) == 0 or name not in images:
            continue
        fmap = encoder(normalise(images[name]))[0]
        parts.append((sel, sample_features(fmap, np.asarray(tracks.obs_uv, np.float32)[sel])))
    order = np.concatenate([s for s, _ in parts])
    feats = F.normalize(torch.cat([f for _, f in parts]).float(), dim=1)
    pts = torch.from_numpy(point[order])
    imgs = torch.from_numpy(image[order])
    hits = 0
    for start in range(0, len(order), 2048):
        sim = feats[start:start + 2048] @ feats.T
        sim[imgs[start:start + 2048, None] == imgs[None]] = -2.0  # only other images' observations
        nn_idx = sim.argmax(dim=1)
        hits += int((pts[nn_idx] == pts[start:start + 2048]).sum())
    return {"observations": int(len(order)), "same_track_nn": hits / max(len(order), 1)}
