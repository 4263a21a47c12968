"""Training buffer: sampled cells carry the encoder's feature and a camera that sees them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from usvc.buffer.augment import warp_view
from usvc.buffer.buffer_file import read_buffer, read_buffer_image_names, write_buffer
from usvc.buffer.build import BufferOptions, fill_buffer, fill_heldout, holdout_split, working_short_side
from usvc.core.errors import UsvcError
from usvc.core.scene import Camera, Frame
from usvc.core.scene_file import read_scene_h5
from usvc.generate.params import RoomParams
from usvc.generate.writer import generate_scene
from usvc.model.encoder import Encoder
from usvc.model.preprocess import normalise
from usvc.prepare.importers import load_scene
from usvc.prepare.working_images import prepare_scene

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both


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


OPTS = BufferOptions(size=1000, samples_per_image=150)
SHORT_SIDE, SEED = 240, 3


def test_buffer_size_views_and_determinism(scene, encoder, tmp_path):
    frames = read_scene_h5(scene / "scene.h5").split("train")
    a = fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED)
    assert a.features.shape == (1000, encoder.out_channels) and a.features.dtype == np.float16
    assert len(a.view_image) == 7  # ceil(1000 / 150) augmented views over 3 images
    assert set(a.view_image.tolist()) == {0, 1, 2}
    write_buffer(tmp_path / "b.h5", a)
    b = read_buffer(tmp_path / "b.h5")
    np.testing.assert_array_equal(a.features, b.features)
    assert read_buffer_image_names(tmp_path / "b.h5") == a.image_names == [f.name for f in frames]
    c = fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED)
    np.testing.assert_array_equal(a.features, c.features)
    np.testing.assert_array_equal(a.view_R_world_to_cam, c.view_R_world_to_cam)


def test_cells_lie_inside_the_source_view_seen_from_the_same_centre(scene, encoder):
    """Augmented cameras keep the source camera's centre, and every sampled cell's ray, carried
    back into the source camera, lands inside the source image (padding is never sampled)."""
    frames = read_scene_h5(scene / "scene.h5").split("train")
    buf = fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED)
    for v in range(len(buf.view_image)):
        frame = frames[buf.view_image[v]]
        K, R, t = (buf.view_K[v].astype(np.float64), buf.view_R_world_to_cam[v].astype(np.float64),
                   buf.view_t_world_to_cam[v].astype(np.float64))
        np.testing.assert_allclose(-R.T @ t, frame.center, atol=1e-4)
        sel = buf.view_index == v
        rays = np.linalg.inv(K) @ np.c_[buf.pixels[sel], np.ones(sel.sum())].T
        uv = frame.camera.K @ (frame.R @ (R.T @ rays))
        uv = (uv[:2] / uv[2]).T
        assert (uv >= 0).all() and (uv[:, 0] <= frame.camera.width).all() and (uv[:, 1] <= frame.camera.height).all()


def test_features_are_the_encoders_at_the_cell(scene, encoder):
    frames = read_scene_h5(scene / "scene.h5").split("train")
    # fp32 pinned: the reference below is an fp32 forward pass, compared bit for bit (`auto` is bf16
    # on CPUs with native bf16, whose features differ from fp32's in the last bits)
    opts = BufferOptions(size=150, samples_per_image=150, scale_min=1.0, scale_max=1.0, max_rotation_deg=0.0,
                         brightness_min=1.0, brightness_max=1.0, contrast_min=1.0, contrast_max=1.0,
                         precision="fp32")
    buf = fill_buffer(frames, encoder, opts, 240, seed=1)
    frame = frames[buf.view_image[0]]
    import cv2

    from usvc.model.preprocess import luma01

    gray = luma01(cv2.imread(str(frame.image_path)), rgb=False)
    view = warp_view(gray, frame.camera.K, frame.R, frame.t, short_side=240)
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the buffer's passes run on one thread each on a CPU (encoder_workers)
    try:
        with torch.inference_mode():
            out = encoder(normalise(view.image))[0].numpy()
    finally:
        torch.set_num_threads(before)
    cols = ((buf.pixels[:, 0] - 4.5) / 8).astype(int)
    rows = ((buf.pixels[:, 1] - 4.5) / 8).astype(int)
    np.testing.assert_allclose(buf.features.astype(np.float32), out[:, rows, cols].T.astype(np.float16), rtol=0, atol=0)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_buffer_is_the_same_for_any_thread_count(scene, encoder, threads):
    """Views are encoded side by side, one torch thread each, in the views' order: the buffer's bits
    do not depend on the thread count, and torch's count is put back afterwards."""
    frames = read_scene_h5(scene / "scene.h5").split("train")
    opts = replace(OPTS, size=1200, samples_per_image=150, precision="fp32")
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        reference = fill_buffer(frames, encoder, opts, SHORT_SIDE, seed=SEED)
        torch.set_num_threads(threads)
        buf = fill_buffer(frames, encoder, opts, SHORT_SIDE, seed=SEED)
        assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(before)
    assert len(buf.view_image) == 8
    for name in ("features", "pixels", "view_index", "view_image", "view_R_world_to_cam", "view_t_world_to_cam",
                 "view_K"):
        np.testing.assert_array_equal(getattr(buf, name), getattr(reference, name), err_msg=name)


def test_distorted_camera_is_rejected(encoder, tmp_path):
    cam = Camera("OPENCV", 64, 48, (50, 50, 32, 24, 0.1, 0, 0, 0))
    frame = Frame("a.png", tmp_path / "a.png", cam, "train", np.eye(3), np.zeros(3))
    with pytest.raises(UsvcError, match="a.png.*pinhole"):
        fill_buffer([frame], encoder, OPTS, SHORT_SIDE, seed=SEED)


# --- keypoint tuples (k, d_k, R_i, t_i, u_obs) -------------------------------------------------

def _keypoints_on_surface(prepared, frames, n=60, seed=0):
    """Surface points back-projected from frame 0's depth: frame 0 observes them in its 'track';
    the other frames can only see them through depth visibility. Plus points hidden behind walls."""
    from usvc.core.scene_file import read_depth
    from usvc.keypoints.keypoints_file import SceneKeypoints

    rng = np.random.default_rng(seed)
    f0 = frames[0]
    depth = read_depth(prepared / "scene.h5", 0)
    h, w = depth.shape
    uv = np.stack([rng.uniform(20, w - 20, n), rng.uniform(20, h - 20, n)], axis=1)
    d = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    rays = np.concatenate([uv, np.ones((n, 1))], axis=1) @ np.linalg.inv(f0.camera.K).T
    xyz = ((rays * d[:, None]) - f0.t) @ f0.R  # camera -> world
    hidden = ((rays * 1.6 * d[:, None]) - f0.t) @ f0.R  # behind the visible surface
    by_image = {f0.name: (np.arange(n), uv)}
    return SceneKeypoints(xyz=np.concatenate([xyz, hidden]), by_image=by_image), n


def test_keypoint_tuples_project_exactly_and_depth_decides_visibility(scene, encoder, tmp_path):
    from usvc.core.scene_file import DepthMaps, read_depth

    frames = read_scene_h5(scene / "scene.h5").split("train")
    kp, n = _keypoints_on_surface(scene, frames)
    depths = [read_depth(scene / "scene.h5", i) for i in range(len(frames))]
    with DepthMaps(scene / "scene.h5", [*range(len(frames)), 10**6], extra=2) as lazy:  # one opening, read when asked for; no such frame: None
        assert len(lazy) == len(frames) + 3 and lazy.any() and lazy[len(frames)] is None and lazy[-1] is None
        assert all(np.array_equal(lazy[i], d) for i, d in enumerate(depths))
    assert lazy._h5 is None  # closed with the block
    buf = fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED, keypoints=kp, depths=depths)
    plain = fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED)
    np.testing.assert_array_equal(buf.features, plain.features)  # keypoints do not disturb pixel sampling
    assert buf.has_keypoints and np.all(np.diff(buf.kp_id) >= 0)
    X = kp.xyz[buf.kp_id]
    v = buf.kp_view
    p = np.einsum("nij,nj->ni", buf.view_R_world_to_cam[v], X) + buf.view_t_world_to_cam[v]
    proj = np.einsum("nij,nj->ni", buf.view_K[v], p)
    err = np.linalg.norm(proj[:, :2] / proj[:, 2:] - buf.kp_pixels, axis=1)
    assert err.max() < 0.05, err.max()
    # track observations only in frame 0; frames 1, 2 see the surface points through depth
    source = buf.view_image[v]
    assert not buf.kp_from_depth[source == 0].any()
    assert buf.kp_from_depth[source != 0].all() and (source != 0).any()
    # points hidden behind the surface are never observed: not in a track, and depth disagrees
    assert buf.kp_id.max() < n
    write_buffer(tmp_path / "kp.h5", buf)
    back = read_buffer(tmp_path / "kp.h5")
    for name in ("kp_id", "kp_features", "kp_pixels", "kp_view", "kp_from_depth", "keypoint_xyz"):
        np.testing.assert_array_equal(getattr(back, name), getattr(buf, name), err_msg=name)


def test_without_depth_only_track_observations_are_used(scene, encoder):
    frames = read_scene_h5(scene / "scene.h5").split("train")
    kp, _ = _keypoints_on_surface(scene, frames)
    buf = fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED, keypoints=kp)
    assert set(buf.view_image[buf.kp_view].tolist()) == {0} and not buf.kp_from_depth.any()


def test_keypoint_feature_is_the_cell_feature_at_a_cell_centre():
    from usvc.buffer.keypoint_obs import sample_features

    fmap = torch.randn(16, 5, 7)
    pixels = np.array([[8 * 3 + 4.5, 8 * 2 + 4.5], [4.5, 4.5]], dtype=np.float32)  # cells (2, 3), (0, 0)
    out = sample_features(fmap, pixels)
    torch.testing.assert_close(out[0], fmap[:, 2, 3])
    torch.testing.assert_close(out[1], fmap[:, 0, 0])
    mid = sample_features(fmap, np.array([[8.5, 4.5]], dtype=np.float32))[0]  # halfway between (0,0) and (0,1)
    torch.testing.assert_close(mid, (fmap[:, 0, 0] + fmap[:, 0, 1]) / 2)


def test_heldout_cells_are_one_unaugmented_view_per_withheld_image(scene, encoder):
    frames = read_scene_h5(scene / "scene.h5").split("train")
    _, held = holdout_split(frames, 2)
    buf = fill_heldout(held, encoder, OPTS, SHORT_SIDE, seed=SEED)
    assert buf.image_names == [f.name for f in held] and not buf.has_keypoints
    assert sorted(buf.view_image.tolist()) == list(range(len(held)))
    assert len(buf.features) == len(held) * OPTS.samples_per_image
    for v, i in enumerate(buf.view_image):  # the source pose, no roll; intrinsics only rescaled
        np.testing.assert_allclose(buf.view_R_world_to_cam[v], held[i].R, atol=1e-6)
        scale = SHORT_SIDE / min(held[i].camera.width, held[i].camera.height)
        np.testing.assert_allclose(buf.view_K[v][0, 0], held[i].camera.K[0, 0] * scale, rtol=1e-3)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_buffer_features_at_a_precision_repeat_and_bf16_stays_close(scene, encoder, precision):
    frames = read_scene_h5(scene / "scene.h5").split("train")[:1]
    opts = BufferOptions(size=150, samples_per_image=150, precision=precision)
    a = fill_buffer(frames, encoder, opts, SHORT_SIDE, seed=SEED)
    b = fill_buffer(frames, encoder, opts, SHORT_SIDE, seed=SEED)
    np.testing.assert_array_equal(a.features, b.features)
    ref = fill_buffer(frames, encoder, BufferOptions(size=150, samples_per_image=150, precision="fp32"),
                      SHORT_SIDE, seed=SEED).features.astype(np.float32)
    rel = np.abs(a.features.astype(np.float32) - ref).max() / np.abs(ref).max()
    assert rel < 0.05, rel  # bf16 keeps 8 bits of mantissa over the encoder's layers


def test_holdout_split_withholds_every_kth_mapping_image():
    frames = [Frame(name=f"{i:02d}.png", image_path=None, camera=Camera("PINHOLE", 8, 8, (8.0, 8.0, 4.0, 4.0)),
                    split="train", R=np.eye(3), t=np.zeros(3)) for i in range(10)]
    train, held = holdout_split(frames, 4)
    assert [f.name for f in held] == ["02.png", "06.png"]
    assert len(train) == 8 and not {f.name for f in train} & {f.name for f in held}
    assert holdout_split(frames, 0) == (frames, [])
    for bad in (1, -2):
        with pytest.raises(UsvcError, match="buffer.holdout_every"):
            holdout_split(frames, bad)


def test_working_short_side_scales_large_images_down_and_never_up():
    # the prepared images' short side, capped by the encoder's pretraining scale
    assert working_short_side(544, 0, 240) == 240
    assert working_short_side(240, 0, 240) == 240
    assert working_short_side(180, 0, 240) == 180  # smaller images keep their size
    assert working_short_side(544, 0, 0) == 544  # 0 = no limit
    # an explicit buffer.short_side wins, upscaling included
    assert working_short_side(544, 360, 240) == 360
    assert working_short_side(180, 300, 240) == 300


def test_training_refuses_a_buffer_of_another_encoder(scene, encoder, tmp_path, caplog):
    """The buffer records its encoder's fingerprint; a different configured encoder is refused at once."""
    from pathlib import Path

    from usvc.buffer.buffer_file import check_buffer_encoder, read_buffer_attrs
    from usvc.model.encoder import encoder_fingerprint

    frames = read_scene_h5(scene / "scene.h5").split("train")
    path = tmp_path / "b.h5"
    write_buffer(path, fill_buffer(frames, encoder, OPTS, SHORT_SIDE, seed=SEED), short_side=240, encoder_file="a.pt",
                 encoder_fingerprint=encoder_fingerprint(encoder))
    attrs = read_buffer_attrs(path)
    check_buffer_encoder(path, attrs, encoder, Path("a.pt"))  # the same encoder passes
    torch.manual_seed(1)
    other = Encoder(width=0.25)
    with pytest.raises(UsvcError, match=r"b.h5 holds features of encoder a.pt, but the configured encoder is b.pt"):
        check_buffer_encoder(path, attrs, other, Path("b.pt"))
    old = {k: v for k, v in attrs.items() if k != "encoder_fingerprint"}
    check_buffer_encoder(path, old, other, Path("b.pt"))  # an older buffer: a warning, not an error
    assert "records no encoder fingerprint" in caplog.text
