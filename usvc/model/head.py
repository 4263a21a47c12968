"""Per-scene regression head (ACE-style) and the encoder+head regressor; `usvc.model.map_file`
stores them as a map file."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from usvc.model.encoder import Encoder

log = logging.getLogger(__name__)

MAX_SCALE = 4.0
MIN_SCALE = 0.01
# softplus_beta(0) = ln 2 / beta = 1 - 1 / MAX_SCALE, so o3 = 0 gives h = 1.
SOFTPLUS_BETA = math.log(2.0) / (1.0 - 1.0 / MAX_SCALE)



def homogeneous_scale(o3: torch.Tensor) -> torch.Tensor:
    """h = softplus_beta(o3) + 1/MAX_SCALE, at most 1/MIN_SCALE; h lies in (0.25, 100]."""
    h = F.softplus(o3, beta=SOFTPLUS_BETA) + 1.0 / MAX_SCALE
    return h.clamp(max=1.0 / MIN_SCALE)


def _conv1x1(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, bias=True)


def _linear(conv: nn.Module, x: torch.Tensor) -> torch.Tensor:
    return F.linear(x, conv.weight[:, :, 0, 0], conv.bias)


class _ResBlock(nn.Module):
    """Three 1x1 conv+ReLU layers added to the input (via a 1x1 projection if channels differ)."""

    def __init__(self, cin: int, width: int) -> None:
        super().__init__()
        self.conv1 = _conv1x1(cin, width)
        self.conv2 = _conv1x1(width, width)
        self.conv3 = _conv1x1(width, width)
        self.skip: nn.Module = nn.Identity() if cin == width else _conv1x1(cin, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.conv1(x))
        y = F.relu(self.conv2(y))
        y = F.relu(self.conv3(y))
        return self.skip(x) + y


class Head(nn.Module):
    """Features (B, C, H, W) -> world scene coordinates (B, 3, H, W), always fp32.

    Layout: residual block on the input features, `num_blocks` more residual blocks, two
    1x1 conv+ReLU layers, a final 1x1 conv to 4 (homogeneous) or 3 outputs, plus the scene centre.
    When `in_channels != width` (a narrow encoder) the first block's skip is a 1x1 projection,
    since the input cannot be added to a `width`-channel output otherwise.

    `scene_center` stays fp32 under `.half()`/`.to(dtype)`: in fp16 it would round at ~cm for
    scenes ~100 m from the origin, and it is added after the output is cast to fp32.
    """

    def __init__(
        self,
        in_channels: int = 512,
        width: int = 512,
        num_blocks: int = 1,
        homogeneous: bool = True,
    ) -> None:
        super().__init__()
        self.in_channels = int(in_channels)
        self.width = int(width)
        self.num_blocks = int(num_blocks)
        self.homogeneous = bool(homogeneous)
        self.blocks = nn.ModuleList(
            [_ResBlock(self.in_channels, self.width)]
            + [_ResBlock(self.width, self.width) for _ in range(self.num_blocks)]
        )
        self.fc1 = _conv1x1(self.width, self.width)
        self.fc2 = _conv1x1(self.width, self.width)
        self.out = _conv1x1(self.width, 4 if self.homogeneous else 3)
        self.register_buffer("scene_center", torch.zeros(1, 3, 1, 1, dtype=torch.float32))

    def config(self) -> dict[str, Any]:
        return {
            "in_channels": self.in_channels,
            "width": self.width,
            "num_blocks": self.num_blocks,
            "homogeneous": self.homogeneous,
        }

    def set_scene_center(self, center: Sequence[float] | torch.Tensor) -> None:
        """Set the offset added to every prediction (ACE: mean mapping camera position)."""
        c = torch.as_tensor(center, dtype=torch.float64).reshape(1, 3, 1, 1)
        self.scene_center.copy_(c.to(self.scene_center.device, torch.float32))

    def _apply(self, fn: Callable[[torch.Tensor], torch.Tensor], recurse: bool = True) -> Head:
        # Let device moves through but keep the centre's fp32 value (taken before any rounding).
        center = self._buffers["scene_center"]
        super()._apply(fn, recurse)
        moved = self._buffers["scene_center"]
        if center is not None and moved is not None:
            self._buffers["scene_center"] = center.to(device=moved.device, dtype=torch.float32)
        return self

    def forward_flat(self, features: torch.Tensor) -> torch.Tensor:
        """(N, C) features -> (N, 3) coordinates; the same weights as `forward`, run as matmuls.

        Training batches are cells gathered from many images, so there is no image grid, and
        on CPU a matmul is ~2x faster than a 1x1 convolution over an (N, C, 1, 1) tensor.
        """
        x = features.to(self.fc1.weight.dtype)
        for block in self.blocks:
            y = F.relu(_linear(block.conv1, x))
            y = F.relu(_linear(block.conv2, y))
            y = F.relu(_linear(block.conv3, y))
            x = (x if isinstance(block.skip, nn.Identity) else _linear(block.skip, x)) + y
        x = F.relu(_linear(self.fc1, x))
        x = F.relu(_linear(self.fc2, x))
        o = _linear(self.out, x).float()
        xyz = o[:, :3] / homogeneous_scale(o[:, 3:4]) if self.homogeneous else o
        return xyz + self.scene_center.reshape(1, 3)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = features.to(self.fc1.weight.dtype)
        for block in self.blocks:
            x = block(x)
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        o = self.out(x).float()
        if self.homogeneous:
            xyz = o[:, :3] / homogeneous_scale(o[:, 3:4])
        else:
            xyz = o
        return xyz + self.scene_center


class Regressor(nn.Module):
    """Normalised luma image (B, 1, H, W) -> scene coordinates (B, 3, ceil(H/8), ceil(W/8))."""

    def __init__(self, encoder: Encoder, head: Head) -> None:
        super().__init__()
        if head.in_channels != encoder.out_channels:
            raise ValueError(
                f"head expects {head.in_channels} input channels, "
                f"encoder gives {encoder.out_channels}"
            )
        self.encoder = encoder
        self.head = head

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(image))
