"""Training buffer: sampled cells carry the encoder's feature and a camera that sees them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from usvc.errors import UsvcError
from usvc.importers import load_scene
from usvc.model.encoder import Encoder
from usvc.model.preprocess import normalise
from usvc.prepare import prepare_scene
from usvc.scene import Camera, Frame
from usvc.scene_io import read_scene_h5
from usvc.synth.params import RoomParams
from usvc.synth.writer import generate_scene
from usvc.training.augment import warp_view
from usvc.training.buffer import BufferOptions, fill_buffer, read_buffer, write_buffer


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("buf")
    generate_scene(root / "raw", RoomParams(frames_per_map_sequence=3, n_map_sequences=1, n_query_frames=1,
                                            supersample=1))
    prepared = root / "prepared"
    prepared.mkdir()
    prepare_scene(load_scene("ace", root / "raw", "mini", "given"), prepared, working_width=0)
    return prepared


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return Encoder(width=0.25)


OPTS = BufferOptions(size=1000, samples_per_image=150, short_side=240, seed=3)


def test_buffer_size_views_and_determinism(scene, encoder, tmp_path):
    frames = read_scene_h5(scene).split("train")
    a = fill_buffer(frames, encoder, OPTS)
    assert a.features.shape == (1000, encoder.out_channels) and a.features.dtype == np.float16
    assert len(a.view_image) == 7  # ceil(1000 / 150) augmented views over 3 images
    assert set(a.view_image.tolist()) == {0, 1, 2}
    write_buffer(tmp_path / "b.h5", a)
    b = read_buffer(tmp_path / "b.h5")
    np.testing.assert_array_equal(a.features, b.features)
    c = fill_buffer(frames, encoder, OPTS)
    np.testing.assert_array_equal(a.features, c.features)
    np.testing.assert_array_equal(a.view_R, c.view_R)


def test_cells_lie_inside_the_source_view_seen_from_the_same_centre(scene, encoder):
    """Augmented cameras keep the source camera's centre, and every sampled cell's ray, carried
    back into the source camera, lands inside the source image (padding is never sampled)."""
    frames = read_scene_h5(scene).split("train")
    buf = fill_buffer(frames, encoder, OPTS)
    for v in range(len(buf.view_image)):
        frame = frames[buf.view_image[v]]
        K, R, t = (buf.view_K[v].astype(np.float64), buf.view_R[v].astype(np.float64),
                   buf.view_t[v].astype(np.float64))
        np.testing.assert_allclose(-R.T @ t, frame.center, atol=1e-4)
        sel = buf.view_index == v
        rays = np.linalg.inv(K) @ np.c_[buf.pixels[sel], np.ones(sel.sum())].T
        uv = frame.camera.K @ (frame.R @ (R.T @ rays))
        uv = (uv[:2] / uv[2]).T
        assert (uv >= 0).all() and (uv[:, 0] <= frame.camera.width).all() and (uv[:, 1] <= frame.camera.height).all()


def test_features_are_the_encoders_at_the_cell(scene, encoder):
    frames = read_scene_h5(scene).split("train")
    opts = BufferOptions(size=150, samples_per_image=150, short_side=240, scale_min=1.0, scale_max=1.0,
                         max_rotation_deg=0.0, brightness=(1.0, 1.0), contrast=(1.0, 1.0), seed=1)
    buf = fill_buffer(frames, encoder, opts)
    frame = frames[buf.view_image[0]]
    import cv2

    from usvc.model.preprocess import luma01

    gray = luma01(cv2.imread(str(frame.image_path)), rgb=False)
    view = warp_view(gray, frame.camera.K, frame.R, frame.t, short_side=240)
    with torch.inference_mode():
        out = encoder(normalise(view.image))[0].numpy()
    cols = ((buf.pixels[:, 0] - 4.5) / 8).astype(int)
    rows = ((buf.pixels[:, 1] - 4.5) / 8).astype(int)
    np.testing.assert_allclose(buf.features.astype(np.float32), out[:, rows, cols].T.astype(np.float16), rtol=0, atol=0)


def test_distorted_camera_is_rejected(encoder, tmp_path):
    cam = Camera("OPENCV", 64, 48, (50, 50, 32, 24, 0.1, 0, 0, 0))
    frame = Frame("a.png", tmp_path / "a.png", cam, "train", np.eye(3), np.zeros(3))
    with pytest.raises(UsvcError, match="a.png.*pinhole"):
        fill_buffer([frame], encoder, OPTS)
