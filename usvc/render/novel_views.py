"""Novel views around keypoint clusters, rendered from the 3DGS model (paper 3.1.3), with the
keypoint observations they contain.

A view starts from a mapping pose: a random keypoint that image sees, and the kept keypoints it
sees within a radius of it, form a cluster; the camera orbits the cluster's centre by a random
rotation of up to `max_angle_deg` (so the cluster stays where it was in the image) and moves by
up to `max_translation_rel` of the cluster's depth. A pose is kept when most of the cluster stays
in the frame and enough keypoints are visible. Visibility comes from the rendered depth and
opacity at the keypoint's projection: in front, not occluded, on a surface the model has.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers
from usvc.core.pose_errors import rotation_error_deg
from usvc.core.scene import Frame
from usvc.keypoints.keypoints_file import SceneKeypoints
from usvc.render.views_file import NovelView
from usvc.render.options import RenderOptions
from usvc.splat.gaussians import Gaussians
from usvc.splat.rasterize import View, render

log = logging.getLogger(__name__)


def orbit_pose(R: np.ndarray, t: np.ndarray, centre: np.ndarray, rotation: np.ndarray,
               shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera pose after rotating the camera rigidly about `centre` by `rotation` (world
    frame) and then moving its centre by `shift`: points near `centre` stay near their pixels."""
    C = camera_centers(R, t)
    C_new = centre + rotation @ (C - centre) + shift
    R_new = R @ rotation.T
    return R_new, -R_new @ C_new


def project(xyz: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = xyz @ R.T + t
    z = p[:, 2]
    uv = (p @ K.T)[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
    return uv, z


def visible_keypoints(xyz: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, depth: np.ndarray,
                      alpha: np.ndarray, tol: float, min_alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """(ids, uv) of the keypoints whose projection lands on rendered surface at their own depth."""
    h, w = depth.shape
    uv, z = project(xyz, R, t, K)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    ids = np.flatnonzero(inside)
    col, row = np.floor(uv[ids, 0]).astype(int), np.floor(uv[ids, 1]).astype(int)
    d, a = depth[row, col], alpha[row, col]
    ok = (a >= min_alpha) & (np.abs(d - z[ids]) < tol * z[ids])
    return ids[ok], uv[ids[ok]]


def _cluster(kp: SceneKeypoints, seen: np.ndarray, R: np.ndarray, t: np.ndarray, opts: RenderOptions,
             rng: np.random.Generator) -> np.ndarray | None:
    seed = kp.xyz[rng.choice(seen)]
    depth = float((R @ seed + t)[2])
    if depth <= 0:
        return None
    near = seen[np.linalg.norm(kp.xyz[seen] - seed, axis=1) < opts.cluster_radius_rel * depth]
    return near if len(near) >= opts.min_cluster_keypoints else None


def _in_frame(uv: np.ndarray, z: np.ndarray, w: int, h: int) -> np.ndarray:
    return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)


@torch.no_grad()
def render_novel_views(model: Gaussians, frames: list[Frame], kp: SceneKeypoints,
                       opts: RenderOptions, tile: int = 8, device: str = "cpu") -> tuple[list[NovelView], dict]:
    """`opts.views` novel views (fewer only when the tries run out; the stats say how many),
    rasterised on `device` (the poses are drawn on the host, so the views are the same ones)."""
    model = model.to(device)
    rng = np.random.default_rng(opts.seed)
    sources = [f for f in frames if len(kp.by_image.get(f.name, (np.zeros(0),))[0]) >= opts.min_cluster_keypoints]
    if not sources:
        raise UsvcError(f"no mapping image sees {opts.min_cluster_keypoints} kept keypoints: nothing to render "
                        "novel views around (lower render.min_cluster_keypoints or keypoints.tau)")
    views: list[NovelView] = []
    tries = rejected_cluster = rejected_visible = 0
    max_angle = np.deg2rad(opts.max_angle_deg)
    order: list[int] = []
    with tqdm(total=opts.views, desc="render", unit="view") as bar:
        while len(views) < opts.views and tries < opts.views * opts.max_tries:
            if not order:
                order = rng.permutation(len(sources)).tolist()
            f = sources[order.pop()]
            tries += 1
            s = 1.0 if opts.width in (0, f.camera.width) else opts.width / f.camera.width
            w, h = round(f.camera.width * s), round(f.camera.height * s)
            K = np.asarray(f.camera.K, dtype=np.float64).copy()
            K[:2] *= s
            seen = np.unique(kp.by_image[f.name][0])
            cluster = _cluster(kp, seen, f.R, f.t, opts, rng)
            if cluster is None:
                rejected_cluster += 1
                continue
            centre = kp.xyz[cluster].mean(0)
            depth = float((f.R @ centre + f.t)[2])
            axis = rng.normal(size=3)
            rot = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0, max_angle)).as_matrix()
            direction = rng.normal(size=3)
            shift = direction / np.linalg.norm(direction) * rng.uniform(0, opts.max_translation_rel) * depth
            R, t = orbit_pose(f.R, f.t, centre, rot, shift)
            uv, z = project(kp.xyz[cluster], R, t, K)
            if _in_frame(uv, z, w, h).mean() < 0.5:
                rejected_cluster += 1
                continue
            view = View(torch.tensor(R, dtype=torch.float32), torch.tensor(t, dtype=torch.float32),
                        torch.tensor(K, dtype=torch.float32), w, h).to(device)
            out = render(model, view, tile=tile)
            d, a = out.depth.cpu().numpy().astype(np.float32), out.alpha.cpu().numpy()
            ids, kuv = visible_keypoints(kp.xyz, R, t, K, d, a, opts.depth_tolerance, opts.min_alpha)
            if len(ids) < opts.min_visible_keypoints:
                rejected_visible += 1
                continue
            rgb = (out.rgb.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
            views.append(NovelView(f.name, R, t, K, rgb, d, ids.astype(np.int32), kuv.astype(np.float32),
                                   rotation_error_deg(R, f.R),
                                   float(np.linalg.norm(camera_centers(R, t) - camera_centers(f.R, f.t)))))
            bar.update(1)
    if not views:
        raise UsvcError(f"no novel view kept after {tries} tries ({rejected_cluster} without a keypoint cluster in "
                        f"frame, {rejected_visible} with fewer than {opts.min_visible_keypoints} visible keypoints)")
    stats = {"views": len(views), "views_requested": opts.views, "tries": tries,
             "rejected_cluster": rejected_cluster, "rejected_visibility": rejected_visible,
             "keypoint_observations": int(sum(len(v.keypoint_ids) for v in views)),
             "keypoints_observed": int(len(np.unique(np.concatenate([v.keypoint_ids for v in views])))),
             "mean_visible_keypoints": float(np.mean([len(v.keypoint_ids) for v in views])),
             "mean_angle_deg": float(np.mean([v.angle_deg for v in views])),
             "mean_translation": float(np.mean([v.translation for v in views])),
             "mean_min_angle_to_mapping_deg": _novelty(views, frames)}
    return views, stats


def _novelty(views: list[NovelView], frames: list[Frame]) -> float:
    """Mean over novel views of the rotation angle to the closest mapping orientation."""
    Rm = np.stack([f.R for f in frames])
    return float(np.mean([rotation_error_deg(np.broadcast_to(v.R, Rm.shape), Rm).min() for v in views]))
