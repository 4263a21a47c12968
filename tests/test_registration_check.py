"""SfM's symmetry ambiguity (doppelgangers): a capture orbiting a can whose label repeats under a
half turn, inside a room that does not. The COLMAP database holds what matching and verification
would: photos next to each other share the can's and the walls' points; photos from opposite
sides share only the label, matched to its look-alike half (the twin points), and those matches
are what verification keeps for them. A run of photos registered on the wrong side (turned by half
a turn about the can's axis, as incremental SfM places them from the label's matches) must be
refused naming its photos; the right poses must pass although the look-alike pairs disagree with them.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from usvc.core.errors import SfmError
from usvc.core.scene import Camera, Frame
from usvc.sfm.registration_check import check_registration, registration_report
from usvc.sfm.reconstruction import register_images

CAM = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
N_PHOTOS = 24
HALF_TURN = Rotation.from_rotvec([0.0, 0.0, np.pi]).as_matrix()  # about the can's (vertical) axis


def look_at(center: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = (target - center) / np.linalg.norm(target - center)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in the world (OpenCV: x right, y down, z ahead)
    return R, -R @ center


def orbit() -> list[Frame]:
    frames = []
    for k in range(N_PHOTOS):
        a = 2 * np.pi * k / N_PHOTOS
        R, t = look_at(np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 0.4]), np.zeros(3))
        frames.append(Frame(f"IMG_{k:03d}.jpg", Path(f"IMG_{k:03d}.jpg"), CAM, "train", R, t))
    return frames


def scene_points(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xyz, outward normal or 0 for walls, twin index or -1): the label's points come in pairs half a
    turn apart (twins), the walls' are unique."""
    phi = rng.uniform(0, np.pi, 300)
    z = rng.uniform(-0.5, 0.5, 300)
    half = np.c_[0.5 * np.cos(phi), 0.5 * np.sin(phi), z]
    label = np.r_[half, half @ HALF_TURN.T]
    twin = np.r_[np.arange(300, 600), np.arange(300)]
    normal = label * [1, 1, 0] / 0.5
    psi = rng.uniform(0, 2 * np.pi, 3000)
    walls = np.c_[6.0 * np.cos(psi), 6.0 * np.sin(psi), rng.uniform(-1.5, 2.5, 3000)]
    return (np.r_[label, walls], np.r_[normal, np.zeros_like(walls)],
            np.r_[twin, np.full(len(walls), -1)])


def capture_database(tmp: Path, seed: int = 0) -> tuple[Path, list[Frame]]:
    rng = np.random.default_rng(seed)
    frames = orbit()
    xyz, normal, twin = scene_points(rng)
    db_path = tmp / "database.db"
    register_images(frames, db_path)
    db = pycolmap.Database.open(db_path)
    seen: list[dict[int, int]] = []  # per photo: point -> keypoint row
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for f in frames:
            x = xyz @ f.R.T + f.t
            uv = x[:, :2] / x[:, 2:] * 500.0 + [320.0, 240.0]
            center = -f.R.T @ f.t
            facing = (np.einsum("ij,ij->i", normal, center - xyz) > 0) | (np.abs(normal).sum(1) == 0)
            ok = (x[:, 2] > 0.1) & facing & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
            pts = np.flatnonzero(ok)
            db.write_keypoints(ids[f.name], (uv[pts] + rng.normal(0, 0.5, (len(pts), 2))).astype(np.float32))
            seen.append({int(p): k for k, p in enumerate(pts)})
        for i in range(len(frames)):
            for j in range(i + 1, len(frames)):
                true = [(seen[i][p], seen[j][p]) for p in seen[i] if p in seen[j]]
                alike = [(seen[i][p], seen[j][twin[p]]) for p in seen[i] if twin[p] >= 0 and twin[p] in seen[j]]
                inliers = max(true, alike, key=len)  # what verification keeps: the larger consistent set
                if len(inliers) < 15:
                    continue
                geometry = pycolmap.TwoViewGeometry()
                geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                geometry.inlier_matches = np.array(inliers, dtype=np.uint32)
                db.write_two_view_geometry(ids[frames[i].name], ids[frames[j].name], geometry)
    finally:
        db.close()
    return db_path, frames


def flipped(frames: list[Frame], run: range) -> list[Frame]:
    """The run registered on the wrong side: each photo's pose turned by half a turn about the axis."""
    return [replace(f, R=f.R @ HALF_TURN.T) if k in run else f for k, f in enumerate(frames)]


def test_right_poses_pass_though_the_look_alike_pairs_disagree(tmp_path: Path) -> None:
    db, frames = capture_database(tmp_path)
    report = check_registration(db, frames, "can")
    assert report["pairs_disagreeing"] > 0, "the look-alike pairs disagree with the right poses"
    assert report["contradicted_pairs"] == [] and report["contradicted_photos"] == []


@pytest.mark.parametrize("run", [range(5, 11), range(14, 21)])
def test_a_run_registered_on_the_wrong_side_is_refused_naming_its_photos(tmp_path: Path, run: range) -> None:
    db, frames = capture_database(tmp_path)
    wrong = flipped(frames, run)
    report = registration_report(db, wrong)
    in_run = {f"IMG_{k:03d}.jpg" for k in run}
    strongest = report["contradicted_pairs"][0]  # next photos in the capture, across the run's border
    assert (strongest[0] in in_run) != (strongest[1] in in_run)
    assert set(report["contradicted_photos"]) == in_run, "the photos named are the run's"
    with pytest.raises(SfmError, match=r"scene 'can': SfM posed the photos inconsistently: .* IMG_0\d\d\.jpg and "
                                       r"IMG_0\d\d\.jpg \(\d+ verified matches, .*give the capture's poses") as err:
        check_registration(db, wrong, "can")
    assert "\n" not in str(err.value)
