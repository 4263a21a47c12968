"""One artifact contract: every artifact file name is spelled once (usvc.core.artifact_names), readers
take the file's path, and tracks.h5 carries the median scene depth that every later step uses."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import tracks_of
from scipy.spatial.transform import Rotation

from usvc.core import artifact_names
from usvc.core.errors import UsvcError
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import read_scene_h5, write_scene_h5
from usvc.sfm.tracks_file import MEDIAN_DEPTH_ATTR, median_scene_depth, read_median_depth, read_tracks, write_tracks

ROOT = Path(__file__).resolve().parents[1]
NAMES = {value: name for name, value in vars(artifact_names).items() if name.isupper()}


def _random_tracks(seed: int = 0, points: int = 200, cameras: int = 5):
    """Cameras around the origin looking at a cloud of points, tracks of 2-4 observations."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(cameras, random_state=seed).as_matrix()
    t = np.column_stack([rng.normal(0, 0.3, (cameras, 2)), rng.uniform(3.0, 6.0, cameras)])
    xyz = rng.normal(0, 1.0, (points, 3))
    length = rng.integers(2, 5, points)
    offset = np.concatenate([[0], np.cumsum(length)])
    obs_image = np.concatenate([rng.choice(cameras, k, replace=False) for k in length])
    return tracks_of(R, t, xyz, offset, obs_image)


def test_tracks_h5_stores_the_median_depth_as_computed(tmp_path):
    tracks = _random_tracks()
    path = tmp_path / artifact_names.TRACKS_H5
    write_tracks(path, tracks)
    expected = median_scene_depth(tracks)
    with h5py.File(path, "r") as h5:
        stored = h5.attrs[MEDIAN_DEPTH_ATTR]
    assert stored.dtype == np.float64 and float(stored) == expected  # the same float, not merely close
    assert read_median_depth(path) == expected == median_scene_depth(read_tracks(path))


def test_a_tracks_h5_written_before_the_attribute_reads_the_same_depth(tmp_path):
    path = tmp_path / artifact_names.TRACKS_H5
    write_tracks(path, _random_tracks(seed=3))
    with_attribute = read_median_depth(path)
    with h5py.File(path, "r+") as h5:
        del h5.attrs[MEDIAN_DEPTH_ATTR]
    assert read_median_depth(path) == with_attribute


def test_tracks_without_a_depth_are_written_and_reading_their_depth_fails(tmp_path):
    # the only observation is behind its camera: no median depth, but the tracks are still valid
    tracks = tracks_of([np.eye(3)], [[0.0, 0.0, 0.0]], [[0.0, 0.0, -1.0]], offset=[0, 1], obs_image=[0])
    path = tmp_path / artifact_names.TRACKS_H5
    write_tracks(path, tracks)
    with h5py.File(path, "r") as h5:
        assert MEDIAN_DEPTH_ATTR not in h5.attrs
    with pytest.raises(UsvcError, match="positive depth"):
        read_median_depth(path)
    with pytest.raises(UsvcError, match="run the sfm stage"):
        read_median_depth(tmp_path / "missing" / artifact_names.TRACKS_H5)


def test_the_scene_reader_takes_the_file_and_finds_the_images_beside_it(tmp_path):
    cam = Camera("PINHOLE", 8, 6, (10.0, 10.0, 4.0, 3.0))
    path = tmp_path / "prepared" / artifact_names.SCENE_H5
    path.parent.mkdir()
    write_scene_h5(path, Scene("s", [Frame("a.png", Path("a.png"), cam, "train", np.eye(3), np.zeros(3))]))
    scene = read_scene_h5(path)
    assert scene.root == path.parent and scene.frames[0].image_path == path.parent / "images" / "a.png"
    with pytest.raises(UsvcError, match="is a folder"):
        read_scene_h5(path.parent)


def _file_name_literals(path: Path) -> list[tuple[int, str]]:
    """String constants that are exactly an artifact file name (docstrings and comments mention
    names in prose; a literal standing alone is a second spelling)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in NAMES]


def test_every_artifact_file_name_is_spelled_once():
    found = []
    for folder in ("usvc", "stages", "tools", "benchmarks"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path == ROOT / "usvc" / "core" / "artifact_names.py":
                continue
            found += [f"{path.relative_to(ROOT)}:{line}: {value!r} (use {NAMES[value]})"
                      for line, value in _file_name_literals(path)]
    assert found == [], "\n".join(found)


def test_the_literal_finder_sees_a_second_spelling(tmp_path):
    module = tmp_path / "m.py"
    module.write_text('"""Writes tracks.h5."""\nPATH = "sfm/" + "tracks.h5"\n')
    assert _file_name_literals(module) == [(2, "tracks.h5")]


def test_the_paths_module_names_files_without_loading_the_libraries():
    code = ("import sys; import usvc.pipeline.paths as p; from usvc.core import artifact_names as a; "
            "assert p.TRACKS_H5 is a.TRACKS_H5 and p.MAP_PT is a.MAP_PT; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'h5py', 'pycolmap', 'cv2')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
