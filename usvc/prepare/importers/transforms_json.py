"""instant-ngp / nerfstudio / Blender ``transforms.json`` layout.

Intrinsics (``fl_x fl_y cx cy w h``, or ``camera_angle_x``) sit at
the top level and may be overridden per frame (nerfstudio). ``transform_matrix`` is
camera-to-world in OpenGL/Blender camera axes (x right, y up, z backwards); negating its y
and z columns gives OpenCV axes. ``cx, cy`` are kept as given: both instant-ngp and
nerfstudio put the image centre at (w/2, h/2), which is COLMAP's convention. A world-frame
change recorded by nerfstudio (``applied_transform``) is a rigid change of the whole world
and is left baked in, since relocalization only needs a consistent world.

Lens models as nerfstudio writes them (``camera_model``): ``OPENCV`` with ``k1 k2 p1 p2`` (and
``k3``, which makes it COLMAP's FULL_OPENCV), ``OPENCV_FISHEYE`` with ``k1 k2 k3 k4``, or
``PINHOLE``; ``is_fisheye: true`` (instant-ngp) means OPENCV_FISHEYE.

Frames listed but absent on disk are skipped with a warning (datasets are often pruned after
export); a scene with none left is an error.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from usvc.core.errors import SceneError
from usvc.core.scene import Camera, Frame, Scene, every_nth_split
from usvc.prepare.importers.common import (
    IMAGE_SUFFIXES,
    as_matrix,
    image_size,
    make_camera,
    make_frame,
    world_to_cam_from_cam_to_world,
)

log = logging.getLogger(__name__)

MAIN_FILE = "transforms.json"
BLENDER_FILES = {"train": "transforms_train.json", "test": "transforms_test.json"}
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_MODELS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneError(f"missing file {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SceneError(f"{path}: unparseable JSON ({e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise SceneError(f"{path}: no 'frames' list at the top level")
    return data


def _number(d: dict[str, Any], key: str, where: str) -> float:
    try:
        return float(d[key])
    except (TypeError, ValueError):
        raise SceneError(f"{where}: {key!r} is not a number ({d[key]!r})") from None


def _focal_from_angle(size: float, intr: dict[str, Any], key: str, where: str) -> float:
    """Focal in pixels from a full field-of-view angle in radians (instant-ngp / Blender)."""
    angle = _number(intr, key, where)
    if not 0.0 < angle < math.pi:
        raise SceneError(f"{where}: {key!r} must be in (0, pi) radians, got {angle}")
    return 0.5 * size / math.tan(0.5 * angle)


def _match_key(file_path: str) -> str:
    """Normalised relative path without an image extension, to match split lists to frames."""
    p = PurePosixPath(os.path.normpath(str(file_path).replace("\\", "/")))
    return str(p.with_suffix("")) if p.suffix.lower() in IMAGE_SUFFIXES else str(p)


def _resolve_image(base: Path, file_path: str) -> Path | None:
    """The image a ``file_path`` refers to; Blender omits the extension, so try the usual ones."""
    p = base / file_path
    if p.is_file():
        return p
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        for ext in IMAGE_SUFFIXES + tuple(s.upper() for s in IMAGE_SUFFIXES):
            candidate = p.with_name(p.name + ext)
            if candidate.is_file():
                return candidate
    return None


def _model(intr: dict[str, Any], where: str) -> str:
    model = "OPENCV_FISHEYE" if intr.get("is_fisheye") else intr.get("camera_model", "OPENCV")
    if model not in _MODELS:
        raise SceneError(f"{where}: camera model {model!r} is not supported; supported: {', '.join(_MODELS)}")
    return str(model)


def _camera(intr: dict[str, Any], image: Path, where: str) -> Camera:
    """Camera from merged top-level and per-frame intrinsics keys."""
    model = _model(intr, where)
    if "w" in intr and "h" in intr:
        w, h = _number(intr, "w", where), _number(intr, "h", where)
    else:
        w, h = (float(v) for v in image_size(image))
    if not (w > 0 and h > 0):
        raise SceneError(f"{where}: image size must be positive, got {w}x{h}")
    if "fl_x" in intr:
        fx = _number(intr, "fl_x", where)
    elif "camera_angle_x" in intr:
        fx = _focal_from_angle(w, intr, "camera_angle_x", where)
    else:
        raise SceneError(f"{where}: neither 'fl_x' nor 'camera_angle_x' is given")
    if "fl_y" in intr:
        fy = _number(intr, "fl_y", where)
    elif "camera_angle_y" in intr:
        fy = _focal_from_angle(h, intr, "camera_angle_y", where)
    else:
        fy = fx
    cx = _number(intr, "cx", where) if "cx" in intr else w / 2.0
    cy = _number(intr, "cy", where) if "cy" in intr else h / 2.0
    d = {k: _number(intr, k, where) if k in intr else 0.0 for k in _DISTORTION_KEYS}
    size = (round(w), round(h))
    if model == "OPENCV_FISHEYE":
        if d["p1"] or d["p2"]:
            raise SceneError(f"{where}: OPENCV_FISHEYE has no tangential terms, got p1={d['p1']}, p2={d['p2']}")
        return make_camera(where, model, *size, (fx, fy, cx, cy, d["k1"], d["k2"], d["k3"], d["k4"]))
    if d["k4"]:
        raise SceneError(f"{where}: distortion 'k4' is not representable in the OPENCV model")
    if d["k3"]:
        return make_camera(where, "FULL_OPENCV", *size,
                           (fx, fy, cx, cy, d["k1"], d["k2"], d["p1"], d["p2"], d["k3"], 0.0, 0.0, 0.0))
    if model == "OPENCV" and any(k in intr for k in _DISTORTION_KEYS):
        return make_camera(where, "OPENCV", *size, (fx, fy, cx, cy, d["k1"], d["k2"], d["p1"], d["p2"]))
    return make_camera(where, "PINHOLE", *size, (fx, fy, cx, cy))


def _frames_from(json_path: Path, root: Path) -> list[tuple[str, Frame]]:
    """(match key, frame with split 'train') for each frame of one json whose image exists."""
    data = _read_json(json_path)
    top = {k: v for k, v in data.items() if k in _INTRINSIC_KEYS + _DISTORTION_KEYS}
    top.update({k: data[k] for k in ("camera_model", "is_fisheye") if k in data})
    out: list[tuple[str, Frame]] = []
    missing: list[str] = []
    for i, entry in enumerate(data["frames"]):
        where = f"{json_path} frame {i}"
        if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
            raise SceneError(f"{where}: needs 'file_path' and 'transform_matrix'")
        file_path = str(entry["file_path"])
        image = _resolve_image(json_path.parent, file_path)
        if image is None:
            missing.append(file_path)
            continue
        where = f"{json_path} frame {i} ({file_path})"
        T = as_matrix(entry["transform_matrix"], [(4, 4), (3, 4)], where)
        R, t = world_to_cam_from_cam_to_world(T[:3, :3] @ _GL_TO_CV, T[:3, 3], where)
        camera = _camera({**top, **entry}, image, where)
        name = Path(os.path.relpath(image, root)).as_posix()
        frame = make_frame(where, name=name, image_path=image.resolve(), camera=camera, split="train", R=R, t=t)
        out.append((_match_key(file_path), frame))
    if missing:
        log.warning(
            "%s: skipping %d listed frame(s) missing on disk, first: %s", json_path, len(missing), missing[0]
        )
        if not out:
            raise SceneError(f"{json_path}: none of the {len(missing)} listed images exist (first: {missing[0]})")
    return out


def _given_lists(data: dict[str, Any], path: Path) -> tuple[set[str], set[str]] | None:
    """nerfstudio's split lists (test falls back to val, as nerfstudio itself does)."""
    test_key = "test_filenames" if "test_filenames" in data else "val_filenames"
    if "train_filenames" not in data or test_key not in data:
        return None
    for key in ("train_filenames", test_key):
        if not isinstance(data[key], list):
            raise SceneError(f"{path}: {key!r} must be a list of file names")
    return {_match_key(s) for s in data["train_filenames"]}, {_match_key(s) for s in data[test_key]}


def _split_by_lists(items: list[tuple[str, Frame]], lists: tuple[set[str], set[str]], src: Path) -> list[Frame]:
    train, test = lists
    frames: list[Frame] = []
    dropped = 0
    for key, frame in items:
        if key in test:
            frame.split = "test"
        elif key in train:
            frame.split = "train"
        else:
            dropped += 1
            continue
        frames.append(frame)
    if dropped:
        log.warning("%s: %d frame(s) are in neither train_filenames nor test_filenames; dropped", src, dropped)
    return frames


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    """Import from ``root`` (a folder with transforms*.json, or a json file itself)."""
    main = root if root.is_file() else root / MAIN_FILE
    base = main.parent
    blender = {s: base / f for s, f in BLENDER_FILES.items()}
    has_blender = all(p.is_file() for p in blender.values())
    if not main.is_file() and not has_blender:
        raise SceneError(f"scene {name!r}: no {MAIN_FILE} (or {' + '.join(BLENDER_FILES.values())}) in {base}")

    if split_rule == "given":
        lists = _given_lists(_read_json(main), main) if main.is_file() else None
        if lists is not None:
            frames = _split_by_lists(_frames_from(main, base), lists, main)
        elif has_blender:
            frames = [f for _, f in _frames_from(blender["train"], base)]
            for _, f in _frames_from(blender["test"], base):
                f.split = "test"
                frames.append(f)
        else:
            raise SceneError(
                f"scene {name!r}: {main} has no train_filenames/test_filenames and there are no "
                f"{' / '.join(BLENDER_FILES.values())}; use split_rule='every_nth'"
            )
    else:
        sources = [main] if main.is_file() else [blender["train"], blender["test"]]
        frames = [f for src in sources for _, f in _frames_from(src, base)]
        for frame, split in zip(frames, every_nth_split(split_n, len(frames))):
            frame.split = split
    log.info("transforms %s: %d frames", name, len(frames))
    return Scene(name=name, frames=frames, metric_scale=metric_scale, root=base)
