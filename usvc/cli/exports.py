"""Localized photos as files other tools open: JSON lines, poses.txt, a COLMAP model and
nerfstudio's transforms.json.

The COLMAP model is COLMAP's text format (cameras.txt, images.txt, points3D.txt) when every photo
name fits it, and its binary format (cameras.bin, images.bin, points3D.bin, rigs.bin, frames.bin)
when a name holds white space, which the text format cuts at.

Poses are world-to-camera (R, t) in OpenCV axes, as everywhere in usvc. :func:`export` renders
and checks every requested file before it writes any, and writes each one atomically, so a
failure leaves the output folder as it was.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from usvc.core.artifact_names import POSES_TXT
from usvc.core.atomic import atomic_file
from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers, matrix_to_quat_wxyz
from usvc.core.poses_file import write_poses_txt
from usvc.core.scene import Camera

FORMATS = ("jsonl", "poses", "colmap", "nerfstudio")
JSONL_FILE, TRANSFORMS_FILE = "queries.jsonl", "transforms.json"
COLMAP_FILES = ("cameras.txt", "images.txt", "points3D.txt")
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])  # flips the camera's y and z axes (either way)


@dataclass(frozen=True)
class Posed:
    """A localized photo: its name as reported, its file, its camera and its pose.

    `R`, `t` are world-to-camera (x_cam = R x_world + t, OpenCV axes).
    """

    name: str
    path: Path
    camera: Camera
    R: np.ndarray
    t: np.ndarray


def _write_text(path: Path, text: str | bytes) -> Path:
    with atomic_file(path) as tmp:
        if isinstance(text, bytes):
            tmp.write_bytes(text)
        else:
            tmp.write_text(text, encoding="utf-8")
    return path


def check_names(formats: Sequence[str], names: Sequence[str], paths: Sequence[Path]) -> None:
    """Fail early on photo names the requested formats cannot hold (before any work is done)."""
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise UsvcError(f"unknown --format {unknown[0]!r}; known: {', '.join(FORMATS)}")
    if set(formats) - {"jsonl"}:
        seen: set[Path] = set()
        for name, path in zip(names, paths):
            if Path(path).resolve() in seen:
                raise UsvcError(f"photo {name} is given twice; --format {','.join(formats)} needs each once")
            seen.add(Path(path).resolve())
    if "colmap" in formats:
        colmap_names(paths)


def jsonl_text(records: Sequence[Mapping[str, Any]]) -> str:
    return "".join(json.dumps(r) + "\n" for r in records)


def colmap_names(paths: Sequence[Path]) -> list[str]:
    """COLMAP image names: paths relative to the photos' common folder (COLMAP's image_path)."""
    resolved = [Path(p).resolve() for p in paths]
    if not resolved:
        return []
    try:
        root = Path(os.path.commonpath([p.parent for p in resolved]))
    except ValueError:  # Windows: photos on different drives
        raise UsvcError("a COLMAP model needs its photos under one folder; these are on different drives") from None
    names = [p.relative_to(root).as_posix() for p in resolved]
    if len(set(names)) != len(names):
        raise UsvcError(f"COLMAP image names must be unique; a photo is given twice (in {root})")
    return names


def text_holds(names: Sequence[str]) -> bool:
    """Whether COLMAP's text model holds these image names (it cuts a name at white space)."""
    return not any(c.isspace() for name in names for c in name)


def colmap_binary(items: Sequence[Posed]) -> dict[str, bytes]:
    """COLMAP's binary model of the photos (any image name), file name -> bytes."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    camera_ids: dict[tuple[Any, ...], int] = {}
    for image_id, (item, name) in enumerate(zip(items, colmap_names([i.path for i in items])), start=1):
        c = item.camera
        key = (c.model, c.width, c.height, *(float(v) for v in c.params))
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(model=c.model, width=c.width, height=c.height,
                                                            params=list(c.params), camera_id=camera_ids[key]))
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(item.R, dtype=np.float64)),
                                np.asarray(item.t, dtype=np.float64).reshape(3))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=camera_ids[key], image_id=image_id), pose)
    with tempfile.TemporaryDirectory(prefix="usvc-colmap-") as folder:
        rec.write_binary(folder)
        return {p.name: p.read_bytes() for p in sorted(Path(folder).iterdir())}


def colmap_texts(items: Sequence[Posed]) -> dict[str, str]:
    """cameras.txt, images.txt and a points3D.txt without points; identical cameras are shared."""
    camera_ids: dict[tuple[Any, ...], int] = {}
    cameras: list[str] = []
    image_lines: list[str] = []
    for image_id, (item, name) in enumerate(zip(items, colmap_names([i.path for i in items])), start=1):
        c = item.camera
        key = (c.model, c.width, c.height, *(float(v) for v in c.params))
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            cameras.append(" ".join([str(camera_ids[key]), *map(str, key[:3]), *map(repr, key[3:])]))
        camera_id = camera_ids[key]
        pose = [*matrix_to_quat_wxyz(item.R), *np.asarray(item.t, dtype=np.float64).reshape(3)]
        image_lines += [" ".join([str(image_id), *(repr(float(v)) for v in pose), str(camera_id), name]), ""]
    return {
        "cameras.txt": "\n".join(["# Camera list with one line of data per camera:",
                                  "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                                  f"# Number of cameras: {len(cameras)}", *cameras]) + "\n",
        "images.txt": "\n".join(["# Image list with two lines of data per image:",
                                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                                 f"# Number of images: {len(items)}, mean observations per image: 0",
                                 *image_lines]) + "\n",
        "points3D.txt": "\n".join(["# 3D point list with one line of data per point:",
                                   "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                                   "# Number of points: 0, mean track length: 0"]) + "\n",
    }


def nerfstudio_intrinsics(camera: Camera, where: str) -> dict[str, Any]:
    """fl_x fl_y cx cy w h, plus camera_model and k1 k2 (k3 k4) p1 p2 for a distorted camera."""
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    out: dict[str, Any] = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": camera.width, "h": camera.height}
    if not camera.has_distortion:
        return out
    p = [float(v) for v in camera.params]
    if camera.model == "OPENCV_FISHEYE":
        return {**out, "camera_model": "OPENCV_FISHEYE", "k1": p[4], "k2": p[5], "k3": p[6], "k4": p[7]}
    if camera.model == "FULL_OPENCV" and any(p[9:]):
        raise UsvcError(f"{where}: FULL_OPENCV with k4..k6 (rational model) has no nerfstudio equivalent")
    q = p + [0.0] * 12  # every model's entry below is evaluated
    k1, k2, p1, p2, k3 = {"SIMPLE_RADIAL": (q[3], 0.0, 0.0, 0.0, 0.0), "RADIAL": (q[3], q[4], 0.0, 0.0, 0.0),
                          "OPENCV": (*q[4:8], 0.0), "FULL_OPENCV": tuple(q[4:9])}[camera.model]
    return {**out, "camera_model": "OPENCV", "k1": k1, "k2": k2, "p1": p1, "p2": p2, **({"k3": k3} if k3 else {})}


def transforms_json_text(items: Sequence[Posed], folder: Path) -> str:
    """nerfstudio transforms.json for a file in ``folder``: camera-to-world in OpenGL axes."""
    frames = []
    for item in items:
        R = np.asarray(item.R, dtype=np.float64)
        cam_to_world = np.eye(4)
        cam_to_world[:3, :3] = R.T @ _CV_TO_GL
        cam_to_world[:3, 3] = camera_centers(R, item.t)
        try:
            file_path = Path(os.path.relpath(Path(item.path).resolve(), folder.resolve())).as_posix()
        except ValueError:  # Windows: another drive than the output folder
            file_path = Path(item.path).resolve().as_posix()
        frames.append({"file_path": file_path,
                       "transform_matrix": cam_to_world.tolist(), **nerfstudio_intrinsics(item.camera, item.name)})
    models = {f.get("camera_model", "OPENCV") for f in frames}
    if len(models) > 1:
        raise UsvcError(f"transforms.json holds one lens type, but the photos mix {sorted(models)}")
    top = {"camera_model": models.pop()} if any("camera_model" in f for f in frames) else {}
    return json.dumps({**top, "frames": frames}, indent=2) + "\n"


def write_poses(path: Path, items: Sequence[Posed]) -> Path:
    write_poses_txt(path, [i.name for i in items], np.array([i.R for i in items]).reshape(-1, 3, 3),
                    np.array([i.t for i in items]).reshape(-1, 3))
    return Path(path)


def export(out_dir: Path, formats: Sequence[str], records: Sequence[Mapping[str, Any]],
           items: Sequence[Posed]) -> list[Path]:
    """Write the requested formats into ``out_dir``: queries.jsonl (all records), poses.txt, the
    COLMAP model (text, or binary for names with white space) and transforms.json (the localized
    photos only)."""
    out_dir = Path(out_dir)
    check_names(formats, [i.name for i in items], [i.path for i in items])
    texts: dict[Path, str | bytes] = {}  # rendered (and so checked) before anything is written
    if "jsonl" in formats:
        texts[out_dir / JSONL_FILE] = jsonl_text(records)
    if "colmap" in formats:
        model = colmap_texts(items) if text_holds(colmap_names([i.path for i in items])) else colmap_binary(items)
        texts.update({out_dir / name: text for name, text in model.items()})
    if "nerfstudio" in formats:
        texts[out_dir / TRANSFORMS_FILE] = transforms_json_text(items, out_dir)
    written = [write_poses(out_dir / POSES_TXT, items)] if "poses" in formats else []
    return written + [_write_text(path, text) for path, text in texts.items()]
