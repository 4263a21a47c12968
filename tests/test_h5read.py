"""Corrupt, truncated or incomplete HDF5 artifacts: one error naming the file, never an h5py traceback."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from usvc.buffer.buffer_file import read_buffer, read_buffer_attrs
from usvc.core.errors import UsvcError
from usvc.core.scene_file import read_scene_h5
from usvc.keypoints.keypoints_file import read_scene_keypoints
from usvc.sfm.tracks_file import read_tracks

READERS = [
    (lambda d: read_scene_h5(d / "scene.h5"), "scene.h5", "prepared scene"),
    (lambda d: read_tracks(d / "tracks.h5"), "tracks.h5", "SfM tracks"),
    (lambda d: read_buffer(d / "buffer.h5"), "buffer.h5", "training buffer"),
    (lambda d: read_buffer_attrs(d / "buffer.h5"), "buffer.h5", "training buffer"),
    (lambda d: read_scene_keypoints(d / "keypoints.h5"), "keypoints.h5", "keypoints"),
]


@pytest.mark.parametrize("read, name, what", READERS)
@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty_hdf5"])
def test_damaged_artifact_is_one_error_naming_it(tmp_path, read, name, what, damage):
    path = tmp_path / name
    if damage == "garbage":
        path.write_bytes(b"this is not an HDF5 file" * 100)
    else:
        with h5py.File(path, "w") as h5:
            h5.create_dataset("something_else", data=np.arange(100000))
        if damage == "truncated":
            path.write_bytes(path.read_bytes()[:3000])
    with pytest.raises(UsvcError) as info:
        read(tmp_path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    if damage == "empty_hdf5":
        assert f"{what} is incomplete or corrupt" in message or "not found" not in message
    else:
        assert f"cannot read {what}" in message
