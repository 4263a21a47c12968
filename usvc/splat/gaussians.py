"""The Gaussian set in the parameterisation 3DGS optimises and stores: log scales, opacity
logits, unnormalised wxyz quaternions and SH coefficients (DC and the rest kept apart, since
they get different learning rates and different PLY properties)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from scipy.spatial import cKDTree

from usvc.core.errors import UsvcError
from usvc.splat.sh import num_coeffs, rgb_to_dc

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


@dataclass
class Gaussians:
    means: torch.Tensor  # (N, 3) world
    log_scales: torch.Tensor  # (N, 3)
    quats: torch.Tensor  # (N, 4) w x y z, unnormalised
    opacity_logits: torch.Tensor  # (N,)
    sh_dc: torch.Tensor  # (N, 3)
    sh_rest: torch.Tensor  # (N, (degree+1)^2 - 1, 3)

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def rotations(self) -> torch.Tensor:
        return torch.nn.functional.normalize(self.quats, dim=-1)

    @property
    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh_dc[:, None], self.sh_rest], dim=1)

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to(self, device: str | torch.device) -> "Gaussians":
        return Gaussians(**{k: v.to(device) for k, v in self.tensors().items()})

    def detach(self) -> "Gaussians":
        return Gaussians(**{k: v.detach() for k, v in self.tensors().items()})


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) unit wxyz -> (N, 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def covariances(g: Gaussians) -> torch.Tensor:
    """World covariances R S S^T R^T, (N, 3, 3)."""
    M = quat_to_rotmat(g.rotations) * g.scales[:, None, :]
    return M @ M.transpose(1, 2)


def from_points(xyz: np.ndarray, rgb: np.ndarray, sh_degree: int, initial_opacity: float = 0.1,
                neighbours: int = 3) -> Gaussians:
    """Isotropic Gaussians on the SfM points: scale = mean distance to the nearest neighbours (as
    3DGS initialises), colour = the point's colour (uint8 RGB) as the SH DC term."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) < neighbours + 1:
        raise UsvcError(f"Gaussian initialisation needs at least {neighbours + 1} 3D points, got {xyz.shape}")
    if not 0 < initial_opacity < 1:
        raise UsvcError(f"initial opacity must be in (0, 1), got {initial_opacity}")
    dist, _ = cKDTree(xyz).query(xyz, k=neighbours + 1)
    mean_d = np.maximum(dist[:, 1:].mean(axis=1), 1e-7)
    n = len(xyz)
    colour = torch.as_tensor(np.asarray(rgb, dtype=np.float32) / 255.0)
    return Gaussians(
        means=torch.as_tensor(xyz, dtype=torch.float32),
        log_scales=torch.as_tensor(np.log(mean_d), dtype=torch.float32)[:, None].repeat(1, 3),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        opacity_logits=torch.full((n,), float(np.log(initial_opacity / (1 - initial_opacity)))),
        sh_dc=rgb_to_dc(colour),
        sh_rest=torch.zeros(n, num_coeffs(sh_degree) - 1, 3),
    )
