"""Median scene depth from SfM tracks: the unit of the depth bounds and the relative metrics."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import tracks_of
from scipy.spatial.transform import Rotation

from usvc.core.errors import UsvcError
from usvc.sfm.tracks_file import median_scene_depth


def test_median_depth_of_known_observations():
    # camera 0 at the origin, camera 1 one unit further back (t_z = 1): depths z and z + 1
    R = np.stack([np.eye(3), np.eye(3)])
    t = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    xyz = [[0.0, 0.0, 1.0], [0.5, 0.0, 2.0], [0.0, 0.3, 4.0]]
    tr = tracks_of(R, t, xyz, offset=[0, 2, 3, 5], obs_image=[0, 1, 0, 0, 1])
    # depths: 1, 2, 2, 4, 5 -> median 2
    assert median_scene_depth(tr) == pytest.approx(2.0)


def test_median_depth_ignores_points_behind_the_camera():
    R = np.stack([np.eye(3)])
    tr = tracks_of(R, np.zeros((1, 3)), [[0, 0, -5.0], [0, 0, -4.0], [0, 0, 3.0]], [0, 1, 2, 3], [0, 0, 0])
    assert median_scene_depth(tr) == pytest.approx(3.0)


def test_median_depth_uses_rotation():
    R = Rotation.from_euler("y", 90, degrees=True).as_matrix()[None]  # camera z = -world x
    tr = tracks_of(R, np.zeros((1, 3)), [[-3.0, 0, 0]], [0, 1], [0])
    assert median_scene_depth(tr) == pytest.approx(3.0)


def test_median_depth_without_positive_depth_fails():
    tr = tracks_of(np.eye(3)[None], np.zeros((1, 3)), [[0, 0, -1.0]], [0, 1], [0])
    with pytest.raises(UsvcError, match="positive depth"):
        median_scene_depth(tr)
