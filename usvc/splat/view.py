"""What the rasterisers take and give: a pinhole view and a rendered image with its depth and alpha."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class View:
    """A pinhole view: world-to-camera R (3, 3), t (3,), intrinsics K (3, 3), size in pixels."""

    R: torch.Tensor
    t: torch.Tensor
    K: torch.Tensor
    width: int
    height: int

    def to(self, device: str | torch.device) -> "View":
        return View(self.R.to(device), self.t.to(device), self.K.to(device), self.width, self.height)


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # (H, W, 3)
    depth: torch.Tensor  # (H, W) expected depth of the composited Gaussians (0 where alpha is 0)
    alpha: torch.Tensor  # (H, W) accumulated opacity
    means2d: torch.Tensor  # (N, 2), retains its gradient for densification
    radii: torch.Tensor  # (N,)
