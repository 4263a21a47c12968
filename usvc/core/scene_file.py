"""The prepared scene on disk: images at working resolution (IMAGE_DIR) beside one scene.h5 of metadata.

Every stage after `prepare` reads this, never the source format, so importers run once.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from usvc.core.errors import SceneError
from usvc.core.h5_file import Field, read_h5, write_h5
from usvc.core.scene import CAMERA_MODELS, Camera, Frame, Scene

IMAGE_DIR = "images"  # beside scene.h5
_MAX_PARAMS = max(CAMERA_MODELS.values())

SCENE_FORMAT, SCENE_VERSION = "usvc-scene", 1
_PIXELS = "pixel centres at integer+0.5 (COLMAP), x right, y down"
_PARAMS_UNITS = "px (focal lengths, principal point); 1 (distortion coefficients)"
# Every dataset of scene.h5 with its attributes; docs/artifacts.md lists the same. File attributes:
# name, metric_scale (metres per scene unit, NaN when unknown), has_poses, pose_source, format, version.
SCENE_SCHEMA: dict[str, Field] = {
    "name": Field("1", "image file name, relative to prepared/images; row i is frame i"),
    "split": Field("1", "'train' (mapping image) or 'test' (query image)"),
    "camera_model": Field("1", "COLMAP camera model of the prepared (undistorted, resized) image"),
    "camera_size": Field("px", "width, height of the prepared image", "image"),
    "camera_params": Field(_PARAMS_UNITS, "parameters of camera_model in COLMAP's order (PINHOLE: fx fy cx cy), "
                                          f"NaN-padded to 12 columns; {_PIXELS}", "image"),
    "source_camera_model": Field("1", "COLMAP camera model of the image as imported (before undistortion "
                                      "and resizing)"),
    "source_camera_size": Field("px", "width, height of the image as imported", "image"),
    "source_camera_params": Field(_PARAMS_UNITS, "parameters of source_camera_model in COLMAP's order, "
                                                 f"NaN-padded to 12 columns; {_PIXELS}", "image"),
    "R_world_to_cam": Field("1", "world-to-camera rotation: x_cam = R x_world + t, OpenCV camera axes "
                                 "(x right, y down, z forward); NaN for a frame without a pose", "world->camera"),
    "t_world_to_cam": Field("scene units", "world-to-camera translation: x_cam = R x_world + t (the world "
                                           "origin in camera coordinates); times metric_scale = metres", "camera"),
    "depth/*": Field("scene units", "depth map of frame <i> (row of name) at working resolution: z along the "
                                    "optical axis per pixel; pixels without a measurement keep the source's value "
                                    "(0 in generated scenes)", "camera"),
}


DEPTH_GZIP_LEVEL = 4  # each depth map is one chunk of HDF5's gzip filter at this level


@dataclass(frozen=True)
class PackedDepth:
    """A float32 depth map compressed as scene.h5 stores it (one gzip chunk): packed where the map is
    read, maps compress side by side and a capture's maps are held compressed until written."""

    shape: tuple[int, ...]
    data: bytes

    @classmethod
    def of(cls, depth: np.ndarray) -> PackedDepth:
        d = np.ascontiguousarray(depth, dtype=np.float32)
        return cls(d.shape, zlib.compress(d.tobytes(), DEPTH_GZIP_LEVEL))


def _write_depth(grp: h5py.Group, name: str, depth: np.ndarray | PackedDepth) -> None:
    packed = depth if isinstance(depth, PackedDepth) else PackedDepth.of(depth)
    if 0 in packed.shape:  # HDF5 chunks have no empty side
        grp.create_dataset(name, shape=packed.shape, dtype=np.float32)
        return
    ds = grp.create_dataset(name, shape=packed.shape, dtype=np.float32, chunks=packed.shape, compression="gzip",
                            compression_opts=DEPTH_GZIP_LEVEL)
    ds.id.write_direct_chunk((0,) * len(packed.shape), packed.data)


def _camera_arrays(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    params = np.full((len(cameras), _MAX_PARAMS), np.nan)
    for i, c in enumerate(cameras):
        params[i, : len(c.params)] = c.params
    models = np.array([c.model for c in cameras], dtype=object)
    return models, np.array([[c.width, c.height] for c in cameras], dtype=np.int32), params


def _cameras_from(models: list[str], sizes: np.ndarray, params: np.ndarray) -> list[Camera]:
    return [Camera(m, int(sizes[i, 0]), int(sizes[i, 1]), tuple(float(v) for v in params[i, : CAMERA_MODELS[m]]))
            for i, m in enumerate(models)]


def _strings(ds: h5py.Dataset) -> list[str]:
    return [s.decode() if isinstance(s, bytes) else s for s in ds[()]]


def write_scene_h5(path: Path, scene: Scene, depths: Sequence[np.ndarray | PackedDepth | None] | None = None,
                   source_cameras: list[Camera] | None = None) -> None:
    """Store frames, cameras and poses; images are referenced by name under IMAGE_DIR; `depths`, one
    per frame or None, as arrays or already packed.

    ``source_cameras`` are the cameras of the images as imported (before undistortion and
    resizing), one per frame: the query side can undistort new photos of the same camera.
    """
    models, sizes, params = _camera_arrays([f.camera for f in scene.frames])
    R = np.stack([f.R if f.has_pose else np.full((3, 3), np.nan) for f in scene.frames])
    t = np.stack([f.t if f.has_pose else np.full(3, np.nan) for f in scene.frames])
    with write_h5(path, SCENE_SCHEMA, SCENE_FORMAT, SCENE_VERSION) as h5:
        h5.attrs["name"] = scene.name
        h5.attrs["metric_scale"] = np.nan if scene.metric_scale is None else scene.metric_scale
        h5.attrs["has_poses"] = scene.has_poses
        h5.attrs["pose_source"] = scene.pose_source
        str_dt = h5py.string_dtype()
        h5.create_dataset("name", data=np.array([f.name for f in scene.frames], dtype=object), dtype=str_dt)
        h5.create_dataset("split", data=np.array([f.split for f in scene.frames], dtype=object), dtype=str_dt)
        h5.create_dataset("camera_model", data=models, dtype=str_dt)
        h5["camera_size"] = sizes
        h5["camera_params"] = params
        if source_cameras is not None:
            if len(source_cameras) != len(scene.frames):
                raise SceneError(f"{path}: {len(source_cameras)} source cameras for {len(scene.frames)} frames")
            s_models, s_sizes, s_params = _camera_arrays(source_cameras)
            h5.create_dataset("source_camera_model", data=s_models, dtype=str_dt)
            h5["source_camera_size"] = s_sizes
            h5["source_camera_params"] = s_params
        h5["R_world_to_cam"] = R
        h5["t_world_to_cam"] = t
        if depths is not None and any(d is not None for d in depths):
            grp = h5.create_group("depth")
            for i, d in enumerate(depths):
                if d is not None:
                    _write_depth(grp, str(i), d)


def read_scene_h5(path: Path) -> Scene:
    """Load a prepared scene from its scene.h5; image paths point into IMAGE_DIR beside it."""
    path = Path(path)
    prepared_dir = path.parent
    if path.is_dir():
        raise SceneError(f"{path} is a folder: read_scene_h5 takes the scene.h5 file in it")
    if not path.is_file():
        raise SceneError(f"prepared scene not found: {path} (run the prepare stage first)")
    with read_h5(path, "prepared scene") as h5:
        names, splits = _strings(h5["name"]), _strings(h5["split"])
        cameras = _cameras_from(_strings(h5["camera_model"]), h5["camera_size"][()], h5["camera_params"][()])
        R, t = h5["R_world_to_cam"][()], h5["t_world_to_cam"][()]
        has_poses = bool(h5.attrs["has_poses"])
        pose_source = str(h5.attrs.get("pose_source", "given"))
        scale = float(h5.attrs["metric_scale"])
        name = str(h5.attrs["name"])
    frames = []
    for i, fname in enumerate(names):
        frames.append(Frame(
            name=fname, image_path=prepared_dir / IMAGE_DIR / fname, camera=cameras[i], split=splits[i],
            R=R[i] if has_poses else None, t=t[i] if has_poses else None,
        ))
    return Scene(name=name, frames=frames, metric_scale=None if np.isnan(scale) else scale, root=prepared_dir,
                 pose_source=pose_source)


def read_depth(path: Path, index: int) -> np.ndarray | None:
    """Depth of frame `index` of scene.h5 `path` in scene units at working resolution, if the scene has depth."""
    with DepthMaps(path, [index]) as depths:
        return depths[0]


class DepthMaps(Sequence):
    """The depth maps of frames `indices` of scene.h5 `path`, each read when asked for (a capture of
    thousands of RGB-D frames holds gigabytes of them), then `extra` entries without one. The file
    is checked once, when this is made, and held open until `close` (or the `with` block ends)."""

    def __init__(self, path: Path, indices: list[int], extra: int = 0) -> None:
        self.path = Path(path)
        with read_h5(self.path, "prepared scene") as h5:
            depth = h5["depth"] if "depth" in h5 else None
            self._names = [str(i) if depth is not None and str(i) in depth else None for i in indices]
        self._names += [None] * extra
        self._h5: h5py.File | None = None

    def __len__(self) -> int:
        return len(self._names)

    def __getitem__(self, i):  # type: ignore[override]
        name = self._names[i]
        if name is None:
            return None
        if self._h5 is None:
            self._h5 = h5py.File(self.path, "r")
        try:
            return self._h5["depth"][name][()]
        except (KeyError, OSError, ValueError) as exc:
            raise SceneError(f"{self.path}: depth map of frame {name} is unreadable ({exc})") from None

    def any(self) -> bool:
        """Whether any of the frames has a depth map."""
        return any(name is not None for name in self._names)

    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def __enter__(self) -> DepthMaps:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
