"""ACE's reprojection loss for scene coordinate regression, vectorised over a batch of cells.

Per sample, with X the predicted world point and (u, v) its target pixel (COLMAP convention,
same as K): p = R X + t in camera coordinates; (u', v') = K p projected after clamping the depth
to >= ``depth_min``; e = |u' - u| + |v' - v| (L1 pixel error, as ACE uses).

- valid (depth_min <= z <= depth_max and e <= max_reproj): loss = tau * tanh(e / tau), a soft
  clamp so that outliers, whose error is large, pull with a bounded force;
- invalid: loss = || p - invalid_depth * K^-1 [u, v, 1]^T ||_1, which pulls points that are
  behind the camera, too far, or wildly off back to a plausible point on the pixel's ray, where
  the reprojection term can take over.

The total is the sum over samples divided by N. Everything is computed in at least fp32 with
autocast disabled, because fp16 depths and pixel errors lose the precision the loss needs.
"""

from __future__ import annotations

import torch


def project_samples(X: torch.Tensor, uv: torch.Tensor, R: torch.Tensor, t: torch.Tensor, K: torch.Tensor,
                    K_inv: torch.Tensor, depth_min: float,
                    invalid_depth: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per sample: camera depth z, the projection (depth clamped to depth_min), and the invalid-
    prediction term |p - invalid_depth * K^-1 [u, v, 1]|_1 that pulls bad points onto the ray.
    Shared by every loss form, so they all treat points behind the camera the same way. Leading
    dimensions broadcast: X (..., 3), uv (..., 2), R, K, K_inv (..., 3, 3), t (..., 3) (the bundle
    loss projects every observation of a group into every view of it this way)."""
    p = torch.einsum("...ij,...j->...i", R, X) + t
    z = p[..., 2]
    h = torch.einsum("...ij,...j->...i", K, p)  # h[..., 2] == z: K's last row is [0, 0, 1]
    proj = h[..., :2] / h[..., 2:3].clamp(min=depth_min)
    uv1 = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)
    invalid = (p - invalid_depth * torch.einsum("...ij,...j->...i", K_inv, uv1)).abs().sum(dim=-1)
    return z, proj, invalid


def lower_median(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The lower median of `values` where `valid` (NaN where none is), as `nanmedian` of the valid
    values gives it, without reading anything back from the device: CUDA's `nanmedian` reads the
    NaN count to the host, which would make every training step wait for the GPU (and cannot be
    captured in a CUDA graph). NaNs sort last, so the median is the sorted values' entry
    (count - 1) // 2, taken with a device-side index."""
    valid = valid & ~values.isnan()
    if not values.is_cuda:  # the host has no device to wait for, and its selection beats a sort
        return torch.where(valid, values, torch.full_like(values, float("nan"))).nanmedian()
    ordered = torch.where(valid, values, torch.full_like(values, float("nan"))).flatten().sort().values
    at = ((valid.sum() - 1).clamp(min=0) // 2).reshape(1)
    return ordered.gather(0, at).reshape(())


def reprojection_loss(
    pred_xyz_world: torch.Tensor,
    pixels: torch.Tensor,
    R_world_to_cam: torch.Tensor,
    t_world_to_cam: torch.Tensor,
    K: torch.Tensor,
    K_inv: torch.Tensor,
    threshold: float | torch.Tensor,
    *,
    depth_min: float,
    depth_max: float,
    max_reproj: float,
    invalid_depth: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean loss over N samples and detached statistics.

    Shapes: pred_xyz_world (N, 3), pixels (N, 2), R_world_to_cam (N, 3, 3), t_world_to_cam (N, 3),
    K and K_inv (N, 3, 3). ``threshold`` is tau in pixels (see ``schedule.circle_threshold``). The depth bounds,
    ``max_reproj`` and ``invalid_depth`` have no defaults: the trainer derives them from
    `TrainOptions` (relative to the scene's median depth), so a value lives in one place.

    Stats (0-dim detached tensors, so the caller decides when to synchronise): ``valid_fraction``,
    ``reproj_mean`` and ``reproj_median`` (lower median) of the valid samples' L1 pixel errors
    (NaN when none is valid).
    """
    n = pred_xyz_world.shape[0]
    if pixels.shape != (n, 2) or R_world_to_cam.shape != (n, 3, 3) or t_world_to_cam.shape != (n, 3):
        raise ValueError(
            f"shape mismatch: pred {tuple(pred_xyz_world.shape)}, pixels {tuple(pixels.shape)}, "
            f"R {tuple(R_world_to_cam.shape)}, t {tuple(t_world_to_cam.shape)}"
        )
    if K.shape != (n, 3, 3) or K_inv.shape != (n, 3, 3):
        raise ValueError(
            f"K and K_inv must be ({n}, 3, 3), got {tuple(K.shape)}, {tuple(K_inv.shape)}"
        )

    dtype = torch.promote_types(pred_xyz_world.dtype, torch.float32)
    with torch.autocast(device_type=pred_xyz_world.device.type, enabled=False):
        X = pred_xyz_world.to(dtype)
        uv = pixels.to(dtype)
        R = R_world_to_cam.to(dtype)
        t = t_world_to_cam.to(dtype)
        Kf = K.to(dtype)
        Kinv = K_inv.to(dtype)
        tau = threshold.to(dtype) if isinstance(threshold, torch.Tensor) else threshold

        z, proj, invalid_loss = project_samples(X, uv, R, t, Kf, Kinv, depth_min, invalid_depth)
        err = (proj - uv).abs().sum(dim=1)
        valid = (z >= depth_min) & (z <= depth_max) & (err <= max_reproj)
        valid_loss = tau * torch.tanh(err / tau)

        per_sample = torch.where(valid, valid_loss, invalid_loss)
        loss = per_sample.sum() / max(n, 1)

        with torch.no_grad():
            # Masked reductions rather than boolean indexing: no host synchronisation on GPU.
            count = valid.sum().to(dtype)
            stats = {
                "valid_fraction": count / n if n else count * float("nan"),
                "reproj_mean": torch.where(valid, err, torch.zeros_like(err)).sum() / count,
                "reproj_median": lower_median(err, valid),
            }
    return loss, stats
