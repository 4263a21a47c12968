"""Raw Microsoft 7-Scenes layout.

``TrainSplit.txt`` / ``TestSplit.txt`` list sequences (``sequence1`` means folder ``seq-01``).
Each sequence holds ``frame-NNNNNN.color.png``, ``.pose.txt`` (4x4 camera-to-world, metres,
OpenCV axes) and ``.depth.png`` (16-bit millimetres, 65535 = invalid). The published
intrinsics are 640x480, focal 525, principal point (320, 240). The raw depth comes from a
separate, uncalibrated sensor and is not registered to the colour image; stages that need
aligned depth must account for that.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from usvc.core.errors import SceneError
from usvc.core.scene import Camera, Frame, Scene, every_nth_split
from usvc.prepare.importers.common import (
    as_matrix,
    make_frame,
    natural_key,
    read_matrix_txt,
    world_to_cam_from_cam_to_world,
)

log = logging.getLogger(__name__)

CAMERA = Camera("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
DEPTH_SCALE = 0.001  # millimetres to metres
_COLOR_SUFFIX = ".color.png"


def _read_split_file(path: Path) -> list[str]:
    """Sequence folder names (``seq-01``) listed in a split file."""
    try:
        lines = path.read_text().split()
    except FileNotFoundError:
        raise SceneError(f"missing split file {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: unreadable ({e})") from None
    seqs = []
    for token in lines:
        m = re.fullmatch(r"sequence(\d+)", token.strip(), flags=re.IGNORECASE)
        if m is None:
            raise SceneError(f"{path}: expected lines like 'sequence1', got {token!r}")
        seqs.append(f"seq-{int(m.group(1)):02d}")
    return seqs


def _sequence_frames(root: Path, seq: str, split: str, source: Path) -> list[Frame]:
    seq_dir = root / seq
    if not seq_dir.is_dir():
        raise SceneError(f"{source}: sequence folder {seq_dir} does not exist")
    colors = sorted(seq_dir.glob(f"frame-*{_COLOR_SUFFIX}"), key=lambda p: natural_key(p.name))
    if not colors:
        raise SceneError(f"{seq_dir}: no frame-*{_COLOR_SUFFIX} images")
    frames = []
    for img in colors:
        stem = img.name[: -len(_COLOR_SUFFIX)]
        pose_file = seq_dir / f"{stem}.pose.txt"
        T = as_matrix(read_matrix_txt(pose_file), [(4, 4), (3, 4)], str(pose_file))
        R, t = world_to_cam_from_cam_to_world(T[:3, :3], T[:3, 3], str(pose_file))
        depth = seq_dir / f"{stem}.depth.png"
        frames.append(
            make_frame(
                str(pose_file),
                name=f"{seq}/{img.name}",
                image_path=img,
                camera=CAMERA,
                split=split,
                R=R,
                t=t,
                depth_path=depth if depth.is_file() else None,
                depth_scale=DEPTH_SCALE,
            )
        )
    return frames


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    """Import a raw 7-Scenes scene; ``every_nth`` uses every ``seq-*`` folder in natural order."""
    frames: list[Frame] = []
    if split_rule == "given":
        for split, fname in SPLIT_FILES.items():
            source = root / fname
            for seq in _read_split_file(source):
                frames.extend(_sequence_frames(root, seq, split, source))
    else:
        seqs = sorted((d.name for d in root.glob("seq-*") if d.is_dir()), key=natural_key)
        if not seqs:
            raise SceneError(f"scene {name!r}: no seq-* folders in {root}")
        for seq in seqs:
            frames.extend(_sequence_frames(root, seq, "train", root))
        frames.sort(key=lambda f: natural_key(f.name))
        for frame, split in zip(frames, every_nth_split(split_n, len(frames))):
            frame.split = split
    log.info("7scenes %s: %d frames", name, len(frames))
    return Scene(name=name, frames=frames, metric_scale=1.0 if metric_scale is None else metric_scale, root=root)
