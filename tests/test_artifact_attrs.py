"""Every HDF5 artifact describes itself: each dataset the pipeline's writers produce carries
non-empty `units` and `description` attributes (and `frame` where one applies), and
docs/artifacts.md lists every dataset with the same dtype, units and frame."""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import REPO

from usvc.buffer.buffer_file import TrainingBuffer, write_buffer
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import write_scene_h5
from usvc.keypoints.keypoints_file import Keypoints, write_keypoints
from usvc.landmarks.landmark_table import LandmarkObservations, Landmarks, MappingKeypoints
from usvc.landmarks.landmarks_file import write_landmarks
from usvc.relocalize.pose_estimate import PoseEstimate
from usvc.relocalize.run import write_results
from usvc.render.views_file import NovelView
from usvc.render.views_file import write_rendered_views
from usvc.sfm.tracks_file import Tracks, write_tracks

DOC = REPO / "docs" / "artifacts.md"
FRAMES = {"world", "camera", "image", "world->camera", "camera->image"}
CAM = Camera("PINHOLE", 8, 6, (10.0, 10.0, 4.0, 3.0))
ROT = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _scene_h5(d: Path) -> Path:
    frames = [Frame("train/a.png", Path("a.png"), CAM, "train", ROT, np.array([0.1, 0.2, 3.0])),
              Frame("test/b.png", Path("b.png"), CAM, "test", np.eye(3), np.zeros(3))]
    source = [Camera("OPENCV", 16, 12, (20.0, 20.0, 8.0, 6.0, 0.1, 0.0, 0.0, 0.0))] * 2
    write_scene_h5(d / "scene.h5", Scene("tiny", frames, 0.5), [np.full((6, 8), 2.0, np.float32), None], source)
    return d / "scene.h5"


def _tracks() -> Tracks:
    """Three points seen by two images, with the dtypes `from_reconstruction` gives them."""
    rng = np.random.default_rng(0)
    n_obs = 6
    return Tracks(
        image_names=["train/a.png", "train/c.png"], R=np.stack([ROT, np.eye(3)]), t=np.zeros((2, 3)),
        K=np.stack([CAM.K, CAM.K]), point_id=np.array([4, 7, 9], np.int64), xyz=rng.normal(size=(3, 3)),
        rgb=np.full((3, 3), 128, np.uint8), error=np.full(3, 0.5, np.float32),
        offset=np.array([0, 2, 4, 6], np.int64), obs_image=np.array([0, 1] * 3, np.int32),
        obs_uv=rng.uniform(0, 6, size=(n_obs, 2)).astype(np.float32),
        obs_descriptor=rng.integers(0, 255, size=(n_obs, 128), dtype=np.uint8),
        obs_error=np.full(n_obs, 0.5, np.float32),
        kp_image=np.array([0, 0, 0, 0, 1, 1, 1], np.int32), kp_uv=rng.uniform(0, 6, size=(7, 2)).astype(np.float32),
        kp_descriptor=rng.integers(0, 255, size=(7, 128), dtype=np.uint8),
        kp_point=np.array([0, -1, 1, 2, 0, 1, 2], np.int64),
    )


def _tracks_h5(d: Path) -> Path:
    write_tracks(d / "tracks.h5", _tracks())
    return d / "tracks.h5"


def _keypoints_h5(d: Path) -> Path:
    kp = Keypoints(index=np.array([0, 2]), score=np.array([1.9, 0.3, 1.7]),
                   mean_descriptor=np.full((2, 128), 0.05, np.float32))
    write_keypoints(d / "keypoints.h5", kp, _tracks())
    return d / "keypoints.h5"


def _buffer_h5(d: Path) -> Path:
    buf = TrainingBuffer(
        features=np.zeros((4, 16), np.float16), pixels=np.full((4, 2), 4.5, np.float32),
        view_index=np.array([0, 0, 1, 1], np.int32), view_image=np.array([0, 1], np.int32),
        view_R_world_to_cam=np.stack([ROT, np.eye(3)]).astype(np.float32),
        view_t_world_to_cam=np.zeros((2, 3), np.float32),
        view_K=np.stack([CAM.K, CAM.K]).astype(np.float32), image_names=["train/a.png", "render/0000.png"],
        kp_id=np.array([0, 1, 1], np.int32), kp_features=np.zeros((3, 16), np.float16),
        kp_pixels=np.full((3, 2), 2.5, np.float32), kp_view=np.array([0, 0, 1], np.int32),
        kp_from_depth=np.array([False, True, False]), keypoint_xyz=np.zeros((2, 3), np.float32))
    write_buffer(d / "buffer.h5", buf, short_side=6, encoder_file="encoder.pt", encoder_fingerprint="0" * 64)
    return d / "buffer.h5"


def _render_h5(d: Path) -> Path:
    views = [NovelView(source="train/a.png", R=ROT, t=np.zeros(3), K=CAM.K, rgb=np.zeros((6, 8, 3), np.uint8),
                       depth=np.ones((6, 8), np.float32), keypoint_ids=np.array([0, 1], np.int32),
                       keypoint_uv=np.full((2, 2), 3.5, np.float32), angle_deg=5.0, translation=0.1)] * 2
    write_rendered_views(d / "render.h5", views)
    return d / "render.h5"


def _queries_h5(d: Path) -> Path:
    seconds = {"preprocess": 0.0, "network": 0.1, "pnp": 0.1, "refine": 0.0, "total": 0.2}
    nan_R, nan_t = np.full((3, 3), np.nan), np.full(3, np.nan)
    ok = PoseEstimate(True, ROT, np.ones(3), 40, 48, seconds, initial_R=ROT, initial_t=np.ones(3),
                      refine_iterations=2, refine_kept=True)
    failed = PoseEstimate(False, nan_R, nan_t, 3, 48, seconds)
    frames = [Frame(n, Path(n), CAM, "test", np.eye(3), np.zeros(3)) for n in ("test/b.png", "test/d.png")]
    write_results(d, frames, [ok, failed])
    return d / "queries.h5"


def _landmarks_h5(d: Path) -> Path:
    obs = LandmarkObservations(landmark=np.array([0, 1, 2, 3, 0, 1, 2, 3], np.int32),
                               image=np.array([0, 0, 0, 0, 1, 1, 1, 1], np.int32),
                               uv=np.full((8, 2), 2.5, np.float32), descriptor=np.zeros((8, 128), np.uint8),
                               image_names=["train/a.png", "train/c.png"], image_K=np.stack([CAM.K, CAM.K]),
                               image_size=np.array([[8, 6], [8, 6]], np.int32),
                               keypoints=MappingKeypoints(image=np.array([0, 0, 1], np.int32),
                                                          uv=np.full((3, 2), 1.5, np.float32),
                                                          descriptor=np.zeros((3, 128), np.uint8),
                                                          landmark=np.array([0, -1, 3], np.int32)))
    lm = Landmarks("scene", np.zeros((4, 3)), np.zeros((4, 128), np.uint8), np.tile([0, 0, 1.0], (4, 1)).astype(np.float32),
                   np.full(4, 5.0, np.float32), np.full(4, 2, np.int32), 6, obs)
    write_landmarks(d / "landmarks.h5", lm)
    return d / "landmarks.h5"


ARTIFACTS = {"scene.h5": _scene_h5, "tracks.h5": _tracks_h5, "keypoints.h5": _keypoints_h5,
             "buffer.h5": _buffer_h5, "render.h5": _render_h5, "queries.h5": _queries_h5,
             "landmarks.h5": _landmarks_h5}


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict[str, Path]:
    """Each HDF5 artifact as its real writer writes it, every optional dataset included."""
    return {name: make(tmp_path_factory.mktemp(name.split(".")[0])) for name, make in ARTIFACTS.items()}


def _datasets(path: Path) -> dict[str, h5py.Dataset]:
    """{path inside the file: (dtype, attrs)} of every dataset."""
    out = {}
    with h5py.File(path, "r") as h5:
        h5.visititems(lambda name, obj: out.__setitem__(name, (obj.dtype, dict(obj.attrs)))
                      if isinstance(obj, h5py.Dataset) else None)
    return out


def _doc_name(dataset: str) -> str:
    """scene.h5's numbered datasets (depth/0, depth/1, ...) are one row, depth/<i>."""
    return re.sub(r"/\d+$", "/<i>", dataset)


@pytest.mark.parametrize("artifact", list(ARTIFACTS))
def test_every_dataset_has_units_and_description(written, artifact):
    datasets = _datasets(written[artifact])
    assert datasets
    for name, (_, attrs) in datasets.items():
        for key in ("units", "description"):
            value = attrs.get(key)
            assert isinstance(value, str) and value.strip(), f"{artifact}:{name} has no {key!r} attribute"
        assert attrs.get("frame", "world") in FRAMES, f"{artifact}:{name} frame {attrs['frame']!r}"
    with h5py.File(written[artifact], "r") as h5:
        assert str(h5.attrs["format"]).startswith("usvc-") and int(h5.attrs["version"]) >= 1


def _doc_tables() -> dict[str, dict[str, dict[str, str]]]:
    """{artifact file: {dataset: row}} from the docs' dataset tables; a table belongs to the
    nearest heading above it that names an .h5 file in backticks."""
    tables: dict[str, dict[str, dict[str, str]]] = {}
    current, header = None, None
    for line in DOC.read_text().splitlines():
        if line.startswith("#"):
            m = re.search(r"`(?:[\w<>/]+/)?(\w+\.h5)`", line)
            current, header = (m.group(1) if m else None), None
            continue
        if current is None or not line.startswith("|"):
            header = None if not line.startswith("|") else header
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            header = [c.lower() for c in cells]
            continue
        if set("".join(cells)) <= set("-: "):
            continue
        row = dict(zip(header, cells))
        if "dataset" in row:
            tables.setdefault(current, {})[row["dataset"].strip("`")] = row
    return tables


def _dtype_matches(doc: str, dtype: np.dtype) -> bool:
    doc = doc.strip("`")
    if doc == "str":
        return h5py.check_string_dtype(dtype) is not None and dtype.kind == "O"
    if doc == "bytes":
        return dtype.kind == "S"
    return np.dtype(doc) == dtype


@pytest.mark.parametrize("artifact", list(ARTIFACTS))
def test_docs_list_every_dataset_as_written(written, artifact):
    text = DOC.read_text()
    rows = _doc_tables().get(artifact, {})
    assert rows, f"docs/artifacts.md has no dataset table under a heading naming `{artifact}`"
    for name, (dtype, attrs) in _datasets(written[artifact]).items():
        doc_name = _doc_name(name)
        assert f"`{doc_name}`" in text, f"docs/artifacts.md does not mention {artifact}:{doc_name}"
        assert doc_name in rows, f"{artifact}:{doc_name} is not in the {artifact} table"
        row = rows[doc_name]
        assert row["units"].strip("`") == attrs["units"], (artifact, doc_name, row["units"], attrs["units"])
        assert row["frame"].strip("`") == attrs.get("frame", "-"), (artifact, doc_name, row["frame"])
        assert _dtype_matches(row["dtype"], dtype), (artifact, doc_name, row["dtype"], dtype)
