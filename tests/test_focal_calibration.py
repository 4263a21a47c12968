"""A map's measure of how well its coordinates tell a view's focal length (usvc.train.focal_calibration),
and the relocalizer letting only a map that tells its own views' within the tolerance judge a
given focal length."""

from __future__ import annotations

import re
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from test_relocalizer import R_TRUE, WORK_CAMERA, exact, photo  # noqa: F401

from usvc.buffer.buffer_file import TrainingBuffer
from usvc.model.encoder import Encoder
from usvc.model.head import Head, Regressor
from usvc.model.map_file import save_map
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.relocalizer import Relocalizer
from usvc.train import focal_calibration
from usvc.train.focal_calibration import FOCAL_ERROR_CAP, map_focal_error

W, H, F = 160, 120, 130.0


class _CoordinateHead(torch.nn.Module):
    """A head whose output is its input's first three channels: the buffer carries the coordinates."""

    def forward_flat(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, :3]


def _buffer(noise: float, views: int = 12, seed: int = 0) -> TrainingBuffer:
    """Views of points 2-4 units in front of cameras turned about the origin; each cell's features
    hold its world point, perturbed by `noise` x the depth."""
    rng = np.random.default_rng(seed)
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    feats, pixels, index, Rs, ts = [], [], [], [], []
    for v in range(views):
        a = np.radians(10.0 * v)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        t = np.array([0.1 * v, 0.0, 0.5])
        uv = rng.uniform([0, 0], [W, H], (300, 2))
        depth = rng.uniform(2.0, 4.0, 300)
        cam = np.c_[(uv - K[:2, 2]) / F, np.ones(300)] * depth[:, None]
        xyz = (cam - t) @ R  # R^T (cam - t)
        xyz = xyz + rng.normal(0.0, noise, xyz.shape) * depth[:, None]
        feats.append(np.c_[xyz, np.zeros((300, 5))].astype(np.float16))
        pixels.append(uv.astype(np.float32))
        index.append(np.full(300, v, np.int32))
        Rs.append(R)
        ts.append(t)
    return TrainingBuffer(np.concatenate(feats), np.concatenate(pixels), np.concatenate(index),
                          np.arange(views, dtype=np.int32), np.array(Rs), np.array(ts), np.repeat(K[None], views, 0),
                          [f"{v}.png" for v in range(views)])


def test_a_map_that_fits_its_views_tells_their_focal_lengths():
    exact_fit = map_focal_error(_CoordinateHead(), _buffer(0.0), "fp32")
    assert exact_fit["views"] == 12 and exact_fit["p90"] < 0.02
    coarse = map_focal_error(_CoordinateHead(), _buffer(0.03), "fp32")
    assert coarse["p90"] > 5 * max(exact_fit["p90"], 0.005)
    buf = _buffer(0.0)
    buf.features[:, :3] = np.random.default_rng(1).permutation(buf.features[:, :3])  # coordinates of other cells
    assert map_focal_error(_CoordinateHead(), buf, "fp32")["median"] >= 0.5


def test_the_views_measured_are_capped_and_picked_by_the_seed(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(focal_calibration, "FOCAL_CHECK_VIEWS", 5)
    buf = _buffer(0.02)
    a, b = map_focal_error(_CoordinateHead(), buf, "fp32", seed=0), map_focal_error(_CoordinateHead(), buf, "fp32", seed=0)
    assert a == b and a["views"] == 5
    assert map_focal_error(_CoordinateHead(), buf, "fp32", seed=1) != a
    monkeypatch.setattr(focal_calibration, "estimate_focal", lambda *args: None)  # no pose anywhere
    assert map_focal_error(_CoordinateHead(), buf, "fp32")["p90"] == FOCAL_ERROR_CAP


def test_views_solved_side_by_side_give_the_figures_of_one_at_a_time(monkeypatch: pytest.MonkeyPatch):
    buf = _buffer(0.02)
    one = map_focal_error(_CoordinateHead(), buf, "fp32", workers=1)
    assert map_focal_error(_CoordinateHead(), buf, "fp32", workers=4) == one
    # and they do run side by side: two solves meet at a barrier that one thread alone never passes
    barrier, solve = threading.Barrier(2, timeout=10), focal_calibration.estimate_focal

    def meeting(*args):
        barrier.wait()
        return solve(*args)

    monkeypatch.setattr(focal_calibration, "estimate_focal", meeting)
    assert map_focal_error(_CoordinateHead(), _buffer(0.02, views=2), "fp32", workers=2)["views"] == 2


def test_the_measure_uses_the_relocalizers_threshold():
    from usvc.relocalize.options import REFERENCE_SHORT_SIDE
    assert focal_calibration.FOCAL_CHECK_MAX_ERROR_PX == RelocalizeOptions().max_error_px
    assert focal_calibration.FOCAL_CHECK_SHORT_SIDE == REFERENCE_SHORT_SIDE


def _map(tmp_path: Path, focal_error: float | None) -> tuple[Path, Path]:
    torch.manual_seed(0)
    encoder = Encoder(width=0.25)
    weights = tmp_path / "encoder.pt"
    torch.save(encoder.state_dict(), weights)
    meta = {"short_side": 120} | ({} if focal_error is None else {"focal_error": focal_error})
    save_map(tmp_path / "map.pt", Regressor(encoder, Head(in_channels=encoder.out_channels, width=64)), meta)
    return tmp_path / "map.pt", weights


@pytest.mark.parametrize("focal_error, judges", [(None, True), (0.1, True), (0.22, True), (0.3, False), (2.0, False)])
def test_only_a_map_that_tells_its_own_views_focal_lengths_judges_a_given_one(
        tmp_path: Path, exact: list, focal_error: float | None, judges: bool):  # noqa: F811
    """Exact coordinates imply the true focal length, so a given one 2x off is refused where the
    map judges; a map that does not tell its own views' focal lengths within the tolerance
    (ln 1.25 = 0.223) has no say, and the answer stands on its confidence."""
    (fx, fy), (cx, cy) = WORK_CAMERA.focal, WORK_CAMERA.principal_point
    reloc = Relocalizer(*_map(tmp_path, focal_error), options=RelocalizeOptions(focal_tolerance=0.25))
    assert reloc.map_judges_focal is judges
    est = reloc.localize(photo(160, 120), (2 * fx, 2 * fy, cx, cy))
    if judges:
        assert not est.success and re.match(r"the image implies a focal length 0\.\d+x", est.rejected)
    else:
        assert not re.search("implies a focal", est.rejected)
        assert any("focal length was not checked" in w and "does not tell its own" in w for w in est.warnings)
    right = reloc.localize(photo(160, 120), (fx, fy, cx, cy))
    assert right.success and any("not checked" in w for w in right.warnings) is not judges


def test_a_map_with_a_bad_focal_error_is_refused_on_load(tmp_path: Path):
    from usvc.model.errors import ModelError
    with pytest.raises(ModelError, match="focal_error"):
        Relocalizer(*_map(tmp_path, -1.0))
