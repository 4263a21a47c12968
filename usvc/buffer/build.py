"""The training buffer: encoder features of augmented mapping views, sampled per view (ACE-style).

Running the frozen encoder once per augmented view and training the head on shuffled cells of
all views is what makes ACE mapping fast. Poses and intrinsics are stored once per view and
referenced by `view_index`, since every cell of a view shares them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch
from tqdm import tqdm

from usvc.buffer.augment import augment
from usvc.buffer.keypoint_obs import sample_features, view_observations
from usvc.buffer.options import BufferOptions
from usvc.core.errors import UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5
from usvc.core.options import check
from usvc.core.precision import autocast, resolve_precision
from usvc.core.scene import Frame
from usvc.keypoints.keypoints_file import SceneKeypoints
from usvc.model.encoder import Encoder, cell_centers
from usvc.model.preprocess import luma01, normalise

log = logging.getLogger(__name__)


BUFFER_FORMAT, BUFFER_VERSION = "usvc-buffer", 1
HELDOUT_FILE = "holdout.h5"  # beside buffer.h5 when buffer.holdout_every > 0: cells of the withheld images
_PIXELS = "pixel centres at integer+0.5 (COLMAP), x right, y down"
# Every dataset of buffer.h5 with its attributes; docs/artifacts.md lists the same. File attributes:
# what the stage passes to write_buffer (short_side, encoder_file, encoder_fingerprint), format, version.
BUFFER_SCHEMA: dict[str, Field] = {
    "features": Field("1", "frozen-encoder feature of one sampled 8x8 cell of an augmented view (fp16)"),
    "pixels": Field("px", f"pixel the cell describes in its augmented view, (8j + 4.5, 8i + 4.5) for cell (i, j); "
                          f"{_PIXELS}", "image"),
    "view_index": Field("1", "augmented view of the cell: row of views/*"),
    "views/image": Field("1", "source image of the augmented view: row of image_names"),
    "views/R_world_to_cam": Field("1", "world-to-camera rotation of the augmented view (source pose with the "
                                       "in-plane roll applied): x_cam = R x_world + t, OpenCV camera axes",
                                  "world->camera"),
    "views/t_world_to_cam": Field("scene units", "world-to-camera translation of the augmented view: "
                                                 "x_cam = R x_world + t", "camera"),
    "views/K": Field("px", f"intrinsic matrix of the augmented (rescaled) view; {_PIXELS}", "camera->image"),
    "image_names": Field("1", "source images: the mapping images used (prepared names), then rendered views "
                              "('render/NNNN.png') when the method uses them"),
    "keypoints/features": Field("1", "encoder feature bilinearly sampled at the keypoint observation (fp16)"),
    "keypoints/id": Field("1", "keypoint index: row of keypoints/xyz (= row of keypoints.h5 keypoints/*), "
                               "not a COLMAP id; rows are sorted by it"),
    "keypoints/pixels": Field("px", f"position of the keypoint observation in the augmented view; {_PIXELS}",
                              "image"),
    "keypoints/view": Field("1", "augmented view of the observation: row of views/*"),
    "keypoints/from_depth": Field("1", "true: a projection of the keypoint that the depth map confirms visible; "
                                       "false: an SfM track observation"),
    "keypoints/xyz": Field("scene units", "3D position of every kept keypoint (keypoints.h5 keypoints/xyz)",
                           "world"),
}


@dataclass
class TrainingBuffer:
    features: np.ndarray  # (M, C) float16
    pixels: np.ndarray  # (M, 2) float32, COLMAP coordinates in the augmented view
    view_index: np.ndarray  # (M,) int32 into the per-view arrays
    view_image: np.ndarray  # (V,) int32 index of the source mapping image
    view_R: np.ndarray  # (V, 3, 3) world-to-camera of the augmented view
    view_t: np.ndarray  # (V, 3)
    view_K: np.ndarray  # (V, 3, 3)
    image_names: list[str]
    # Keypoint tuples (k, d_k, view -> (R_i, t_i, K_i), u_obs), sorted by keypoint id so that the
    # observations of one keypoint (a bundle-loss group) are contiguous.
    kp_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))  # (P,)
    kp_features: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float16))  # (P, C)
    kp_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # (P, 2)
    kp_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))  # (P,)
    kp_from_depth: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (P,) not from the SfM track
    keypoint_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # (K, 3)

    @property
    def has_keypoints(self) -> bool:
        return len(self.kp_id) > 0


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


def write_buffer(path: Path, buf: TrainingBuffer, **attrs: int | float | str) -> None:
    """Write the buffer; `attrs` (e.g. the working short side) travel with it to the map. Every
    dataset carries units/description/frame attributes (BUFFER_SCHEMA)."""
    with write_h5(path, BUFFER_SCHEMA, BUFFER_FORMAT, BUFFER_VERSION) as h5:
        h5.attrs.update(attrs)
        h5.create_dataset("features", data=buf.features, chunks=(min(len(buf.features), 4096), buf.features.shape[1]))
        h5["pixels"], h5["view_index"] = buf.pixels, buf.view_index
        views = h5.create_group("views")
        views["image"], views["R_world_to_cam"], views["t_world_to_cam"], views["K"] = (
            buf.view_image, buf.view_R, buf.view_t, buf.view_K)
        h5.create_dataset("image_names", data=np.array(buf.image_names, dtype=object), dtype=h5py.string_dtype())
        if buf.has_keypoints:
            kp = h5.create_group("keypoints")
            kp.create_dataset("features", data=buf.kp_features,
                              chunks=(min(len(buf.kp_features), 4096), buf.kp_features.shape[1]))
            kp["id"], kp["pixels"], kp["view"], kp["from_depth"] = buf.kp_id, buf.kp_pixels, buf.kp_view, buf.kp_from_depth
            kp["xyz"] = buf.keypoint_xyz


def check_buffer_encoder(path: Path, attrs: dict, encoder: torch.nn.Module, weights: Path) -> None:
    """The head must be trained on features of the encoder the map will carry: refuse a buffer
    whose recorded encoder fingerprint differs from the configured encoder's."""
    from usvc.model.encoder import encoder_fingerprint

    recorded = attrs.get("encoder_fingerprint")
    if recorded is None:
        log.warning("%s records no encoder fingerprint (an older buffer): cannot check it matches %s",
                    path, weights.name)
        return
    if recorded != encoder_fingerprint(encoder):
        raise UsvcError(f"{path} holds features of encoder {attrs.get('encoder_file', '?')}, but the configured "
                        f"encoder is {weights.name} (another model.* setting?): rerun the buffer stage with "
                        "the same model config, or train with the buffer's")


def read_buffer_attrs(path: Path) -> dict:
    """The attributes the buffer stage records (working short side, encoder file and fingerprint)."""
    with read_h5(path, "training buffer") as h5:
        if "short_side" not in h5.attrs:
            raise KeyError("no short_side attribute")
        return {k: (v.item() if hasattr(v, "item") else v) for k, v in h5.attrs.items()}


def read_buffer_image_names(path: Path) -> list[str]:
    """The names of the images a buffer was built from (without loading its features)."""
    with read_h5(path, "training buffer") as h5:
        return [n.decode() if isinstance(n, bytes) else str(n) for n in h5["image_names"][()]]


def read_buffer(path: Path) -> TrainingBuffer:
    with read_h5(path, "training buffer") as h5:  # names a missing or damaged file
        buf = TrainingBuffer(
            features=h5["features"][()], pixels=h5["pixels"][()], view_index=h5["view_index"][()],
            view_image=h5["views/image"][()], view_R=h5["views/R_world_to_cam"][()],
            view_t=h5["views/t_world_to_cam"][()], view_K=h5["views/K"][()],
            image_names=[n.decode() if isinstance(n, bytes) else n for n in h5["image_names"][()]],
        )
        if "keypoints" in h5:
            kp = h5["keypoints"]
            buf.kp_id, buf.kp_features, buf.kp_pixels = kp["id"][()], kp["features"][()], kp["pixels"][()]
            buf.kp_view, buf.kp_from_depth, buf.keypoint_xyz = kp["view"][()], kp["from_depth"][()], kp["xyz"][()]
    return buf
