from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from usvc.train.reprojection_loss import reprojection_loss
from usvc.train.schedule import circle_threshold

# ACE's absolute bounds (metres at an indoor scale): the loss has no defaults of its own (the trainer
# passes TrainOptions' bounds times the median depth), and these tests are written for ACE's values.
ACE = {"depth_min": 0.1, "depth_max": 1000.0, "max_reproj": 1000.0, "invalid_depth": 10.0}


def _random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2)).unsqueeze(1)
    return q * torch.sign(torch.linalg.det(q)).view(n, 1, 1)


def _batch(n: int, seed: int = 0, depth: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Cameras, target pixels and the world points that project exactly onto them (float64)."""
    gen = torch.Generator().manual_seed(seed)
    R = _random_rotations(n, gen)
    t = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 2
    K = torch.zeros(n, 3, 3, dtype=torch.float64)
    K[:, 0, 0] = 500 + 50 * torch.rand(n, generator=gen, dtype=torch.float64)
    K[:, 1, 1] = 480 + 50 * torch.rand(n, generator=gen, dtype=torch.float64)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = 320.0, 240.0, 1.0
    pixels = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    if depth is None:
        depth = 1 + 9 * torch.rand(n, generator=gen, dtype=torch.float64)
    K_inv = torch.linalg.inv(K)
    uv1 = torch.cat([pixels, torch.ones(n, 1, dtype=torch.float64)], dim=1)
    p = depth.unsqueeze(1) * torch.einsum("nij,nj->ni", K_inv, uv1)
    X = torch.einsum("nji,nj->ni", R, p - t)
    return {"pred_xyz_world": X, "pixels": pixels, "R_world_to_cam": R, "t_world_to_cam": t, "K": K, "K_inv": K_inv}


def _to(b: dict[str, torch.Tensor], dtype: torch.dtype) -> dict[str, torch.Tensor]:
    return {k: v.to(dtype) for k, v in b.items()}


def test_circle_threshold_endpoints_and_monotone() -> None:
    assert circle_threshold(0, 100, 50.0, 1.0) == pytest.approx(51.0)
    assert circle_threshold(100, 100, 50.0, 1.0) == pytest.approx(1.0)
    assert circle_threshold(250, 100, 50.0, 1.0) == pytest.approx(1.0)
    assert circle_threshold(50, 100, 50.0, 1.0) == pytest.approx(50 * math.sqrt(0.75) + 1)
    values = [circle_threshold(i, 1000, 50.0, 1.0) for i in range(1001)]
    assert all(a > b for a, b in zip(values, values[1:]))
    tt = circle_threshold(torch.arange(1001), 1000, 50.0, 1.0)
    assert isinstance(tt, torch.Tensor)
    np.testing.assert_allclose(tt.numpy(), values, rtol=1e-6)
    assert circle_threshold(0, 10, start=20.0, end=2.0) == pytest.approx(22.0)
    with pytest.raises(ValueError):
        circle_threshold(0, 0, 50.0, 1.0)


def test_perfect_prediction_has_zero_loss() -> None:
    b = _to(_batch(64), torch.float32)
    loss, stats = reprojection_loss(**b, threshold=10.0, **ACE)
    assert loss.ndim == 0 and loss.dtype == torch.float32
    assert loss.item() < 1e-2
    assert stats["valid_fraction"].item() == 1.0
    assert stats["reproj_mean"].item() < 1e-2 and stats["reproj_median"].item() < 1e-2


def test_point_behind_camera_pulls_to_depth_ten_on_ray() -> None:
    b = _batch(5, depth=torch.tensor([-2.0, 3.0, -0.5, 0.05, 2000.0], dtype=torch.float64))
    loss, stats = reprojection_loss(**b, threshold=10.0, **ACE)
    # Camera coordinates of the predictions and the depth-10 points on the pixels' rays.
    p = torch.einsum("nij,nj->ni", b["R_world_to_cam"], b["pred_xyz_world"]) + b["t_world_to_cam"]
    uv1 = torch.cat([b["pixels"], torch.ones(5, 1, dtype=torch.float64)], dim=1)
    target = 10 * torch.einsum("nij,nj->ni", b["K_inv"], uv1)
    expected = (p - target).abs().sum(dim=1)
    expected[1] = 0.0  # the one valid, perfect sample
    assert stats["valid_fraction"].item() == pytest.approx(0.2)
    assert loss.item() == pytest.approx(expected.sum().item() / 5, rel=1e-9)


def test_large_reprojection_error_is_invalid() -> None:
    b = _batch(2)
    b["pixels"] = b["pixels"] + torch.tensor([[600.0, 500.0], [0.0, 0.0]], dtype=torch.float64)
    _, stats = reprojection_loss(**b, threshold=10.0, **ACE)
    assert stats["valid_fraction"].item() == pytest.approx(0.5)


def test_tanh_clamp_bounds_valid_loss_by_threshold() -> None:
    b = _batch(32, seed=3)
    b["pixels"] = b["pixels"] + 300.0  # L1 error 600 px: valid but far beyond tau
    tau = 5.0
    loss, stats = reprojection_loss(**b, threshold=tau, **ACE)
    assert stats["valid_fraction"].item() == 1.0
    assert stats["reproj_mean"].item() == pytest.approx(600.0, rel=1e-6)
    assert loss.item() <= tau
    assert loss.item() == pytest.approx(tau, rel=1e-6)
    # Small errors are nearly linear: tau * tanh(e / tau) ~ e.
    b = _batch(1, seed=4)
    b["pixels"] = b["pixels"] + torch.tensor([[0.01, -0.02]], dtype=torch.float64)
    loss, _ = reprojection_loss(**b, threshold=50.0, **ACE)
    assert loss.item() == pytest.approx(0.03, rel=1e-4)


def test_gradients_match_finite_differences() -> None:
    depth = torch.tensor([2.0, 4.0, -3.0, 6.0, 1500.0, 8.0], dtype=torch.float64)
    b = _batch(6, seed=5, depth=depth)
    gen = torch.Generator().manual_seed(6)
    pred = (b.pop("pred_xyz_world") + 0.05 * torch.randn(6, 3, generator=gen, dtype=torch.float64))
    pred.requires_grad_(True)

    def f(x: torch.Tensor) -> torch.Tensor:
        return reprojection_loss(x, **b, threshold=7.0, **ACE)[0]

    assert torch.autograd.gradcheck(f, (pred,), eps=1e-6, atol=1e-5)


def test_gradient_step_reduces_loss() -> None:
    b = _to(_batch(128, seed=7), torch.float32)
    gen = torch.Generator().manual_seed(8)
    pred = (b.pop("pred_xyz_world") + 0.3 * torch.randn(128, 3, generator=gen)).requires_grad_(True)
    losses = []
    for _ in range(5):
        loss, _ = reprojection_loss(pred, **b, threshold=20.0, **ACE)
        losses.append(loss.item())
        (grad,) = torch.autograd.grad(loss, pred)
        with torch.no_grad():
            pred -= 1e-4 * grad / grad.norm(dim=1, keepdim=True).clamp(min=1e-12) * 128
    assert all(a > b_ for a, b_ in zip(losses, losses[1:]))


def test_shape_mismatch_raises() -> None:
    b = _batch(4)
    b["pixels"] = b["pixels"][:3]
    with pytest.raises(ValueError):
        reprojection_loss(**b, threshold=1.0, **ACE)


def test_half_inputs_and_autocast_are_computed_in_fp32() -> None:
    b64 = _batch(256, seed=9)
    b64["pred_xyz_world"] = b64["pred_xyz_world"] + 0.01
    b16 = _to(b64, torch.float16)
    ref, _ = reprojection_loss(**_to(b16, torch.float64), threshold=10.0, **ACE)
    loss16, stats = reprojection_loss(**b16, threshold=10.0, **ACE)
    assert loss16.dtype == torch.float32 and stats["reproj_mean"].dtype == torch.float32
    assert loss16.item() == pytest.approx(ref.item(), rel=1e-4)

    b32 = _to(b64, torch.float32)
    plain, _ = reprojection_loss(**b32, threshold=10.0, **ACE)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        auto, _ = reprojection_loss(**b32, threshold=10.0, **ACE)
    assert auto.dtype == torch.float32
    assert auto.item() == pytest.approx(plain.item(), rel=1e-6)


def test_no_valid_sample_gives_nan_stats() -> None:
    b = _batch(3, depth=torch.full((3,), -1.0, dtype=torch.float64))
    loss, stats = reprojection_loss(**b, threshold=10.0, **ACE)
    assert torch.isfinite(loss)
    assert stats["valid_fraction"].item() == 0.0
    assert math.isnan(stats["reproj_mean"].item()) and math.isnan(stats["reproj_median"].item())
