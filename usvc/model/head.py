"""Per-scene regression head (ACE-style), the encoder+head regressor, and the map file format.

A map file holds only the head (fp16 weights, fp32 scene centre), the identity of the encoder it
was trained on and free-form metadata, so it stays ~4 MB and cannot be paired with the wrong
encoder by accident.
"""

from __future__ import annotations

import hashlib
import logging
import math
import struct
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
from usvc.model.safe_load import load_tensors

log = logging.getLogger(__name__)

MAX_SCALE = 4.0
MIN_SCALE = 0.01
# softplus_beta(0) = ln 2 / beta = 1 - 1 / MAX_SCALE, so o3 = 0 gives h = 1.
SOFTPLUS_BETA = math.log(2.0) / (1.0 - 1.0 / MAX_SCALE)

MAP_FORMAT = "usvc-map"
MAP_VERSION = 1
# "sha256:<hex>" of everything else in the payload (weights' bytes included), in a fixed order
# (`map_checksum`); maps saved before it existed have none and load with one note.
CHECKSUM_KEY = "checksum"
# Metadata fields the code reads: each is checked on load (and on save) when present.
SHORT_SIDE_RANGE = (32, 8192)  # the working short side the head was trained at, px


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


_PLAIN = (str, int, float, bool, type(None))


def _check_plain(value: object, where: str) -> None:
    """Metadata must survive a `weights_only=True` load: plain types and tensors only."""
    if isinstance(value, _PLAIN) or isinstance(value, torch.Tensor):
        return
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _check_plain(item, f"{where}[{i}]")
        return
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ModelError(f"map metadata key {where}.{key!r} is not a string")
            _check_plain(item, f"{where}.{key}")
        return
    raise ModelError(f"map metadata {where} is a {type(value).__name__}; use plain types")


def save_map(path: str | Path, regressor: Regressor, metadata: Mapping[str, Any],
             keypoints_xyz: np.ndarray | None = None) -> None:
    """Write the head (fp16 weights, fp32 centre), the encoder's identity and `metadata`.

    `keypoints_xyz` (K,3), when given, are the scene's kept 3D keypoints, stored as fp32 under
    "keypoints_xyz": query-time refinement projects them to pick reliable cells, so the map
    file alone is enough to relocalize with it.
    """
    metadata = dict(metadata)
    _check_plain(metadata, "metadata")
    keypoints = None
    if keypoints_xyz is not None:
        keypoints = torch.as_tensor(np.asarray(keypoints_xyz, dtype=np.float32)).clone()
        _check_keypoints(keypoints, Path(path))
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
    _check_head_config(payload["head_config"], where)
    _check_metadata(metadata, where)
    _check_finite_state(state, where)
    payload[CHECKSUM_KEY] = map_checksum(payload)
    with atomic_file(Path(path)) as tmp:
        torch.save(payload, tmp)
    log.info("saved map %s", path)


def _feed(h: Any, value: object) -> None:
    """Feed `value` to the hash `h` in a canonical form: dict keys sorted, types tagged."""
    if isinstance(value, torch.Tensor):
        t = value.detach().to("cpu").contiguous()
        h.update(b"T" + str(t.dtype).encode() + struct.pack("<q", t.ndim)
                 + b"".join(struct.pack("<q", n) for n in t.shape))
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(value, dict):
        h.update(b"D" + struct.pack("<q", len(value)))
        for key in sorted(value, key=str):
            _feed(h, str(key))
            _feed(h, value[key])
    elif isinstance(value, (list, tuple)):
        h.update(b"L" + struct.pack("<q", len(value)))
        for item in value:
            _feed(h, item)
    elif isinstance(value, str):
        data = value.encode("utf-8", "surrogatepass")
        h.update(b"S" + struct.pack("<q", len(data)) + data)
    elif isinstance(value, bool):
        h.update(b"B1" if value else b"B0")
    elif isinstance(value, int):
        data = str(value).encode()
        h.update(b"I" + struct.pack("<q", len(data)) + data)
    elif isinstance(value, float):
        data = value.hex().encode()
        h.update(b"F" + struct.pack("<q", len(data)) + data)
    elif value is None:
        h.update(b"N")
    else:  # not in a map we wrote; a file that holds it fails the comparison
        data = repr(value).encode()
        h.update(b"?" + struct.pack("<q", len(data)) + data)


def map_checksum(payload: Mapping[str, Any]) -> str:
    """"sha256:<hex>" over every payload entry but the checksum itself (head weights' bytes,
    configuration, encoder identity, metadata, keypoints), keys in sorted order."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in payload.items() if k != CHECKSUM_KEY})
    return "sha256:" + h.hexdigest()


_NOTED_UNCHECKED: set[str] = set()


def _verify_checksum(payload: Mapping[str, Any], path: Path) -> None:
    stored = payload.get(CHECKSUM_KEY)
    if stored is None:
        key = str(path.resolve())
        if key not in _NOTED_UNCHECKED:  # one note per map file, however often it is read
            _NOTED_UNCHECKED.add(key)
            log.warning("map %s has no checksum (saved by an older usvc): loading it unverified; "
                        "retrain it to add one", path)
        return
    if not isinstance(stored, str) or not stored.startswith("sha256:"):
        raise ModelError(f"map file {path} is corrupt: its checksum entry is {stored!r:.80}, not 'sha256:<hex>'")
    if map_checksum(payload) != stored:
        raise ModelError(f"map file {path} is corrupt: checksum mismatch (the file changed after it was saved: "
                         "a damaged copy or disk?)")


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_head_config(config: Mapping[str, Any], where: str) -> None:
    """in_channels, width (1..65536), num_blocks (0..64) integers and homogeneous a bool."""
    expected = {"in_channels", "width", "num_blocks", "homogeneous"}
    if set(config) != expected:
        missing, extra = sorted(expected - set(config)), sorted(map(str, set(config) - expected))
        raise ModelError(f"{where}: head_config must have {sorted(expected)}"
                         + (f"; missing {missing}" if missing else "") + (f"; unexpected {extra}" if extra else ""))
    for key, low, high in (("in_channels", 1, 65536), ("width", 1, 65536), ("num_blocks", 0, 64)):
        value = config[key]
        if not _is_int(value) or not low <= value <= high:
            raise ModelError(f"{where}: head_config {key}={value!r:.40} must be an integer in [{low}, {high}]")
    if not isinstance(config["homogeneous"], bool):
        raise ModelError(f"{where}: head_config homogeneous={config['homogeneous']!r:.40} must be true or false")


def _check_encoder_entry(encoder: Mapping[str, Any], where: str) -> None:
    for key, ok, want in (("fingerprint", lambda v: isinstance(v, str) and v, "a non-empty string"),
                          ("width", lambda v: _is_number(v) and 0 <= v <= 16, "a number in [0, 16]"),
                          ("kind", lambda v: isinstance(v, str) and v, "a non-empty string"),
                          ("out_channels", lambda v: _is_int(v) and 0 < v <= 65536, "an integer in [1, 65536]")):
        if key not in encoder:
            raise ModelError(f"{where}: encoder entry has no '{key}'")
        if not ok(encoder[key]):
            raise ModelError(f"{where}: encoder {key}={encoder[key]!r:.40} must be {want}")


def _check_metadata(metadata: Mapping[str, Any], where: str) -> None:
    """The fields the code reads, where present: short_side, median_depth, scene, encoder_file,
    model, method, precision, seed, iterations, final_loss, focal_range."""
    low, high = SHORT_SIDE_RANGE
    checks: dict[str, tuple[Callable[[Any], bool], str]] = {
        "short_side": (lambda v: _is_int(v) and low <= v <= high, f"an integer in [{low}, {high}] (px)"),
        "median_depth": (lambda v: _is_number(v) and math.isfinite(v) and v > 0,
                         "a finite positive number (scene units)"),
        "scene": (lambda v: isinstance(v, str) and v != "", "a non-empty string"),
        "encoder_file": (lambda v: isinstance(v, str) and v != "", "a non-empty string"),
        "model": (lambda v: isinstance(v, str), "a string"),
        "method": (lambda v: isinstance(v, str), "a string"),
        "precision": (lambda v: isinstance(v, str), "a string"),
        "seed": (lambda v: _is_int(v), "an integer"),
        "iterations": (lambda v: _is_int(v) and v >= 0, "a non-negative integer"),
        "final_loss": (lambda v: v is None or _is_number(v), "a number"),
        "focal_range": (lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(
            _is_number(x) and math.isfinite(x) and x > 0 for x in v) and v[0] <= v[1],
                        "[low, high]: the mapping cameras' focal lengths over their long side, 0 < low <= high"),
    }
    for key, (ok, want) in checks.items():
        if key in metadata and not ok(metadata[key]):
            raise ModelError(f"{where}: metadata {key}={metadata[key]!r:.40} must be {want}")


def _check_finite_state(state: Mapping[str, Any], where: str) -> None:
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ModelError(f"{where}: head weight {key} has non-finite values (NaN or inf)")


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
    _check_head_config(payload["head_config"], where)
    _check_encoder_entry(payload["encoder"], where)
    _check_metadata(payload["metadata"], where)
    for key, value in payload["head_state"].items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ModelError(f"map file {path} is corrupt: head weight {key} has non-finite values (NaN or inf)")
    if "keypoints_xyz" in payload:
        _check_keypoints(payload["keypoints_xyz"], path)
    _verify_checksum(payload, path)  # last: a field out of range is named as such, edited or not
    return payload


def _check_keypoints(value: object, path: Path) -> None:
    """A (K,3) finite float tensor, or a one-line ModelError naming the file."""
    if not isinstance(value, torch.Tensor):
        raise ModelError(f"{path}: map keypoints_xyz is a {type(value).__name__}, expected a (K,3) tensor")
    if value.ndim != 2 or value.shape[1] != 3 or not value.is_floating_point():
        raise ModelError(f"{path}: map keypoints_xyz must be a (K,3) float tensor, "
                         f"got {value.dtype} {tuple(value.shape)}")
    if not bool(torch.isfinite(value).all()):
        raise ModelError(f"{path}: map keypoints_xyz has non-finite values")


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
