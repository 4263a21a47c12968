"""The training buffer: encoder features of augmented mapping views, sampled per view (ACE-style).

Running the frozen encoder once per augmented view and training the head on shuffled cells of
all views is what makes ACE mapping fast. Poses and intrinsics are stored once per view and
referenced by `view_index`, since every cell of a view shares them.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
import torch
from tqdm import tqdm

from usvc.buffer.augment import AugmentedView, augment
from usvc.buffer.buffer_file import TrainingBuffer
from usvc.buffer.keypoint_obs import sample_features, view_observations
from usvc.buffer.options import BufferOptions
from usvc.core.errors import UsvcError
from usvc.core.options import check
from usvc.core.ordered_pool import library_threads, ordered_map
from usvc.core.precision import autocast, resolve_precision
from usvc.core.scene import Frame
from usvc.keypoints.keypoints_file import SceneKeypoints
from usvc.model.encoder import Encoder, cell_centers, feature_size
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


@dataclass
class _PlannedView:
    """One augmented view and everything drawn for it before its encoder pass."""

    frame: int  # index into the frames
    view: AugmentedView
    cells: tuple[int, int]  # the encoder's output grid (h, w) for this view
    sel: np.ndarray  # the sampled cells, flat indices (with repeats)
    keypoints: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # ids, pixels, from depth


def _planned_views(frames: list[Frame], opts: BufferOptions, short_side: int, seed: int,
                   keypoints: SceneKeypoints | None,
                   depths: Sequence[np.ndarray | None] | None) -> Iterator[_PlannedView]:
    """The views in buffer order, with their random draws: what fill_buffer's loop drew, in its
    order, except the encoder pass (a view's cell grid follows from its size)."""
    rng = np.random.default_rng(seed)
    kp_rng = np.random.default_rng([seed, 1])
    count = 0
    while count < opts.size:
        for i in rng.permutation(len(frames)):
            frame = frames[i]
            view = augment(_load_gray(frame), frame.camera.K, frame.R, frame.t, rng,
                           scale_range=(opts.scale_min, opts.scale_max), short_side=short_side,
                           max_rotation_deg=opts.max_rotation_deg, brightness=(opts.brightness_min, opts.brightness_max),
                           contrast=(opts.contrast_min, opts.contrast_max))
            h, w = feature_size(*view.image.shape[:2])
            valid = _valid_cells(view.mask, h, w)
            if len(valid) == 0:
                continue
            take = min(opts.samples_per_image, opts.size - count)
            sel = rng.choice(valid, size=take, replace=True)
            kp = None
            if keypoints is not None:
                ids, uv, from_depth = view_observations(
                    keypoints, frame.name, view, frame.R, frame.t, frame.camera.K,
                    None if depths is None else depths[i], opts.depth_visibility_tol)
                if 0 < opts.keypoint_obs_per_view < len(ids):
                    pick = np.sort(kp_rng.choice(len(ids), opts.keypoint_obs_per_view, replace=False))
                    ids, uv, from_depth = ids[pick], uv[pick], from_depth[pick]
                kp = (ids, uv, from_depth)
            yield _PlannedView(int(i), view, (h, w), sel, kp)
            count += take
            if count >= opts.size:
                return


def encoder_workers(device: str) -> int:
    """Views encoded at once: on a CPU one per torch thread, each pass on one thread (a batch-1
    convolution keeps two cores busier as two passes than as one: 52 against 76 ms a view at the
    small encoder's size on a 2-core CPU); on a GPU one."""
    return max(1, torch.get_num_threads()) if str(device).startswith("cpu") else 1


def _encode(encoder: Encoder, plan: _PlannedView, precision: str, device: str,
            ) -> tuple[np.ndarray, np.ndarray | None]:
    """One view's sampled cells (take, C) and its keypoints' features, fp16 on the host."""
    with torch.inference_mode(), autocast(precision, device):
        out = encoder(normalise(plan.view.image).to(device))[0].float()  # (C, h, w)
    c, h, w = out.shape
    if (h, w) != plan.cells:
        raise UsvcError(f"the encoder gave a {h}x{w} grid for a {plan.view.image.shape[0]}x"
                        f"{plan.view.image.shape[1]} view, expected {plan.cells[0]}x{plan.cells[1]}")
    flat = out.reshape(c, -1)[:, torch.from_numpy(plan.sel).to(device)]
    kp = None if plan.keypoints is None else sample_features(out, plan.keypoints[1]).to(torch.float16).cpu().numpy()
    return flat.T.to(torch.float16).cpu().numpy(), kp


def _encoded(encoder: Encoder, plans: Iterator[_PlannedView], precision: str, device: str,
             workers: int) -> Iterator[tuple[_PlannedView, np.ndarray, np.ndarray | None]]:
    """(view, cell features, keypoint features) in the plans' order; with several workers, that
    many views are encoded side by side, each on one torch thread (the same bits for any count)."""
    if workers <= 1:
        for plan in plans:
            yield (plan, *_encode(encoder, plan, precision, device))
        return
    with library_threads(torch.get_num_threads, torch.set_num_threads, 1):
        for plan, (cells, kp) in ordered_map(lambda p: _encode(encoder, p, precision, device), plans, workers,
                                             name="usvc-encode"):
            yield plan, cells, kp


@torch.inference_mode()
def fill_buffer(frames: list[Frame], encoder: Encoder, opts: BufferOptions, short_side: int, seed: int = 0,
                device: str = "cpu",
                keypoints: SceneKeypoints | None = None,
                depths: Sequence[np.ndarray | None] | None = None,
                mapping_images: int | None = None) -> TrainingBuffer:
    """Repeated passes over the mapping images with fresh augmentation until the buffer holds
    `opts.cells_for(mapping_images)` cells (`mapping_images`: the photos the budget counts, by
    default every frame; rendered views add views, not budget).

    With `keypoints`, every view also stores the tuples of the keypoints it sees (`depths`, one per
    frame or None, let points off their tracks count where depth confirms them). Their subsampling
    draws from its own generator, so the pixel samples are the same with or without keypoints.
    On a CPU, views are encoded side by side (encoder_workers), each on one thread: the buffer is
    the same for any thread count.
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
    kp_parts: dict[str, list] = {"id": [], "features": [], "pixels": [], "view": [], "from_depth": []}
    encoder = encoder.to(device).eval()
    feats, pixels, view_idx = [], [], []
    views: dict[str, list] = {"image": [], "R": [], "t": [], "K": []}
    count = 0
    n_views = math.ceil(opts.size / opts.samples_per_image)
    plans = _planned_views(frames, opts, short_side, seed, keypoints, depths)
    with tqdm(total=opts.size, desc="buffer", unit="cell") as bar:
        for plan, cell_features, kp_features in _encoded(encoder, plans, precision, device, encoder_workers(device)):
            take = len(plan.sel)
            h, w = plan.cells
            feats.append(cell_features)
            pixels.append(cell_centers(h, w, "colmap").reshape(2, -1)[:, plan.sel].T.numpy().astype(np.float32))
            view_idx.append(np.full(take, len(views["image"]), dtype=np.int32))
            if plan.keypoints is not None:
                ids, uv, from_depth = plan.keypoints
                kp_parts["id"].append(ids.astype(np.int32))
                kp_parts["features"].append(kp_features)
                kp_parts["pixels"].append(uv)
                kp_parts["view"].append(np.full(len(ids), len(views["image"]), dtype=np.int32))
                kp_parts["from_depth"].append(from_depth)
            views["image"].append(plan.frame)
            views["R"].append(plan.view.R_world_to_cam)
            views["t"].append(plan.view.t_world_to_cam)
            views["K"].append(plan.view.K)
            count += take
            bar.update(take)
    log.info("buffer: %d cells from %d augmented views (planned about %d), encoder at %s", count,
             len(views["image"]), n_views, precision)
    buf = TrainingBuffer(
        features=np.concatenate(feats), pixels=np.concatenate(pixels), view_index=np.concatenate(view_idx),
        view_image=np.asarray(views["image"], dtype=np.int32),
        view_R_world_to_cam=np.stack(views["R"]).astype(np.float32),
        view_t_world_to_cam=np.stack(views["t"]).astype(np.float32), view_K=np.stack(views["K"]).astype(np.float32),
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
