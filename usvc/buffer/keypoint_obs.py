"""Keypoint observations of one augmented buffer view (paper 3.1.3: tuples (k, d_k, R_i, t_i, u_i^obs)).

An observation of kept keypoint k in a mapping image comes from its SfM track (the measured SIFT
position), or, where the track has no entry for that image, from the projection of X_k when a depth
map confirms the point is visible there (not occluded, not off the surface). Scenes without depth
use track observations only: visibility is never assumed. Positions then follow the view's
augmentation (`pixel_transform`) and must land on valid (non-padded) pixels of the augmented view.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from usvc.buffer.augment import AugmentedView
from usvc.keypoints.keypoints_file import SceneKeypoints
from usvc.model.encoder import OUTPUT_STRIDE


def depth_visible(xyz: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, depth: np.ndarray,
                  tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of points whose projection lands on a depth pixel agreeing with their depth (|d - z| < tol z)."""
    cam = xyz @ R.T + t
    z = cam[:, 2]
    front = z > 1e-9
    uv = np.full((len(xyz), 2), -1.0)
    uv[front] = (cam[front] @ K.T)[:, :2] / z[front, None]
    h, w = depth.shape
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    idx = np.flatnonzero(inside)
    d = depth[uv[idx, 1].astype(int), uv[idx, 0].astype(int)]  # COLMAP coords: pixel (r, c) spans [c, c+1)
    ok = (d > 0) & (np.abs(d - z[idx]) < tol * z[idx])
    return idx[ok], uv[idx[ok]]


def view_observations(kp: SceneKeypoints, image_name: str, view: AugmentedView, source_R: np.ndarray,
                      source_t: np.ndarray, source_K: np.ndarray, depth: np.ndarray | None,
                      depth_tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(keypoint index, pixel in the augmented view, from_depth flag) of every keypoint the view sees."""
    idx, uv = kp.by_image.get(image_name, (np.zeros(0, np.int64), np.zeros((0, 2))))
    from_depth = np.zeros(len(idx), dtype=bool)
    if depth is not None:
        vis, vis_uv = depth_visible(kp.xyz, source_R, source_t, source_K, depth, depth_tol)
        extra = ~np.isin(vis, idx)
        idx = np.concatenate([idx, vis[extra]])
        uv = np.concatenate([uv, vis_uv[extra]])
        from_depth = np.concatenate([from_depth, np.ones(int(extra.sum()), dtype=bool)])
    uv_aug = uv @ view.pixel_transform[:2, :2].T + view.pixel_transform[:2, 2]
    h, w = view.mask.shape
    inside = (uv_aug[:, 0] >= 0) & (uv_aug[:, 0] < w) & (uv_aug[:, 1] >= 0) & (uv_aug[:, 1] < h)
    keep = np.flatnonzero(inside)
    keep = keep[view.mask[uv_aug[keep, 1].astype(int), uv_aug[keep, 0].astype(int)]]
    return idx[keep].astype(np.int64), uv_aug[keep].astype(np.float32), from_depth[keep]


def sample_features(feature_map: torch.Tensor, pixels: np.ndarray) -> torch.Tensor:
    """Bilinear encoder features at COLMAP pixel positions: (C, h, w) map -> (N, C).

    Cell (i, j) describes pixel (8j + 4.5, 8i + 4.5), so a keypoint between cell centres gets the
    interpolated feature, and the coordinate the head predicts from it refers to that exact pixel.
    """
    c, h, w = feature_map.shape
    cells = (torch.from_numpy(pixels).to(feature_map.device, torch.float32) - OUTPUT_STRIDE / 2 - 0.5) / OUTPUT_STRIDE
    grid = torch.stack([cells[:, 0] / max(w - 1, 1), cells[:, 1] / max(h - 1, 1)], dim=1) * 2 - 1
    out = F.grid_sample(feature_map[None].float(), grid[None, None], mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out[0, :, 0].T
