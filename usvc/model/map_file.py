"""map.pt, the train stage's artifact: the map file's one writer and its readers.

A map file holds only the head (fp16 weights, fp32 scene centre), the identity of the encoder it
was trained on and free-form metadata, so it stays ~4 MB and cannot be paired with the wrong
encoder by accident. `usvc.model.map_checks` validates each entry.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from usvc.core.atomic import WriteError, atomic_file
from usvc.model.encoder import Encoder, _first_line, check_state_dict, encoder_fingerprint
from usvc.model.errors import ModelError
from usvc.model.head import Head, Regressor
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

MAP_FORMAT = "usvc-map"
MAP_VERSION = 1


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
        try:
            torch.save(payload, tmp)
        except RuntimeError as exc:  # torch's zip writer reports a failed write without errno
            if "inline_container" not in str(exc) and "PytorchStreamWriter" not in str(exc):
                raise
            detail = (str(exc).splitlines() or [""])[0].rsplit("] ", 1)[-1].lstrip(". ")[:80]
            why = OSError(errno.EIO, f"torch's writer failed ({detail}): a full disk, a quota or a file-size limit?")
            raise WriteError(tmp, why) from None
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
        # The header's sizes are checked against the weights the file holds before anything is
        # allocated: a head built on the meta device has the shapes and no storage (head_config may
        # declare a 65536-wide, 64-block head, terabytes, in a file of a few MB).
        with torch.device("meta"):
            skeleton = Head(**payload["head_config"])
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{path}: invalid head configuration ({_first_line(exc)})") from exc
    check_state_dict(path, payload["head_state"], skeleton, "map head (as its head_config declares it)")
    head = Head(**payload["head_config"])
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
