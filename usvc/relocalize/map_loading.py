"""What a `Relocalizer` loads of its map: the network (the map's head on the encoder it was trained
with) on its device at the precision it runs, what the map records of its own views, and its
landmarks, for refinement by features."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from usvc.core.errors import UsvcError
from usvc.core.precision import resolve_precision
from usvc.landmarks.landmark_table import Landmarks
from usvc.landmarks.landmarks_file import landmarks_beside, landmarks_disagree, read_landmarks
from usvc.model.head import Regressor
from usvc.model.map_file import load_map, map_keypoints
from usvc.weights import WEIGHTS_DIR, load_configured_encoder

log = logging.getLogger(__name__)


@dataclass
class MapNetwork:
    """The map's network, ready to run: its head on the encoder it was trained with, on `device`."""

    regressor: Regressor
    metadata: dict[str, Any]  # the map's metadata (short_side, scene, focal_range, ...)
    precision: str  # the precision its products run at: fp32 | bf16
    memory_format: torch.memory_format  # the layout its input is given in
    encoder_weights: str | Path | None  # the encoder's weight file (None: the shipped one of its width)


def load_network(map_path: str | Path, header: dict[str, Any], encoder_weights: str | Path | None,
                 precision: str, device: str) -> MapNetwork:
    """The map's network on `device` at `precision` (`auto` resolved); its encoder `encoder_weights`,
    else the shipped file the map was trained with where there is one (e.g. model=small_real)."""
    width = float(header["encoder"].get("width", 1.0))
    kind = str(header["encoder"].get("kind", "ace"))
    if encoder_weights is None:  # the shipped file the map was trained with (e.g. model=small_real)
        recorded = header["metadata"].get("encoder_file")
        if isinstance(recorded, str) and kind == "ace" and (WEIGHTS_DIR / Path(recorded).name).is_file():
            encoder_weights = WEIGHTS_DIR / Path(recorded).name
    encoder, _ = load_configured_encoder(width, encoder_weights, kind)
    regressor, metadata = load_map(map_path, encoder, header)
    regressor.to(device).eval()
    # The map's weights are stored at fp16 whatever precision it was trained at, so any map runs
    # at either precision on any machine.
    resolved = resolve_precision(precision, device)
    # bf16 on a CPU: oneDNN's convolutions run faster in the channels-last layout (the network alone
    # 18-20 against 20-24 ms on mini's map, 20-22 against 23-30 on bird's; docs/speed.md); fp32 did not gain
    memory_format = torch.channels_last if resolved == "bf16" and torch.device(device).type == "cpu" \
        else torch.contiguous_format
    regressor.to(memory_format=memory_format)
    return MapNetwork(regressor, metadata, resolved, memory_format, encoder_weights)


@dataclass(frozen=True)
class MapViews:
    """What the map records of its own views, for the relocalizer's checks."""

    focal_range: tuple[float, float] | None  # its cameras' focal lengths over the long side (None: not recorded)
    judges_focal: bool  # whether it tells its own views' focal lengths within focal_tolerance
    keypoints_xyz: np.ndarray | None  # its 3D keypoints (None: it has none)
    median_depth: float  # its views' median scene depth (1.0 where not recorded)


def map_views(map_path: str | Path, header: dict[str, Any], metadata: dict[str, Any],
              focal_tolerance: float) -> MapViews:
    """`MapViews` of the map at `map_path` (`header`: its `read_map_header`, `metadata` its metadata)."""
    spread = metadata.get("focal_range")  # checked on load; maps before it have none
    focal_range = (float(spread[0]), float(spread[1])) if spread is not None else None
    # The map judges a given focal length only if it tells its own views' within the tolerance
    # (usvc.train.focal_calibration; maps before that measure judge, as they did)
    error = metadata.get("focal_error")
    judges = bool(error is None or float(error) <= np.log1p(focal_tolerance))
    if not judges and focal_tolerance > 0:
        log.info("map %s implies its own views' focal lengths only within %.0f %% (90th percentile), over "
                 "focal_tolerance %g: the map does not judge given focal lengths, the photos' features do",
                 map_path, 100 * (np.exp(float(error)) - 1), focal_tolerance)
    depth = metadata.get("median_depth")
    median_depth = float(depth) if isinstance(depth, (int, float)) and np.isfinite(depth) and depth > 0 else 1.0
    return MapViews(focal_range, judges, map_keypoints(header), median_depth)


def find_landmarks(landmarks: str | Path | None, map_path: Path, metadata: dict[str, Any],
                   keypoints_xyz: np.ndarray | None, prior: bool) -> tuple[Landmarks, Path] | None:
    """The map's landmarks, read and checked against the map, and their file: `landmarks`, else the
    file beside the map (`landmarks_beside`); None, with a warning, where the map has none (it then
    localizes without refinement). prior=none (`prior` False) needs them, with their observations."""
    if landmarks is not None and not isinstance(landmarks, (str, Path)):
        raise UsvcError(f"landmarks must be the path of a landmarks.h5, got {type(landmarks).__name__}")
    path = Path(landmarks) if landmarks is not None else landmarks_beside(map_path)
    if path is None:
        if not prior:
            raise UsvcError(f"relocalize.prior=none needs the map's landmarks, and map {map_path} has none "
                            "beside it (landmarks.h5; --landmarks names it)")
        log.warning("map %s has no landmarks beside it (landmarks.h5): refinement by features is off", map_path)
        return None
    found = read_landmarks(path)
    why = landmarks_disagree(found, metadata.get("scene"), keypoints_xyz)
    if why:
        raise UsvcError(f"{path} are not the landmarks of map {map_path}: {why}")
    if not prior and found.observations is None:
        raise UsvcError(f"relocalize.prior=none needs landmarks with their observations; {path} has none "
                        "(format version 1): rebuild them with the landmarks stage")
    return found, path
