"""Head training: the flat (matmul) head equals the conv head, AdaBelief steps like its paper,
and training on a synthetic multi-view buffer recovers the 3D points from 2D observations alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from usvc.buffer.buffer_file import TrainingBuffer
from usvc.core.errors import UsvcError
from usvc.model.head import Head
from usvc.train.adabelief import AdaBelief
from usvc.train.trainer import TrainOptions, mapping_center, train_head

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both


def test_flat_head_equals_conv_head():
    torch.manual_seed(0)
    head = Head(in_channels=48, width=64, num_blocks=1)
    head.set_scene_center([10.0, -2.0, 3.0])
    x = torch.randn(37, 48)
    torch.testing.assert_close(head.forward_flat(x), head(x[:, :, None, None])[:, :, 0, 0], rtol=1e-5, atol=1e-5)


def test_adabelief_first_step_is_lr_sized_and_minimises_a_quadratic():
    w = torch.nn.Parameter(torch.tensor([3.0, -2.0]))
    opt = AdaBelief([w], lr=0.1)
    (w ** 2).sum().backward()
    opt.step()
    # first step: m/(1-b1) = g, s/(1-b2) = (g - m)^2-ish, so the step is about lr * sign(g) * (1 / 0.9)
    assert torch.all((torch.tensor([3.0, -2.0]) - w.detach()).abs() > 0.05)
    for _ in range(300):
        opt.zero_grad()
        (w ** 2).sum().backward()
        opt.step()
    assert w.detach().abs().max() < 0.05
    with pytest.raises(ValueError):
        AdaBelief([w], lr=-1.0)


def _look_at(centre: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # world-to-camera rows
    return R, -R @ centre


def synthetic_buffer(n_points: int = 300, n_views: int = 12, dim: int = 32, seed: int = 0):
    """Points in a 1 m cube seen by cameras on a 3 m circle; each point has its own feature."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.5, 0.5, (n_points, 3))
    feats = rng.standard_normal((n_points, dim)).astype(np.float16)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    Rs, ts, pix, fidx, vidx = [], [], [], [], []
    for v in range(n_views):
        a = 2 * np.pi * v / n_views
        R, t = _look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.5]), np.zeros(3))
        cam = pts @ R.T + t
        uv = cam[:, :2] / cam[:, 2:] * 300.0 + [160.0, 120.0]
        Rs.append(R), ts.append(t), pix.append(uv), fidx.append(np.arange(n_points)), vidx.append(np.full(n_points, v))
    f = np.concatenate(fidx)
    buf = TrainingBuffer(
        features=feats[f], pixels=np.concatenate(pix).astype(np.float32), view_index=np.concatenate(vidx).astype(np.int32),
        view_image=np.arange(n_views, dtype=np.int32), view_R_world_to_cam=np.array(Rs, np.float32),
        view_t_world_to_cam=np.array(ts, np.float32),
        view_K=np.repeat(K[None], n_views, 0).astype(np.float32), image_names=[f"v{v}" for v in range(n_views)])
    return buf, pts, feats


OPTS = TrainOptions(iterations=400, batch_size=512, lr=3e-3, threshold_start=20.0, bundle_weight=0.0)


def test_training_recovers_points_from_reprojection_alone():
    buf, pts, feats = synthetic_buffer()
    np.testing.assert_allclose(mapping_center(buf), [0, 0, 0.5], atol=1e-5)
    head, summary = train_head(buf, median_depth=3.0, opts=OPTS, head_width=128, head_blocks=1)
    with torch.no_grad():
        pred = head.forward_flat(torch.from_numpy(feats).float()).numpy()
    err = np.linalg.norm(pred - pts, axis=1)
    assert np.median(err) < 0.03, np.median(err)
    assert summary["final_reproj_median_px"] < 3.0 and summary["final_valid_fraction"] > 0.99
    assert summary["loss_curve"][-1] < summary["loss_curve"][0]


def test_training_is_deterministic_and_adabelief_runs():
    buf, _, _ = synthetic_buffer(n_points=50, n_views=4)
    short = TrainOptions(iterations=5, batch_size=64, bundle_weight=0.0)
    a, _ = train_head(buf, 3.0, short, head_width=32, head_blocks=1)
    b, _ = train_head(buf, 3.0, short, head_width=32, head_blocks=1)
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(va, vb, rtol=0, atol=0, msg=k)
    c, summary = train_head(buf, 3.0, TrainOptions(iterations=5, batch_size=64, bundle_weight=0.0,
                                                   optimizer="adabelief", lr=1e-4, schedule="constant"),
                            head_width=32, head_blocks=1)
    assert np.isfinite(summary["final_loss"])


@pytest.mark.parametrize("opts, depth, message", [
    (TrainOptions(batch_size=10_000, bundle_weight=0.0), 3.0, "fewer than one batch"),
    (TrainOptions(optimizer="sgd", batch_size=64), 3.0, "train option optimizer"),
    (TrainOptions(batch_size=64, bundle_weight=0.0), 0.0, "median scene depth"),
])
def test_bad_training_input_is_named(opts, depth, message):
    buf, _, _ = synthetic_buffer(n_points=50, n_views=4)
    with pytest.raises(UsvcError, match=message):
        train_head(buf, depth, opts, head_width=256, head_blocks=1)


def with_keypoint_tuples(buf: TrainingBuffer, pts: np.ndarray, feats: np.ndarray, one_view_pixels: bool):
    """Every point is a keypoint observed in every view; optionally keep each point's ordinary
    pixel samples in one view only, where reprojection alone cannot tell its depth."""
    n_views = len(buf.view_image)
    n = len(pts)
    point = np.tile(np.arange(n), n_views)
    order = np.argsort(point, kind="stable")
    buf.kp_id = point[order].astype(np.int32)
    buf.kp_view = buf.view_index[order].copy()
    buf.kp_pixels = buf.pixels[order].copy()
    buf.kp_features = buf.features[order].copy()
    buf.kp_from_depth = np.zeros(len(order), dtype=bool)
    buf.keypoint_xyz = pts.astype(np.float32)
    if one_view_pixels:
        keep = buf.view_index == point % n_views
        buf.features, buf.pixels, buf.view_index = buf.features[keep], buf.pixels[keep], buf.view_index[keep]
    return buf


def test_zero_bundle_weight_is_exactly_single_view_training():
    buf, pts, feats = synthetic_buffer(n_points=50, n_views=4)
    opts = TrainOptions(iterations=5, batch_size=64, bundle_weight=0.0)
    a, _ = train_head(buf, 3.0, opts, head_width=32, head_blocks=1)
    b, _ = train_head(with_keypoint_tuples(buf, pts, feats, one_view_pixels=False), 3.0, opts, head_width=32,
                      head_blocks=1)
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(va, vb, rtol=0, atol=0, msg=k)


def test_bundle_loss_recovers_depth_that_single_view_reprojection_leaves_open():
    """Each point's pixel samples come from one view only: its depth along that ray is free under
    L_pi. The keypoint tuples from the other views (bundle loss) pin it down.

    Measured over 3 buffers x 3 seeds at 1 and 2 threads: at 400 iterations the bundle median
    was bimodal (0.001 or 0.14-0.19 m, by CPU and seed); from 600 iterations it is <= 0.001 m
    and L_pi alone stays at 0.34-0.46 m. About a third of the points stay unconverged either
    way (90th percentile ~0.7 m), so the median is what this asserts."""
    buf, pts, feats = synthetic_buffer(n_points=200, n_views=8)
    buf = with_keypoint_tuples(buf, pts, feats, one_view_pixels=True)
    errors = {}
    for weight in (0.0, 1.0):
        opts = TrainOptions(iterations=800, batch_size=128, lr=3e-3, threshold_start=20.0,
                            bundle_weight=weight, bundle_groups_per_batch=32, bundle_obs_per_group=8)
        head, summary = train_head(buf, 3.0, opts, head_width=128, head_blocks=1)
        with torch.no_grad():
            pred = head.forward_flat(torch.from_numpy(feats).float()).numpy()
        errors[weight] = float(np.median(np.linalg.norm(pred - pts, axis=1)))
    assert summary["bundle_groups"] == 200 and "final_bundle_reproj_median_px" in summary
    assert errors[1.0] < 0.02, errors
    assert errors[0.0] > 0.15, errors


def test_bundle_weight_without_keypoint_tuples_is_refused():
    buf, _, _ = synthetic_buffer(n_points=50, n_views=4)
    with pytest.raises(UsvcError, match="keypoint observations"):
        train_head(buf, 3.0, TrainOptions(iterations=5, batch_size=64, bundle_weight=1.0), head_width=32, head_blocks=1)
