"""buffer.h5 (and holdout.h5), the buffer stage's artifact: the training buffer's record, its one
writer and its readers. `usvc.buffer.build` fills a TrainingBuffer; training reads it back.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import h5py
import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

BUFFER_FORMAT, BUFFER_VERSION = "usvc-buffer", 1
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
    view_R_world_to_cam: np.ndarray  # (V, 3, 3) world-to-camera of the augmented view
    view_t_world_to_cam: np.ndarray  # (V, 3)
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


def write_buffer(path: Path, buf: TrainingBuffer, **attrs: int | float | str) -> None:
    """Write the buffer; `attrs` (e.g. the working short side) travel with it to the map. Every
    dataset carries units/description/frame attributes (BUFFER_SCHEMA)."""
    with write_h5(path, BUFFER_SCHEMA, BUFFER_FORMAT, BUFFER_VERSION) as h5:
        h5.attrs.update(attrs)
        h5.create_dataset("features", data=buf.features, chunks=(min(len(buf.features), 4096), buf.features.shape[1]))
        h5["pixels"], h5["view_index"] = buf.pixels, buf.view_index
        views = h5.create_group("views")
        views["image"], views["R_world_to_cam"], views["t_world_to_cam"], views["K"] = (
            buf.view_image, buf.view_R_world_to_cam, buf.view_t_world_to_cam, buf.view_K)
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
            view_image=h5["views/image"][()], view_R_world_to_cam=h5["views/R_world_to_cam"][()],
            view_t_world_to_cam=h5["views/t_world_to_cam"][()], view_K=h5["views/K"][()],
            image_names=[n.decode() if isinstance(n, bytes) else n for n in h5["image_names"][()]],
        )
        if "keypoints" in h5:
            kp = h5["keypoints"]
            buf.kp_id, buf.kp_features, buf.kp_pixels = kp["id"][()], kp["features"][()], kp["pixels"][()]
            buf.kp_view, buf.kp_from_depth, buf.keypoint_xyz = kp["view"][()], kp["from_depth"][()], kp["xyz"][()]
    return buf
