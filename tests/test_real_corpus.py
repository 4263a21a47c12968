"""The real-capture pretraining corpus: SfM observations become sparse labels, held-out views stay out."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from usvc.core.errors import UsvcError
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import IMAGE_DIR, write_scene_h5
from usvc.pretrain.pretrain import PretrainOptions, contrastive_loss, pair_frames
from usvc.pretrain.real_corpus import (
    LABEL_RADIUS_PX,
    REFERENCE_DEPTH,
    real_corpus_scene,
)
from usvc.sfm.tracks_file import Tracks, write_tracks

H, W, F = 48, 64, 50.0


def _scene_dir(tmp_path, n_images: int = 5):
    """n mapping images (plus one query) looking down +z at a plane 4 units away, 3 tracks each."""
    cam = Camera("PINHOLE", W, H, (F, F, W / 2, H / 2))
    (tmp_path / "prepared" / IMAGE_DIR).mkdir(parents=True)
    (tmp_path / "sfm").mkdir()
    frames, rng = [], np.random.default_rng(0)
    for i in range(n_images + 1):
        name = f"im{i}.png"
        cv2.imwrite(str(tmp_path / "prepared" / IMAGE_DIR / name), rng.integers(0, 255, (H, W, 3), np.uint8))
        frames.append(Frame(name, tmp_path / "prepared" / IMAGE_DIR / name, cam, "test" if i == 0 else "train",
                            np.eye(3), np.array([-0.1 * i, 0.0, 0.0])))
    write_scene_h5(tmp_path / "prepared" / "scene.h5", Scene("s", frames))
    mapping = [f for f in frames if f.split == "train"]
    xyz = np.array([[0.0, 0.0, 4.0], [1.2, 0.6, 4.0], [-1.0, -0.6, 4.0]])  # >= 12 px apart
    obs_image, obs_uv = [], []
    for p in xyz:
        for m, f in enumerate(mapping):
            cam_pt = p + f.t
            obs_image.append(m)
            obs_uv.append([F * cam_pt[0] / cam_pt[2] + W / 2, F * cam_pt[1] / cam_pt[2] + H / 2])
    n, k = len(xyz), len(mapping)
    tracks = Tracks(image_names=[f.name for f in mapping], R=np.stack([f.R for f in mapping]),
                    t=np.stack([f.t for f in mapping]), K=np.stack([cam.K] * k), point_id=np.arange(n), xyz=xyz,
                    rgb=np.zeros((n, 3), np.uint8), error=np.zeros(n), offset=np.arange(0, n * k + 1, k),
                    obs_image=np.array(obs_image), obs_uv=np.array(obs_uv), obs_descriptor=np.zeros((n * k, 128), np.uint8),
                    obs_error=np.zeros(n * k))
    write_tracks(tmp_path / "sfm" / "tracks.h5", tracks)
    return tmp_path, tracks


def test_observations_label_the_pixels_around_their_keypoint_and_nothing_else(tmp_path):
    scene_dir, tracks = _scene_dir(tmp_path)
    corpus = real_corpus_scene(scene_dir)
    assert corpus.gray.shape == (5, H, W) and corpus.xyz.shape == (5, H, W, 3)
    labelled = np.isfinite(corpus.xyz[..., 0])
    side = 2 * LABEL_RADIUS_PX + 1
    assert labelled.sum() <= 5 * 3 * side * side and labelled.any()
    # every image sees point 0 at its keypoint: that pixel carries the point, rescaled so the
    # median depth (4 units) becomes the reference depth
    scale = REFERENCE_DEPTH / 4.0
    centre = tracks.xyz.mean(0)
    for m in range(5):
        u, v = np.rint(tracks.obs_uv[m] - 0.5).astype(int)  # point 0's observation in image m
        np.testing.assert_allclose(corpus.xyz[m, v, u].astype(float), (tracks.xyz[0] - centre) * scale, atol=2e-3)
    # the pairs come from images sharing tracks, never the image itself
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = pair_frames(corpus, PretrainOptions(), rng)
        assert a != b


def test_held_out_mapping_images_and_queries_never_enter_the_corpus(tmp_path):
    scene_dir, _ = _scene_dir(tmp_path, n_images=6)
    full = real_corpus_scene(scene_dir)
    held = real_corpus_scene(scene_dir, holdout_every=3)
    assert len(full.gray) == 6  # the query (split test) is not there
    assert len(held.gray) == 4  # images 1 and 4 of the six mapping images withheld


def test_the_same_track_in_two_images_is_a_positive_of_the_contrastive_loss(tmp_path):
    import torch

    scene_dir, _ = _scene_dir(tmp_path)
    corpus = real_corpus_scene(scene_dir)
    cells = lambda m: torch.from_numpy(corpus.xyz[m, 4::8, 4::8].astype(np.float32))  # noqa: E731
    feats = torch.randn(2, 16, H // 8, W // 8)
    loss = contrastive_loss(feats[0], feats[1], cells(0), cells(1), PretrainOptions())
    assert torch.isfinite(loss) and loss > 0


def test_a_scene_without_tracks_is_one_clear_error(tmp_path):
    with pytest.raises(UsvcError, match="no SfM tracks"):
        real_corpus_scene(tmp_path)


def test_fine_tuning_on_a_real_capture_starts_from_the_given_weights_and_writes_an_encoder(tmp_path):
    from usvc.model.encoder import encoder_fingerprint, load_encoder_weights
    from usvc.pretrain.pretrain import pretrain_encoder
    from usvc.weights import encoder_weights_path

    scene_dir, _ = _scene_dir(tmp_path)
    shipped = encoder_weights_path(0.5, None)
    opts = PretrainOptions(encoder_width=0.5, n_scenes=0, iterations=3, batch=2, crop_h=48, crop_w=64,
                           init_weights=str(shipped), real_scenes=str(scene_dir))
    encoder, provenance = pretrain_encoder(opts)
    assert provenance["corpus"]["rooms"] == 1 and provenance["options"]["real_scenes"] == str(scene_dir)
    assert encoder_fingerprint(encoder) != encoder_fingerprint(load_encoder_weights(shipped, 0.5))
    with pytest.raises(UsvcError, match="objective=contrastive"):
        pretrain_encoder(PretrainOptions(n_scenes=0, objective="regression", real_scenes=str(scene_dir)))
    with pytest.raises(UsvcError, match="empty"):
        pretrain_encoder(PretrainOptions(n_scenes=0))


def test_model_small_real_loads_the_shipped_real_photo_encoder(tmp_path, monkeypatch):
    import json

    from usvc.model.encoder import encoder_fingerprint
    from usvc.pipeline.config import compose_for_script
    from usvc.weights import WEIGHTS_DIR, encoder_weights_path, load_configured_encoder

    monkeypatch.chdir(tmp_path)  # a bare name resolves to the shipped file from any working directory
    cfg = compose_for_script("mini", ["model=small_real"])
    encoder, path = load_configured_encoder(cfg.model.encoder_width, cfg.model.encoder_weights, cfg.model.encoder)
    assert path == WEIGHTS_DIR / "encoder_small_real.pt"
    record = json.loads(path.with_suffix(".json").read_text())
    assert encoder_fingerprint(encoder) == record["fingerprint"] and record["options"]["init_weights"]
    # a file of that name in the working directory wins, as any explicit path does
    (tmp_path / "encoder_small_real.pt").write_bytes(b"")
    assert encoder_weights_path(0.5, "encoder_small_real.pt") == tmp_path.joinpath("encoder_small_real.pt").relative_to(tmp_path)
