"""The procedural room generator: layout on disk, exact geometry, trajectories, determinism."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from usvc.core.errors import UsvcError
from usvc.generate import writer
from usvc.generate.params import RoomParams, validate
from usvc.generate.room import cast, make_layout
from usvc.generate.trajectory import MIN_CLEARANCE
from usvc.generate.writer import generate_scene, intrinsics

TINY = dict(frames_per_map_sequence=3, n_query_frames=2)


def _frames(root: Path, split: str) -> list[str]:
    return sorted(p.name[: -len(".color.png")] for p in (root / split / "rgb").glob("*.color.png"))


def _pose(root: Path, split: str, stem: str) -> np.ndarray:
    return np.loadtxt(root / split / "poses" / f"{stem}.pose.txt")


def _depth_m(root: Path, split: str, stem: str) -> np.ndarray:
    return cv2.imread(str(root / split / "depth" / f"{stem}.depth.png"), cv2.IMREAD_UNCHANGED) / 1000.0


def _centres(root: Path, split: str, prefix: str = "") -> np.ndarray:
    return np.array([_pose(root, split, s)[:3, 3] for s in _frames(root, split) if s.startswith(prefix)])


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, RoomParams, dict]:
    params = RoomParams()
    root = tmp_path_factory.mktemp("synth") / "room"
    stats = generate_scene(root, params)
    return root, params, stats


def test_params_are_a_plain_structured_config() -> None:
    for field in dataclasses.fields(RoomParams):
        assert field.type in ("int", "float", "bool", "str"), field
    with pytest.raises(UsvcError, match="room"):
        validate(RoomParams(room_x=1.0))
    with pytest.raises(UsvcError, match="supersample"):
        validate(RoomParams(supersample=5))


def test_writes_the_ace_layout(scene: tuple[Path, RoomParams, dict]) -> None:
    root, params, stats = scene
    assert stats["train_frames"] == 60 and stats["test_frames"] == 20
    train, test = _frames(root, "train"), _frames(root, "test")
    assert train[0] == "seq-01-frame-000000" and train[-1] == "seq-02-frame-000029"
    assert test[0] == "seq-03-frame-000000" and len(test) == 20
    for split, stems in (("train", train), ("test", test)):
        for sub, suffix in (("depth", "depth.png"), ("poses", "pose.txt"),
                            ("calibration", "calibration.txt")):
            assert sorted(p.name for p in (root / split / sub).iterdir()) == [f"{s}.{suffix}" for s in stems]
    rgb = cv2.imread(str(root / "train" / "rgb" / f"{train[0]}.color.png"), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(root / "train" / "depth" / f"{train[0]}.depth.png"), cv2.IMREAD_UNCHANGED)
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    assert depth.shape == (240, 320) and depth.dtype == np.uint16
    pose = _pose(root, "train", train[0])
    assert pose.shape == (4, 4) and np.allclose(pose[3], [0, 0, 0, 1])
    assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6)
    assert float((root / "test" / "calibration" / f"{test[0]}.calibration.txt").read_text()) == params.focal
    record = json.loads((root / "scene.json").read_text())
    assert record["params"] == dataclasses.asdict(params) and record["counts"] == {"train": 60, "test": 20}
    assert not list(root.parent.glob(".room.tmp-*"))


def test_depth_is_positive_and_bounded(scene: tuple[Path, RoomParams, dict]) -> None:
    root, params, _ = scene
    diagonal = np.linalg.norm([params.room_x, params.room_y, params.room_z])
    for split in ("train", "test"):
        for stem in _frames(root, split)[::7]:
            depth = _depth_m(root, split, stem)
            assert np.isfinite(depth).all() and (depth > 0.05).all() and (depth < diagonal).all(), stem


def test_depth_is_exact_against_a_plane() -> None:
    """Facing a wall or the floor of an empty room head-on, z-depth is the distance to that plane."""
    params = RoomParams(n_objects=0, n_wall_objects=0)
    layout = make_layout(params)
    centre = np.array([1.2, 1.5, 1.3])
    rays = writer.pixel_rays(params.width, params.height, params.focal)
    facing_wall = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # columns: x, y, z axes
    facing_floor = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=float)
    cases = ((facing_wall, 1, params.room_x - centre[0]), (facing_floor, 4, centre[2]))
    for rotation, face_id, distance in cases:
        dirs = (rotation.astype(np.float32) @ rays.reshape(3, -1)).reshape(rays.shape)
        t, face = cast(centre, dirs, layout)
        assert (face[100:140, 140:180] == face_id).all()
        assert np.allclose(t[face == face_id], distance, atol=1e-5)


def test_sift_matches_agree_with_depth_and_poses(scene: tuple[Path, RoomParams, dict]) -> None:
    """Reprojecting frame A's keypoints through its depth and both poses lands on B's matches."""
    root, params, _ = scene
    K = intrinsics(params)
    sift, matcher = cv2.SIFT_create(), cv2.BFMatcher(cv2.NORM_L2)
    n_keypoints, n_matches, medians = [], [], []
    for split in ("train", "test"):
        stems = _frames(root, split)
        feats = {}
        for stem in stems:
            gray = cv2.imread(str(root / split / "rgb" / f"{stem}.color.png"), cv2.IMREAD_GRAYSCALE)
            kps, desc = sift.detectAndCompute(gray, None)
            feats[stem] = (np.array([k.pt for k in kps]), desc)
            n_keypoints.append(len(kps))
        for a, b in zip(stems[:-1], stems[1:]):
            if a[:6] != b[:6]:
                continue  # consecutive frames of one sequence only
            (pts_a, desc_a), (pts_b, desc_b) = feats[a], feats[b]
            pairs = [m[0] for m in matcher.knnMatch(desc_a, desc_b, k=2)
                     if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
            xa = pts_a[[m.queryIdx for m in pairs]]
            xb = pts_b[[m.trainIdx for m in pairs]]
            # OpenCV puts pixel centres at integers, COLMAP (our K) at +0.5; depth is per pixel centre.
            col = np.clip(np.rint(xa[:, 0]).astype(int), 0, params.width - 1)
            row = np.clip(np.rint(xa[:, 1]).astype(int), 0, params.height - 1)
            z = _depth_m(root, split, a)[row, col]
            cam_a = np.linalg.inv(K) @ np.vstack([xa.T + 0.5, np.ones(len(xa))]) * z
            pose_a, pose_b = _pose(root, split, a), _pose(root, split, b)
            world = pose_a[:3, :3] @ cam_a + pose_a[:3, 3:]
            cam_b = pose_b[:3, :3].T @ (world - pose_b[:3, 3:])
            proj = (K @ cam_b)[:2] / cam_b[2] - 0.5
            n_matches.append(len(pairs))
            medians.append(float(np.median(np.linalg.norm(proj.T - xb, axis=1))))
    assert np.mean(n_keypoints) > 300, np.mean(n_keypoints)
    assert np.mean(n_matches) > 100 and min(n_matches) > 30, n_matches
    assert max(medians) < 1.5, medians


def test_cameras_stay_inside_the_room_and_clear_of_boxes(scene: tuple[Path, RoomParams, dict]) -> None:
    root, params, _ = scene
    layout = make_layout(params)
    record = json.loads((root / "scene.json").read_text())
    assert np.allclose([b["lo"] for b in record["boxes"]], layout.lo)
    for split in ("train", "test"):
        for centre in _centres(root, split):
            assert (centre > 0).all() and (centre < layout.hi[0]).all()
            assert layout.clearance(centre) >= MIN_CLEARANCE


def test_query_path_runs_near_but_off_the_mapping_paths(scene: tuple[Path, RoomParams, dict]) -> None:
    root, _, _ = scene
    mapping, query = _centres(root, "train"), _centres(root, "test")
    nearest = np.linalg.norm(query[:, None] - mapping[None], axis=2).min(axis=1)
    assert (nearest > 0.05).all() and (nearest < 1.0).all(), nearest


def test_consecutive_frames_are_close(scene: tuple[Path, RoomParams, dict]) -> None:
    root, _, _ = scene
    for split in ("train", "test"):
        stems = _frames(root, split)
        for a, b in zip(stems[:-1], stems[1:]):
            if a[:6] != b[:6]:
                continue
            pa, pb = _pose(root, split, a), _pose(root, split, b)
            angle = np.degrees(np.arccos(np.clip((np.trace(pa[:3, :3].T @ pb[:3, :3]) - 1) / 2, -1, 1)))
            assert np.linalg.norm(pa[:3, 3] - pb[:3, 3]) < 0.2 and angle < 15.0, (a, b, angle)


def test_same_params_give_identical_files(tmp_path: Path) -> None:
    params = RoomParams(seed=5, **TINY)
    generate_scene(tmp_path / "a", params)
    generate_scene(tmp_path / "b", params)
    first, second = _hashes(tmp_path / "a"), _hashes(tmp_path / "b")
    assert len(first) == 4 * 8 + 1 and first == second


def test_different_seeds_give_different_scenes(tmp_path: Path) -> None:
    images = []
    for seed in (1, 2):
        generate_scene(tmp_path / f"s{seed}", RoomParams(seed=seed, **TINY))
        rgb = tmp_path / f"s{seed}" / "train" / "rgb" / "seq-01-frame-000000.color.png"
        images.append(cv2.imread(str(rgb)))
    assert np.abs(images[0].astype(int) - images[1].astype(int)).mean() > 20


def test_failure_leaves_the_previous_output_untouched(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "room"
    out.mkdir()
    (out / "marker").write_text("old")

    def explode(root: Path, *args: object) -> None:
        (root / "train").mkdir(parents=True)
        raise RuntimeError("disk full")

    monkeypatch.setattr(writer, "_write_frames", explode)
    with pytest.raises(RuntimeError, match="disk full"):
        generate_scene(out, RoomParams(**TINY))
    assert (out / "marker").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room"]
