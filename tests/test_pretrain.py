"""Encoder pretraining: crop targets sit under their cells, a short run learns, and the written
weight file loads strictly with the fingerprint its provenance records."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from usvc.core.errors import UsvcError
from usvc.generate.params import RoomParams, validate
from usvc.model.encoder import encoder_fingerprint, load_encoder_weights
from usvc.pretrain.encoder_file import save_encoder_weights
from usvc.pretrain.pretrain import PretrainOptions, crop_view, pretrain_encoder
from usvc.pretrain.pretrain_data import corpus_params, render_scene


@pytest.fixture(scope="module")
def room():
    return render_scene(corpus_params(1234, frames_per_scene=2))


def test_corpus_rooms_are_valid_and_differ_from_the_miniature_scene():
    for seed in range(1000, 1040):
        params = corpus_params(seed, 40)
        validate(params)
        assert params.seed != RoomParams().seed


def test_crop_targets_are_the_world_points_under_the_cell_centres(room):
    opts = PretrainOptions(scale_min=1.0, scale_max=1.0, crop_h=120, crop_w=160)
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    crop, target = crop_view(room, 0, opts, rng)
    assert crop.shape == (120, 160) and target.shape == (15, 20, 3)
    # replay the draws: scale (ignored at 1.0), then the crop offsets in cell units
    rng.bit_generator.state = state
    rng.uniform()
    y0 = int(rng.integers(0, (240 - 120) // 8 + 1)) * 8
    x0 = int(rng.integers(0, (320 - 160) // 8 + 1)) * 8
    expect = room.xyz[0][y0 + 4::8, x0 + 4::8][:15, :20].astype(np.float32)
    np.testing.assert_allclose(target, expect)


def test_short_pretraining_lowers_the_loss_and_writes_a_loadable_file(tmp_path):
    opts = PretrainOptions(encoder_width=0.25, n_scenes=2, frames_per_scene=8, iterations=60, batch=4,
                           objective="contrastive", lr=2e-3)
    encoder, prov = pretrain_encoder(opts)
    assert prov["loss_curve"][-1] < prov["loss_curve"][0]
    assert set(prov["held_out_matching_top1"]) == {"pretrained", "random_init"}
    assert prov["feature_scale_applied"] > 0
    assert prov["corpus"]["room_seeds"] == [1000, 1001]
    record = save_encoder_weights(tmp_path / "enc.pt", encoder, prov)
    loaded = load_encoder_weights(tmp_path / "enc.pt", width=0.25)
    saved = json.loads((tmp_path / "enc.json").read_text())
    assert saved["fingerprint"] == record["fingerprint"] == encoder_fingerprint(loaded)
    assert all(v.dtype == torch.float16 for v in torch.load(tmp_path / "enc.pt", weights_only=True).values())


def test_oversized_texture_is_rejected_with_its_reason():
    with pytest.raises(UsvcError, match="texture_resolution"):
        validate(replace(RoomParams(), room_x=6.0, texture_resolution=400.0))


def test_regression_objective_runs_with_one_head_per_room():
    opts = PretrainOptions(encoder_width=0.25, n_scenes=2, frames_per_scene=2, head_width=16, iterations=3,
                           objective="regression",
                           batch=2, crop_h=64, crop_w=64)
    _, prov = pretrain_encoder(opts)
    assert np.isfinite(prov["loss_last_100"])
    with pytest.raises(UsvcError, match="objective"):
        pretrain_encoder(replace(opts, objective="magic"))
