"""Importers from published dataset layouts into the canonical :class:`usvc.core.scene.Scene`.

Each format module exposes ``load(root, name, split_rule, split_n, metric_scale) -> Scene``
and converts poses, intrinsics and pixel conventions itself, so nothing downstream guesses.
The helpers they share live in ``common``; every bad input becomes one ``SceneError``
line naming the file at fault instead of a numpy or KeyError traceback.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from usvc.core.errors import SceneError
from usvc.core.scene import Scene
from usvc.prepare.options import FORMATS, SPLIT_RULES

_MODULES = {
    "llff": "llff",
    "transforms": "transforms_json",
    "colmap": "colmap_model",
    "ace": "ace_layout",
    "7scenes": "seven_scenes",
    "cambridge": "cambridge",
    "images": "photos",
}


def import_scene(
    fmt: str,
    path: str | Path,
    name: str,
    split_rule: str = "given",
    split_n: int = 8,
    metric_scale: float | None = None,
    exif_focal: bool = True,
) -> Scene:
    """The scene at ``path`` stored in layout ``fmt``, not yet checked for its images and splits
    (:func:`load_scene` does both): for callers that first count the photos themselves.

    ``exif_focal`` (format ``images`` only): False ignores the photos' EXIF focal lengths.
    """
    if fmt not in FORMATS:
        raise SceneError(f"unknown scene format {fmt!r}; known formats: {', '.join(FORMATS)}")
    if split_rule not in SPLIT_RULES:
        raise SceneError(f"scene {name!r}: unknown split rule {split_rule!r}; expected one of {SPLIT_RULES}")
    root = Path(path).expanduser()
    if not root.exists():
        raise SceneError(f"scene {name!r}: path {root} does not exist")
    root = root.resolve()
    module = importlib.import_module(f"usvc.prepare.importers.{_MODULES[fmt]}")
    extra = {} if fmt != "images" else {"exif_focal": exif_focal}
    try:
        scene: Scene = module.load(root, name, split_rule, split_n, metric_scale, **extra)
    except OSError as e:  # permissions, broken links: still one line naming the file
        raise SceneError(f"scene {name!r}: {e}") from None
    return scene


def load_scene(
    fmt: str,
    path: str | Path,
    name: str,
    split_rule: str = "given",
    split_n: int = 8,
    metric_scale: float | None = None,
    exif_focal: bool = True,
) -> Scene:
    """Import the scene at ``path`` stored in layout ``fmt`` and validate it fully.

    Validation happens here rather than lazily so a broken scene fails at import time with
    the file named, not halfway through a long stage: images must exist and both splits
    must be non-empty.
    """
    scene = import_scene(fmt, path, name, split_rule, split_n, metric_scale, exif_focal)
    scene.check_images_exist()
    for which in ("train", "test"):
        scene.split(which)
    return scene
