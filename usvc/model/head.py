"""Per-scene regression head (ACE-style), the encoder+head regressor, and the map file format.

A map file holds only the head (fp16 weights, fp32 scene centre), the identity of the encoder it
was trained on and free-form metadata, so it stays ~4 MB and cannot be paired with the wrong
encoder by accident.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from usvc.core.atomic import atomic_file
from usvc.model.encoder import (
    Encoder,
    _first_line,
    check_state_dict,
    encoder_fingerprint,
)
from usvc.model.errors import ModelError
from usvc.model.map_checks import (
    CHECKSUM_KEY,
    check_encoder_entry,
    check_finite_state,
    check_head_config,
    check_keypoints,
    check_metadata,
    check_plain,
    map_checksum,
    verify_checksum,
)
from usvc.model.safe_load import load_tensors

log = logging.getLogger(__name__)

MAX_SCALE = 4.0
MIN_SCALE = 0.01
# softplus_beta(0) = ln 2 / beta = 1 - 1 / MAX_SCALE, so o3 = 0 gives h = 1.
SOFTPLUS_BETA = math.log(2.0) / (1.0 - 1.0 / MAX_SCALE)

MAP_FORMAT = "usvc-map"
MAP_VERSION = 1


def homogeneous_scale(o3: torch.Tensor) -> torch.Tensor:
    """h = softplus_beta(o3) + 1/MAX_SCALE, at most 1/MIN_SCALE; h lies in (0.25, 100]."""
    h = F.softplus(o3, beta=SOFTPLUS_BETA) + 1.0 / MAX_SCALE
    return h.clamp(max=1.0 / MIN_SCALE)


def _conv1x1(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, bias=True)


def _linear(conv: nn.Module, x: torch.Tensor) -> torch.Tensor:
    return F.linear(x, conv.weight[:, :, 0, 0], conv.bias)


class _ResBlock(nn.Module):
    """Three 1x1 conv+ReLU layers added to the input (via a 1x1 projection if channels differ)."""

    def __init__(self, cin: int, width: int) -> None:
        super().__init__()
        self.conv1 = _conv1x1(cin, width)
        self.conv2 = _conv1x1(width, width)
        self.conv3 = _conv1x1(width, width)
        self.skip: nn.Module = nn.Identity() if cin == width else _conv1x1(cin, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.conv1(x))
        y = F.relu(self.conv2(y))
        y = F.relu(self.conv3(y))
        return self.skip(x) + y


class Head(nn.Module):
    """Features (B, C, H, W) -> world scene coordinates (B, 3, H, W), always fp32.

    Layout: residual block on the input features, `num_blocks` more residual blocks, two
    1x1 conv+ReLU layers, a final 1x1 conv to 4 (homogeneous) or 3 outputs, plus the scene centre.
    When `in_channels != width` (a narrow encoder) the first block's skip is a 1x1 projection,
    since the input cannot be added to a `width`-channel output otherwise.

    `scene_center` stays fp32 under `.half()`/`.to(dtype)`: in fp16 it would round at ~cm for
    scenes ~100 m from the origin, and it is added after the output is cast to fp32.
    """

    def __init__(
        self,
        in_channels: int = 512,
        width: int = 512,
        num_blocks: int = 1,
        homogeneous: bool = True,
    ) -> None:
        super().__init__()
        self.in_channels = int(in_channels)
        self.width = int(width)
        self.num_blocks = int(num_blocks)
        self.homogeneous = bool(homogeneous)
        self.blocks = nn.ModuleList(
            [_ResBlock(self.in_channels, self.width)]
            + [_ResBlock(self.width, self.width) for _ in range(self.num_blocks)]
        )
        self.fc1 = _conv1x1(self.width, self.width)
        self.fc2 = _conv1x1(self.width, self.width)
        self.out = _conv1x1(self.width, 4 if self.homogeneous else 3)
        self.register_buffer("scene_center", torch.zeros(1, 3, 1, 1, dtype=torch.float32))

    def config(self) -> dict[str, Any]:
        return {
            "in_channels": self.in_channels,
            "width": self.width,
            "num_blocks": self.num_blocks,
            "homogeneous": self.homogeneous,
        }

    def set_scene_center(self, center: Sequence[float] | torch.Tensor) -> None:
        """Set the offset added to every prediction (ACE: mean mapping camera position)."""
        c = torch.as_tensor(center, dtype=torch.float64).reshape(1, 3, 1, 1)
        self.scene_center.copy_(c.to(self.scene_center.device, torch.float32))

    def _apply(self, fn: Callable[[torch.Tensor], torch.Tensor], recurse: bool = True) -> Head:
        # Let device moves through but keep the centre's fp32 value (taken before any rounding).
        center = self._buffers["scene_center"]
        super()._apply(fn, recurse)
        moved = self._buffers["scene_center"]
        if center is not None and moved is not None:
            self._buffers["scene_center"] = center.to(device=moved.device, dtype=torch.float32)
        return self

    def forward_flat(self, features: torch.Tensor) -> torch.Tensor:
        """(N, C) features -> (N, 3) coordinates; the same weights as `forward`, run as matmuls.

        Training batches are cells gathered from many images, so there is no image grid, and
        on CPU a matmul is ~2x faster than a 1x1 convolution over an (N, C, 1, 1) tensor.
        """
        x = features.to(self.fc1.weight.dtype)
        for block in self.blocks:
            y = F.relu(_linear(block.conv1, x))
            y = F.relu(_linear(block.conv2, y))
            y = F.relu(_linear(block.conv3, y))
            x = (x if isinstance(block.skip, nn.Identity) else _linear(block.skip, x)) + y
        x = F.relu(_linear(self.fc1, x))
        x = F.relu(_linear(self.fc2, x))
        o = _linear(self.out, x).float()
        xyz = o[:, :3] / homogeneous_scale(o[:, 3:4]) if self.homogeneous else o
        return xyz + self.scene_center.reshape(1, 3)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = features.to(self.fc1.weight.dtype)
        for block in self.blocks:
            x = block(x)
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        o = self.out(x).float()
        if self.homogeneous:
            xyz = o[:, :3] / homogeneous_scale(o[:, 3:4])
        else:
            xyz = o
        return xyz + self.scene_center


class Regressor(nn.Module):
    """Normalised luma image (B, 1, H, W) -> scene coordinates (B, 3, ceil(H/8), ceil(W/8))."""

    def __init__(self, encoder: Encoder, head: Head) -> None:
        super().__init__()
        if head.in_channels != encoder.out_channels:
            raise ValueError(
                f"head expects {head.in_channels} input channels, "
                f"encoder gives {encoder.out_channels}"
            )
        self.encoder = encoder
        self.head = head

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(image))


def save_map(path: str | Path, regressor: Regressor, metadata: Mapping[str, Any],
             keypoints_xyz: np.ndarray | None = None) -> None:
    """Write the head (fp16 weights, fp32 centre), the encoder's identity and `metadata`.

    `keypoints_xyz` (K,3), when given, are the scene's kept 3D keypoints, stored as fp32 under
    "keypoints_xyz": query-time refinement projects them to pick reliable cells, so the map
    file alone is enough to relocalize with it.
    """
    metadata = dict(metadata)
    check_plain(metadata, "metadata")
    keypoints = None
    if keypoints_xyz is not None:
        keypoints = torch.as_tensor(np.asarray(keypoints_xyz, dtype=np.float32)).clone()
        check_keypoints(keypoints, Path(path))
    head = regressor.head
    state = {}
    for key, tensor in head.state_dict().items():
        dtype = torch.float32 if key == "scene_center" else torch.float16
        state[key] = tensor.detach().to("cpu", dtype).clone()
    payload = {
        "format": MAP_FORMAT,
        "version": MAP_VERSION,
        "head_config": head.config(),
        "head_state": state,
        "encoder": {
            "fingerprint": encoder_fingerprint(regressor.encoder),
            "width": regressor.encoder.width,
            "kind": getattr(regressor.encoder, "kind", "ace"),
            "out_channels": regressor.encoder.out_channels,
        },
        "metadata": metadata,
    }
    if keypoints is not None:
        payload["keypoints_xyz"] = keypoints
    where = f"{path}: cannot save map"
    check_head_config(payload["head_config"], where)
    check_metadata(metadata, where)
    check_finite_state(state, where)
    payload[CHECKSUM_KEY] = map_checksum(payload)
    with atomic_file(Path(path)) as tmp:
        torch.save(payload, tmp)
    log.info("saved map %s", path)


def read_map_header(path: str | Path) -> dict[str, Any]:
    """The validated map payload, without building the head (to learn which encoder it needs)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: map file does not exist")
    payload = load_tensors(path, "map")
    if not isinstance(payload, dict) or payload.get("format") != MAP_FORMAT:
        raise ModelError(f"{path}: not a usvc map file")
    if payload.get("version") != MAP_VERSION:
        raise ModelError(
            f"{path}: map format version {payload.get('version')!r}, this code reads {MAP_VERSION}"
        )
    for key in ("head_config", "head_state", "encoder", "metadata"):
        if not isinstance(payload.get(key), dict):
            raise ModelError(f"{path}: map file has no valid '{key}' entry")
    where = f"map file {path}"
    check_head_config(payload["head_config"], where)
    check_encoder_entry(payload["encoder"], where)
    check_metadata(payload["metadata"], where)
    for key, value in payload["head_state"].items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ModelError(f"map file {path} is corrupt: head weight {key} has non-finite values (NaN or inf)")
    if "keypoints_xyz" in payload:
        check_keypoints(payload["keypoints_xyz"], path)
    verify_checksum(payload, path)  # last: a field out of range is named as such, edited or not
    return payload


def map_keypoints(payload: Mapping[str, Any]) -> np.ndarray | None:
    """The map's 3D keypoints as float64 (K,3) from a `read_map_header` payload, or None if it has none."""
    value = payload.get("keypoints_xyz")
    if value is None:
        return None
    return value.detach().cpu().double().numpy().reshape(-1, 3)


def load_head(path: str | Path, encoder_fp: str,
              payload: dict[str, Any] | None = None) -> tuple[Head, dict[str, Any]]:
    """Read a map's head; refuse it unless its encoder's fingerprint is `encoder_fp`.
    `payload`: the file's `read_map_header` answer, when the caller has it (not read again)."""
    path = Path(path)
    payload = read_map_header(path) if payload is None else payload
    stored = payload["encoder"].get("fingerprint")
    if stored != encoder_fp:
        raise ModelError(
            f"{path}: map was trained with another encoder (fingerprint {str(stored)[:12]}, "
            f"this encoder {encoder_fp[:12]}, width {payload['encoder'].get('width')})"
        )
    try:
        head = Head(**payload["head_config"])
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{path}: invalid head configuration ({_first_line(exc)})") from exc
    check_state_dict(path, payload["head_state"], head, "map head")
    head.load_state_dict(payload["head_state"], strict=True)
    return head, payload["metadata"]


def load_map(path: str | Path, encoder: Encoder,
             payload: dict[str, Any] | None = None) -> tuple[Regressor, dict[str, Any]]:
    """Read a map and pair its head with `encoder`, which must be the one it was trained on
    (`payload`: its `read_map_header` answer, when the caller has it)."""
    head, metadata = load_head(path, encoder_fingerprint(encoder), payload)
    try:
        regressor = Regressor(encoder, head)
    except ValueError as exc:
        raise ModelError(f"{path}: {exc}") from exc
    log.info("loaded map %s", path)
    return regressor, metadata
