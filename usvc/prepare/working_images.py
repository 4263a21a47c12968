"""Import a scene, undistort every image to a PINHOLE camera, and resize it to the working width.

Undistortion happens here, once, at the source resolution (``usvc.core.undistort``), before resizing:
every later stage (SfM, buffer, Gaussian splatting, relocalization, metrics) sees pinhole images
only. Poses are unchanged by undistortion, so metrics still score against the imported poses.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from usvc.core.artifact_names import SCENE_H5
from usvc.core.atomic import WRITE_ERRNOS, WriteError, final_path
from usvc.core.cores import cores_available
from usvc.core.errors import SceneError
from usvc.core.geometry import field_of_view_deg
from usvc.core.images import read_photo
from usvc.core.ordered_pool import library_threads, ordered_map
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import IMAGE_DIR, PackedDepth, read_scene_h5, write_scene_h5
from usvc.core.undistort import check_distortion, undistort
from usvc.sfm.posing import pose_scene
from usvc.sfm.reconstruction import MIN_MAPPING_IMAGES, SfmOptions

log = logging.getLogger(__name__)

# Field of view (degrees) a camera's given intrinsics may imply. Below the narrow end, across the
# longer side, no photographic lens reaches (a 3,000 mm equivalent super-zoom sees about 0.7 deg);
# beyond the wide end a pinhole (undistorted) model cannot image at all, so a wider view needs a
# distortion model. Outside them the focal length is wrong (a unit mix-up, a field swapped).
MIN_GIVEN_FOV_DEG, MAX_PINHOLE_FOV_DEG = 0.5, 170.0


def working_size(width: int, height: int, working_width: int) -> tuple[int, int]:
    """Size after resizing to `working_width` (0 keeps it), preserving the aspect ratio."""
    if working_width == 0 or working_width == width:
        return width, height
    return working_width, max(1, round(height * working_width / width))


def _read_depth(frame: Frame) -> np.ndarray | None:
    if frame.depth_path is None or not Path(frame.depth_path).is_file():
        return None
    raw = cv2.imread(str(frame.depth_path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SceneError(f"cannot read depth map {frame.depth_path}")
    return raw.astype(np.float32) * np.float32(frame.depth_scale)


def prepare_scene(scene: Scene, out_dir: Path, working_width: int, undistort_fov: str = "crop",
                  sfm: SfmOptions | None = None, threads: int = -1) -> dict:
    """Write undistorted, resized images and scene.h5 into `out_dir` (which must be empty).

    `undistort_fov` is ``crop`` (no black borders) or ``full`` (every source pixel kept); see
    :mod:`usvc.core.undistort`. A scene without poses is first posed by SfM (:mod:`usvc.sfm.posing`,
    options `sfm`, feature extraction on `threads` threads) on its photos at working resolution,
    then undistorted with the calibrated cameras. Photos are read, undistorted, resized and written
    `threads` at a time (-1: every core this process may use), the same files for any count.
    Returns summary figures for the stage's metrics file.
    """
    if not scene.has_poses:
        return _prepare_unposed(scene, out_dir, working_width, undistort_fov, sfm,
                                threads)
    return _write_prepared(scene, out_dir, working_width, undistort_fov, threads=threads)


def check_distinct_mapping_images(scene: str, contents: dict[str, list[str]]) -> None:
    """Copies of one photo carry no geometry (SfM would triangulate noise between them): refuse a
    scene that is mostly copies, warn about a few."""
    copies = [names for names in contents.values() if len(names) > 1]
    if not copies:
        return
    n_images = sum(len(names) for names in contents.values())
    example = ", ".join(max(copies, key=len)[:3])
    if len(contents) < MIN_MAPPING_IMAGES or len(contents) < n_images / 2:
        raise SceneError(f"scene {scene!r}: only {len(contents)} of {n_images} mapping images differ; the rest are "
                         f"pixel-identical copies (e.g. {example}): SfM and the map need photos from different "
                         "viewpoints")
    log.warning("scene %r: %d mapping images are pixel-identical copies of others (e.g. %s)", scene,
                sum(len(n) - 1 for n in copies), example)


def field_of_view_problem(camera: Camera) -> str:
    """Why the camera's focal lengths cannot be a real camera's ("" when they can): a field of view
    across the longer side under MIN_GIVEN_FOV_DEG, or one over MAX_PINHOLE_FOV_DEG along either
    axis for a model without distortion."""
    fovs = [(axis, size, focal, field_of_view_deg(focal, size))
            for axis, size, focal in (("horizontal", camera.width, camera.focal[0]),
                                      ("vertical", camera.height, camera.focal[1]))]
    size = f"{camera.width}x{camera.height} images"
    axis, _, focal, fov = fovs[0] if camera.width >= camera.height else fovs[1]
    if fov < MIN_GIVEN_FOV_DEG:
        return (f"focal length {focal:.6g} px for {size} implies a {fov:.3g} deg {axis} field of view, narrower "
                f"than any camera's ({MIN_GIVEN_FOV_DEG:g} deg): check its unit and field")
    for axis, _, focal, fov in fovs:
        if fov > MAX_PINHOLE_FOV_DEG and not camera.has_distortion:
            return (f"focal length {focal:.6g} px for {size} implies a {fov:.4g} deg {axis} field of view, wider "
                    f"than a camera without lens distortion can see ({MAX_PINHOLE_FOV_DEG:g} deg): check its unit "
                    "and field, or give the distortion model")
    return ""


def decoded(frame: Frame) -> tuple[np.ndarray, Camera]:
    """The frame's photo and its camera at the decoded size: a JPEG over MAX_DECODE_PIXELS is
    decoded reduced (usvc.core.images.read_photo), and its camera is scaled with it."""
    photo = read_photo(frame.image_path)
    if photo.reduction == 1:
        return photo.bgr, frame.camera
    h, w = photo.bgr.shape[:2]
    if photo.size != (frame.camera.width, frame.camera.height):  # the size check names both
        return photo.bgr, frame.camera
    log.info("%s: %dx%d pixels, decoded at 1/%d", frame.image_path, *photo.size, photo.reduction)
    return photo.bgr, frame.camera.scaled(w, h)


def check_cameras(frames: list[Frame], undistort_fov: str) -> None:
    """Every distinct camera's focal lengths and distortion, before any photo is decoded (errors
    name its photos)."""
    photos: dict = {}
    for f in frames:
        photos.setdefault(f.camera, []).append(f.name)
    for camera, names in photos.items():
        more = f" and {len(names) - 1} more photo{'s' * (len(names) > 2)}" if len(names) > 1 else ""
        why = field_of_view_problem(camera)
        if why:
            raise SceneError(f"the camera of {names[0]}{more}: {why}")
        check_distortion(camera, undistort_fov, where=f"{names[0]}{more}")


COLMAP_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")  # the formats SfM's reader decodes


def write_image(dst: Path, image: np.ndarray, where: str | None = None) -> None:
    """Encode in memory and write with Python's own file calls (the same bytes as cv2.imwrite), so a
    full or read-only disk is a WriteError naming the destination folder and the reason
    (cv2.imwrite only answers False). `where`: the folder to name instead of dst's (in words)."""
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if dst.suffix.lower() in (".jpg", ".jpeg") else []
    # A photo in a format COLMAP's reader does not decode (.webp) keeps its name, with PNG's bytes:
    # COLMAP, OpenCV and Pillow all tell the format by the content.
    ok, encoded = cv2.imencode(dst.suffix if dst.suffix.lower() in COLMAP_SUFFIXES else ".png", image, params)
    if not ok:
        raise SceneError(f"cannot encode image {final_path(dst)} as {dst.suffix}")
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(dst, "wb") as f:
            f.write(encoded.tobytes())
    except OSError as exc:
        if exc.errno not in WRITE_ERRNOS:
            raise
        with contextlib.suppress(OSError):
            dst.unlink(missing_ok=True)
        raise WriteError(dst, exc, "image", where) from None


def _prepared_image(frame: Frame, out_dir: Path, working_width: int, undistort_fov: str,
                    where: str | None) -> tuple[Frame, PackedDepth | None, str | None]:
    """Undistort, resize and write one frame's image: (its prepared frame, its depth at working
    size, packed, or None, the hash of a mapping image's pixels)."""
    image, camera = undistort(*decoded(frame), undistort_fov, where=str(frame.image_path))
    depth = _read_depth(frame)
    if depth is not None and frame.camera.has_distortion:
        depth = cv2.resize(depth, (frame.camera.width, frame.camera.height), interpolation=cv2.INTER_NEAREST)
        depth, _ = undistort(depth, frame.camera, undistort_fov, where=str(frame.depth_path), nearest=True)
    h, w = image.shape[:2]
    ww, wh = working_size(w, h, working_width)
    if (ww, wh) != (w, h):
        image = cv2.resize(image, (ww, wh), interpolation=cv2.INTER_AREA)
    dst = out_dir / IMAGE_DIR / frame.name
    write_image(dst, image, where)
    if depth is not None and depth.shape[:2] != (wh, ww):
        depth = cv2.resize(depth, (ww, wh), interpolation=cv2.INTER_NEAREST)
    digest = hashlib.sha1(image.tobytes()).hexdigest() if frame.split == "train" else None
    return (replace(frame, image_path=dst, camera=camera.scaled(ww, wh), depth_path=None),
            None if depth is None else PackedDepth.of(depth), digest)


def _write_prepared(scene: Scene, out_dir: Path, working_width: int, undistort_fov: str,
                    where: str | None = None, threads: int = -1) -> dict:
    """Undistort, resize and write every image (`threads` photos side by side; -1: every core this
    process may use; the same files for any count), then scene.h5 (poses, cameras, depth). `where`:
    how a failed write names `out_dir` (default: its artifact folder)."""
    scene.split("train")
    scene.split("test")
    check_cameras(scene.frames, undistort_fov)
    out_frames: list[Frame] = []
    depths: list[PackedDepth | None] = []
    contents: dict[str, list[str]] = {}  # pixel hash -> mapping images with exactly these pixels
    workers = min(threads if threads > 0 else cores_available(), len(scene.frames))
    with library_threads(cv2.getNumThreads, cv2.setNumThreads, 1 if workers > 1 else cv2.getNumThreads()):
        done = ordered_map(lambda f: _prepared_image(f, out_dir, working_width, undistort_fov, where),
                           scene.frames, workers, name="usvc-prepare")
        for frame, (out_frame, depth, digest) in tqdm(done, total=len(scene.frames), desc=f"prepare {scene.name}",
                                                      unit="img"):
            depths.append(depth)
            out_frames.append(out_frame)
            if digest is not None:
                contents.setdefault(digest, []).append(frame.name)
    check_distinct_mapping_images(scene.name, contents)
    prepared = Scene(scene.name, out_frames, scene.metric_scale, out_dir, pose_source=scene.pose_source)
    try:
        write_scene_h5(out_dir / SCENE_H5, prepared, depths, source_cameras=[f.camera for f in scene.frames])
    except WriteError as exc:
        if where is None:
            raise
        raise WriteError(out_dir / SCENE_H5, exc.error, where=where) from None
    n_train = len(prepared.split("train"))
    stats = {
        "frames": len(out_frames),
        "train": n_train,
        "test": len(out_frames) - n_train,
        "width": out_frames[0].camera.width,
        "height": out_frames[0].camera.height,
        "has_depth": any(d is not None for d in depths),
        "undistorted": sum(f.camera.has_distortion for f in scene.frames),
        "source_camera_models": sorted({f.camera.model for f in scene.frames}),
        "undistort_fov": undistort_fov,
    }
    log.info("prepared %s: %s", scene.name, stats)
    return stats


def _prepare_unposed(scene: Scene, out_dir: Path, working_width: int, undistort_fov: str,
                     sfm: SfmOptions | None, threads: int) -> dict:
    if sfm is None:
        raise SceneError(f"scene {scene.name!r} has no poses: preparing it needs SfM options")
    with tempfile.TemporaryDirectory(prefix="usvc-posing-") as work:
        resized_dir = Path(work) / "resized"
        resized_dir.mkdir()
        # Its files are gone when the error is read: name the folder that is full, not them.
        where = f"{tempfile.gettempdir()} (the temporary folder SfM poses the photos in; TMPDIR sets it)"
        _write_prepared(scene, resized_dir, working_width, undistort_fov, where, threads)
        resized = read_scene_h5(resized_dir / SCENE_H5)
        # SfM calibrates the importer's camera model (SIMPLE_RADIAL): keep it, at working size
        source = {f.name: f for f in scene.frames}
        resized = replace(resized, frames=[
            replace(f, camera=source[f.name].camera.scaled(f.camera.width, f.camera.height),
                    focal_known=source[f.name].focal_known) for f in resized.frames])
        posed, missing = pose_scene(resized, resized_dir / IMAGE_DIR, Path(work), sfm, threads)
        stats = _write_prepared(posed, out_dir, 0, undistort_fov, threads=threads)
    cams = sorted({f.camera for f in posed.frames}, key=lambda c: c.params)
    return {**stats, "pose_source": "sfm", "unposed": missing, "photos": len(scene.frames),
            "sfm_cameras": [{"model": c.model, "params": [round(v, 6) for v in c.params]} for c in cams]}
