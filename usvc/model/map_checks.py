"""What a map file must hold to be loaded: plain metadata, every field the code reads within its
range, finite weights and keypoints, and a checksum over the whole payload (a damaged copy is
refused, a map saved before checksums loads with one note)."""

from __future__ import annotations

import hashlib
import logging
import math
import struct
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from usvc.model.errors import ModelError

log = logging.getLogger(__name__)

# "sha256:<hex>" of everything else in the payload (weights' bytes included), in a fixed order
# (`map_checksum`); maps saved before it existed have none and load with one note.
CHECKSUM_KEY = "checksum"
# Metadata fields the code reads: each is checked on load (and on save) when present.
SHORT_SIDE_RANGE = (32, 8192)  # the working short side the head was trained at, px


_PLAIN = (str, int, float, bool, type(None))


def check_plain(value: object, where: str) -> None:
    """Metadata must survive a `weights_only=True` load: plain types and tensors only."""
    if isinstance(value, _PLAIN) or isinstance(value, torch.Tensor):
        return
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            check_plain(item, f"{where}[{i}]")
        return
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ModelError(f"map metadata key {where}.{key!r} is not a string")
            check_plain(item, f"{where}.{key}")
        return
    raise ModelError(f"map metadata {where} is a {type(value).__name__}; use plain types")


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


def verify_checksum(payload: Mapping[str, Any], path: Path) -> None:
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


def check_head_config(config: Mapping[str, Any], where: str) -> None:
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


def check_encoder_entry(encoder: Mapping[str, Any], where: str) -> None:
    for key, ok, want in (("fingerprint", lambda v: isinstance(v, str) and v, "a non-empty string"),
                          ("width", lambda v: _is_number(v) and 0 <= v <= 16, "a number in [0, 16]"),
                          ("kind", lambda v: isinstance(v, str) and v, "a non-empty string"),
                          ("out_channels", lambda v: _is_int(v) and 0 < v <= 65536, "an integer in [1, 65536]")):
        if key not in encoder:
            raise ModelError(f"{where}: encoder entry has no '{key}'")
        if not ok(encoder[key]):
            raise ModelError(f"{where}: encoder {key}={encoder[key]!r:.40} must be {want}")


def check_metadata(metadata: Mapping[str, Any], where: str) -> None:
    """The fields the code reads, where present: short_side, median_depth, scene, encoder_file,
    model, method, precision, seed, iterations, final_loss, focal_range, focal_error."""
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
        "focal_error": (lambda v: _is_number(v) and math.isfinite(v) and v >= 0,
                        "a finite number >= 0: |ln(estimated / known focal)| of the map's own views, 90th percentile"),
    }
    for key, (ok, want) in checks.items():
        if key in metadata and not ok(metadata[key]):
            raise ModelError(f"{where}: metadata {key}={metadata[key]!r:.40} must be {want}")


def check_finite_state(state: Mapping[str, Any], where: str) -> None:
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ModelError(f"{where}: head weight {key} has non-finite values (NaN or inf)")


def check_keypoints(value: object, path: Path) -> None:
    """A (K,3) finite float tensor, or a one-line ModelError naming the file."""
    if not isinstance(value, torch.Tensor):
        raise ModelError(f"{path}: map keypoints_xyz is a {type(value).__name__}, expected a (K,3) tensor")
    if value.ndim != 2 or value.shape[1] != 3 or not value.is_floating_point():
        raise ModelError(f"{path}: map keypoints_xyz must be a (K,3) float tensor, "
                         f"got {value.dtype} {tuple(value.shape)}")
    if not bool(torch.isfinite(value).all()):
        raise ModelError(f"{path}: map keypoints_xyz has non-finite values")
