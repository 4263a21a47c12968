"""The train step: fit the scene's regression head on the buffer (ACE's reprojection loss plus the
multi-view bundle loss) -> map.pt, the encoder and head with the keypoints the query-time
refinement projects."""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from usvc.buffer.buffer_file import check_buffer_encoder, read_buffer, read_buffer_attrs
from usvc.core.artifact_names import MAP_PT
from usvc.core.errors import UsvcError
from usvc.model.head import Regressor
from usvc.model.map_file import save_map
from usvc.model.options import ModelOptions
from usvc.sfm.tracks_file import read_median_depth, read_tracks
from usvc.train.focal_calibration import map_focal_error
from usvc.train.options import TrainOptions
from usvc.train.trainer import train_head
from usvc.weights import load_configured_encoder

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    buffer: Path  # the training buffer (buffer/buffer.h5)
    holdout: Path  # cells of withheld mapping images (buffer/holdout.h5), when the buffer step wrote them
    tracks: Path  # the SfM model (sfm/tracks.h5): median depth and the cameras' focal lengths


def focal_range(K: np.ndarray) -> list[float]:
    """[low, high] of the mapping cameras' focal lengths over their long side (2 x the principal
    point's larger coordinate: prepared images are centred), from the SfM intrinsics (N,3,3): the
    relocalizer refuses a photo whose estimated focal length is far outside it."""
    K = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
    ratios = np.sqrt(K[:, 0, 0] * K[:, 1, 1]) / (2.0 * np.maximum(K[:, 0, 2], K[:, 1, 2]))
    ratios = ratios[np.isfinite(ratios) & (ratios > 0)]
    if ratios.size == 0:
        raise UsvcError("train: the SfM cameras have no valid intrinsics to record in the map")
    return [round(float(ratios.min()), 4), round(float(ratios.max()), 4)]


def run(inputs: Inputs, out: Path, options: TrainOptions, model: ModelOptions, *, seed: int, scene: str,
        method: str, device: str = "cpu") -> dict:
    """Train the head (on `device`) and write the map of `scene` into `out`; returns the training figures."""
    # Every input is read and checked before the long step: the encoder the map will carry must
    # be the one whose features fill the buffer.
    encoder, weights = load_configured_encoder(model.encoder_width, model.encoder_weights, model.encoder)
    attrs = read_buffer_attrs(inputs.buffer)
    check_buffer_encoder(inputs.buffer, attrs, encoder, weights)
    buf = read_buffer(inputs.buffer)
    heldout = read_buffer(inputs.holdout) if inputs.holdout.is_file() else None
    tracks = read_tracks(inputs.tracks)
    median_depth = read_median_depth(inputs.tracks)
    head, summary = train_head(buf, median_depth, options, head_width=model.head_width,
                               head_blocks=model.head_blocks, seed=seed, heldout=heldout, device=device)
    focal_error = map_focal_error(head, buf, summary["precision"], device, seed)
    metadata = {"scene": scene, "short_side": int(attrs["short_side"]), "median_depth": median_depth,
                "encoder_file": weights.name, "model": model.name, "method": method,
                "train": asdict(options), "precision": summary["precision"], "seed": seed,
                "iterations": summary["iterations"], "final_loss": summary["final_loss"],  # no timings: same bytes
                "focal_range": focal_range(tracks.K), "focal_error": focal_error["p90"]}
    # The kept keypoints travel with the map: query-time refinement projects them (paper 3.2.2).
    save_map(out / MAP_PT, Regressor(encoder, head), metadata,
             keypoints_xyz=buf.keypoint_xyz if buf.has_keypoints else None)
    stats = {**summary, "map_megabytes": (out / MAP_PT).stat().st_size / 2**20, "focal_error": focal_error}
    log.info("train %s: map %.2f MB; its coordinates imply its views' focal lengths within %.1f %% (90th percentile "
             "of %d views)", scene, stats["map_megabytes"], 100 * (np.exp(focal_error["p90"]) - 1), focal_error["views"])
    return stats
