"""Raw Cambridge Landmarks layout (PoseNet release).

``dataset_train.txt`` / ``dataset_test.txt`` hold three header lines, then one line per
image: ``seq1/frame00001.png X Y Z W P Q R`` = camera centre (world) and the world-to-camera
rotation as a (w, x, y, z) quaternion, both from the VisualSFM reconstruction.

The split files carry no intrinsics, so the per-image focal length is taken from the
VisualSFM model ``reconstruction.nvm`` (NVM_V3: camera lines
``<name> <focal> <qw qx qy qz> <cx cy cz> <radial> 0``). NVM names use ``.jpg`` where the
split files say ``.png``, so images are matched on their path without extension.

Assumptions, stated because the release documents neither:
- the NVM focal refers to the 1920x1080 original frames; the images on disk may be
  downscaled, so the focal is multiplied by (actual width / 1920), with the actual size
  read from the first image and shared by all (an aspect ratio other than 16:9 is an error);
- the camera is SIMPLE_PINHOLE with the principal point at the image centre. The NVM radial
  term uses VisualSFM's own distortion model, which does not map onto COLMAP's, and it is
  small for these frames, so it is dropped rather than converted approximately.
"""

from __future__ import annotations

import logging
from pathlib import Path, PurePosixPath

import numpy as np

from usvc.core.errors import SceneError
from usvc.core.scene import Frame, Scene, every_nth_split
from usvc.prepare.importers.common import (
    image_size,
    make_camera,
    make_frame,
    natural_key,
    quat_wxyz_to_R,
)

log = logging.getLogger(__name__)

SPLIT_FILES = {"train": "dataset_train.txt", "test": "dataset_test.txt"}
NVM_FILE = "reconstruction.nvm"
ORIGINAL_SIZE = (1920, 1080)
_HEADER_LINES = 3


def _key(name: str) -> str:
    """Image path without extension, ``/``-separated, so NVM ``.jpg`` matches split ``.png``."""
    p = PurePosixPath(name.strip().replace("\\", "/"))
    parts = [s for s in p.parts if s != "."]
    return str(PurePosixPath(*parts).with_suffix("")) if parts else ""


def read_split_file(path: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(image name, camera centre, world-to-camera quaternion wxyz) for each entry of a split file."""
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise SceneError(f"missing split file {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: unreadable ({e})") from None
    out = []
    for lineno, line in enumerate(lines[_HEADER_LINES:], start=_HEADER_LINES + 1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != 8:
            raise SceneError(f"{path}:{lineno}: expected 'image X Y Z W P Q R', got {len(tokens)} fields")
        try:
            values = np.array([float(v) for v in tokens[1:]])
        except ValueError:
            raise SceneError(f"{path}:{lineno}: pose values are not numbers") from None
        out.append((tokens[0], values[:3], values[3:]))
    if not out:
        raise SceneError(f"{path}: no image entries after the {_HEADER_LINES} header lines")
    return out


def read_nvm_focals(path: Path) -> dict[str, float]:
    """Focal length per image key from the first model of an NVM_V3 file (cameras only)."""
    if not path.is_file():
        raise SceneError(
            f"{path} is missing: Cambridge split files carry no intrinsics, so the NVM model is needed"
        )
    focals: dict[str, float] = {}
    try:
        with path.open() as fh:
            lines = (line for line in fh if line.strip())
            header = next(lines, "")
            if not header.startswith("NVM_V3"):
                raise SceneError(f"{path}: not an NVM_V3 file (header {header.strip()[:40]!r})")
            count = int(next(lines, "").split()[0])
            for i in range(count):
                tokens = next(lines, "").split()
                if len(tokens) < 10:
                    raise SceneError(f"{path}: camera {i} line is truncated")
                focals[_key(tokens[0])] = float(tokens[1])
    except (IndexError, ValueError):
        raise SceneError(f"{path}: unparseable NVM camera list") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: unreadable ({e})") from None
    return focals


def _scale(root: Path, first_image: str) -> tuple[tuple[int, int], float]:
    """Actual image size and focal scale factor relative to the 1920x1080 originals."""
    W, H = image_size(root / first_image)
    sx, sy = W / ORIGINAL_SIZE[0], H / ORIGINAL_SIZE[1]
    if abs(sx - sy) > 0.01 * sx:
        raise SceneError(
            f"{root / first_image}: size {W}x{H} is not a scaled copy of the "
            f"{ORIGINAL_SIZE[0]}x{ORIGINAL_SIZE[1]} originals the NVM focal refers to"
        )
    return (W, H), sx


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    """Import a Cambridge Landmarks scene; ``every_nth`` re-splits the union in natural order."""
    entries: list[tuple[str, str, np.ndarray, np.ndarray, Path]] = []
    for split, fname in SPLIT_FILES.items():
        src = root / fname
        entries.extend((split, img, c, q, src) for img, c, q in read_split_file(src))
    focals = read_nvm_focals(root / NVM_FILE)
    if split_rule == "every_nth":
        entries.sort(key=lambda e: natural_key(e[1]))
        entries = [(s, *e[1:]) for s, e in zip(every_nth_split(split_n, len(entries)), entries)]
    (W, H), scale = _scale(root, entries[0][1])
    frames: list[Frame] = []
    for split, img, center, quat, src in entries:
        where = f"{src} ({img})"
        if _key(img) not in focals:
            raise SceneError(f"{where}: image not found in {root / NVM_FILE}")
        R = quat_wxyz_to_R(quat, where)
        cam = make_camera(where, "SIMPLE_PINHOLE", W, H, (focals[_key(img)] * scale, W / 2.0, H / 2.0))
        frames.append(
            make_frame(where, name=img, image_path=root / img, camera=cam, split=split, R=R, t=-R @ center)
        )
    log.info("cambridge %s: %d frames, images %dx%d", name, len(frames), W, H)
    return Scene(name=name, frames=frames, metric_scale=1.0 if metric_scale is None else metric_scale, root=root)
