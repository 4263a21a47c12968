"""The training buffer: encoder features of augmented mapping views, sampled per view (ACE-style).

Running the frozen encoder once per augmented view and training the head on shuffled cells of
all views is what makes ACE mapping fast. Poses and intrinsics are stored once per view and
referenced by `view_index`, since every cell of a view shares them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import cv2
import numpy as np
import torch
from tqdm import tqdm

from usvc.buffer.augment import augment
from usvc.buffer.buffer_file import TrainingBuffer
from usvc.buffer.keypoint_obs import sample_features, view_observations
from usvc.buffer.options import BufferOptions
from usvc.core.errors import UsvcError
from usvc.core.options import check
from usvc.core.precision import autocast, resolve_precision
from usvc.core.scene import Frame
from usvc.keypoints.keypoints_file import SceneKeypoints
from usvc.model.encoder import Encoder, cell_centers
from usvc.model.preprocess import luma01, normalise

log = logging.getLogger(__name__)


def _check_pinhole(frame: Frame) -> None:
    if frame.camera.has_distortion:
        raise UsvcError(f"{frame.name}: the training buffer needs undistorted (pinhole) images, "
                        f"got {frame.camera.model} with distortion")
    if not frame.has_pose:
        raise UsvcError(f"{frame.name}: the training buffer needs a posed mapping image")


def _load_gray(frame: Frame) -> np.ndarray:
    image = cv2.imread(str(frame.image_path), cv2.IMREAD_COLOR)
    if image is None:
        raise UsvcError(f"cannot read image {frame.image_path}")
    return luma01(image, rgb=False)


def _valid_cells(mask: np.ndarray, h_cells: int, w_cells: int) -> np.ndarray:
    """Flat indices of cells whose centre pixel lies inside the valid (non-padded) image area."""
    rows, cols = np.arange(h_cells) * 8 + 4, np.arange(w_cells) * 8 + 4
    r_ok, c_ok = rows < mask.shape[0], cols < mask.shape[1]
    inside = np.zeros((h_cells, w_cells), dtype=bool)
    inside[np.ix_(r_ok, c_ok)] = mask[np.ix_(rows[r_ok], cols[c_ok])]
    return np.flatnonzero(inside)


def working_short_side(image_short_side: int, short_side: int = 0, max_short_side: int = 0) -> int:
    """The short side a map is trained (and queried) at: ``short_side`` when set, else the images'
    own, scaled down to ``max_short_side`` when that is set and smaller. Never upscales by default."""
    if short_side > 0:
        return int(short_side)
    if max_short_side > 0:
        return int(min(image_short_side, max_short_side))
    return int(image_short_side)


def holdout_split(mapping: list[Frame], every: int) -> tuple[list[Frame], list[Frame]]:
    """(training, held out): every ``every``-th mapping image (from the ``every // 2``-th on, so the split
    does not line up with an every-n-th query split) is withheld; ``every`` 0 withholds none."""
    if every < 0 or every == 1:
        raise UsvcError(f"buffer.holdout_every must be 0 (none) or >= 2, got {every}")
    if every == 0:
        return list(mapping), []
    held = [i % every == every // 2 for i in range(len(mapping))]
    train = [f for f, h in zip(mapping, held) if not h]
    if not train:
        raise UsvcError(f"buffer.holdout_every={every} leaves no mapping image to train on")
    return train, [f for f, h in zip(mapping, held) if h]


@torch.inference_mode()
def fill_buffer(frames: list[Frame], encoder: Encoder, opts: BufferOptions, short_side: int, seed: int = 0,
                device: str = "cpu",
                keypoints: SceneKeypoints | None = None,
                depths: list[np.ndarray | None] | None = None,
                mapping_images: int | None = None) -> TrainingBuffer:
    """Repeated passes over the mapping images with fresh augmentation until the buffer holds
    `opts.cells_for(mapping_images)` cells (`mapping_images`: the photos the budget counts, by
    default every frame; rendered views add views, not budget).

    With `keypoints`, every view also stores the tuples of the keypoints it sees (`depths`, one per
    frame or None, let points off their tracks count where depth confirms them). Their subsampling
    draws from its own generator, so the pixel samples are the same with or without keypoints.
    """
    if not frames:
        raise UsvcError("the training buffer needs at least one mapping image")
    for f in frames:
        _check_pinhole(f)
    if depths is not None and len(depths) != len(frames):
        raise UsvcError(f"got {len(depths)} depth maps for {len(frames)} mapping images")
    check(opts, "buffer")
    opts = replace(opts, size=opts.cells_for(len(frames) if mapping_images is None else mapping_images))
    precision = resolve_precision(opts.precision, device)
    rng = np.random.default_rng(seed)
    kp_rng = np.random.default_rng([seed, 1])
    kp_parts: dict[str, list] = {"id": [], "features": [], "pixels": [], "view": [], "from_depth": []}
    encoder = encoder.to(device).eval()
    feats, pixels, view_idx = [], [], []
    views: dict[str, list] = {"image": [], "R": [], "t": [], "K": []}
    count = 0
    n_views = math.ceil(opts.size / opts.samples_per_image)
    with tqdm(total=opts.size, desc="buffer", unit="cell") as bar:
        while count < opts.size:
            for i in rng.permutation(len(frames)):
                frame = frames[i]
                view = augment(_load_gray(frame), frame.camera.K, frame.R, frame.t, rng,
                               scale_range=(opts.scale_min, opts.scale_max), short_side=short_side,
                               max_rotation_deg=opts.max_rotation_deg, brightness=(opts.brightness_min, opts.brightness_max),
                               contrast=(opts.contrast_min, opts.contrast_max))
                with autocast(precision, device):
                    out = encoder(normalise(view.image).to(device))[0].float()  # (C, h, w)
                c, h, w = out.shape
                valid = _valid_cells(view.mask, h, w)
                if len(valid) == 0:
                    continue
                take = min(opts.samples_per_image, opts.size - count)
                sel = rng.choice(valid, size=take, replace=True)
                flat = out.reshape(c, -1)[:, torch.from_numpy(sel).to(device)]
                feats.append(flat.T.to(torch.float16).cpu().numpy())
                centres = cell_centers(h, w, "colmap").reshape(2, -1)[:, sel].T
                pixels.append(centres.numpy().astype(np.float32))
                view_idx.append(np.full(take, len(views["image"]), dtype=np.int32))
                if keypoints is not None:
                    ids, uv, from_depth = view_observations(
                        keypoints, frame.name, view, frame.R, frame.t, frame.camera.K,
                        None if depths is None else depths[i], opts.depth_visibility_tol)
                    if 0 < opts.keypoint_obs_per_view < len(ids):
                        pick = np.sort(kp_rng.choice(len(ids), opts.keypoint_obs_per_view, replace=False))
                        ids, uv, from_depth = ids[pick], uv[pick], from_depth[pick]
                    kp_parts["id"].append(ids.astype(np.int32))
                    kp_parts["features"].append(sample_features(out, uv).to(torch.float16).cpu().numpy())
                    kp_parts["pixels"].append(uv)
                    kp_parts["view"].append(np.full(len(ids), len(views["image"]), dtype=np.int32))
                    kp_parts["from_depth"].append(from_depth)
                views["image"].append(i)
                views["R"].append(view.R_w2c)
                views["t"].append(view.t_w2c)
                views["K"].append(view.K)
                count += take
                bar.update(take)
                if count >= opts.size:
                    break
    log.info("buffer: %d cells from %d augmented views (planned about %d), encoder at %s", count,
             len(views["image"]), n_views, precision)
    buf = TrainingBuffer(
        features=np.concatenate(feats), pixels=np.concatenate(pixels), view_index=np.concatenate(view_idx),
        view_image=np.asarray(views["image"], dtype=np.int32), view_R=np.stack(views["R"]).astype(np.float32),
        view_t=np.stack(views["t"]).astype(np.float32), view_K=np.stack(views["K"]).astype(np.float32),
        image_names=[f.name for f in frames],
    )
    if keypoints is not None:
        ids = np.concatenate(kp_parts["id"])
        if len(ids) == 0:
            raise UsvcError("no kept keypoint is observed in any buffer view: check the keypoints stage's "
                            "output against the prepared mapping images")
        order = np.argsort(ids, kind="stable")
        buf.kp_id, buf.kp_pixels = ids[order], np.concatenate(kp_parts["pixels"])[order]
        buf.kp_features = np.concatenate(kp_parts["features"])[order]
        buf.kp_view, buf.kp_from_depth = np.concatenate(kp_parts["view"])[order], np.concatenate(kp_parts["from_depth"])[order]
        buf.keypoint_xyz = keypoints.xyz.astype(np.float32)
        log.info("buffer: %d keypoint observations of %d keypoints (%.1f %% from depth visibility)", len(ids),
                 len(np.unique(ids)), 100 * buf.kp_from_depth.mean())
    return buf


def fill_heldout(frames: list[Frame], encoder: Encoder, opts: BufferOptions, short_side: int, seed: int = 0,
                 device: str = "cpu") -> TrainingBuffer:
    """Cells of the held-out mapping images (`holdout_split`), one view each at the working size with
    no augmentation and no keypoints: what training measures its held-out fit on."""
    plain = replace(opts, size=len(frames) * opts.samples_per_image, scale_min=1.0, scale_max=1.0,
                    max_rotation_deg=0.0, brightness_min=1.0, brightness_max=1.0, contrast_min=1.0, contrast_max=1.0)
    return fill_buffer(frames, encoder, plain, short_side, seed=seed, device=device)
