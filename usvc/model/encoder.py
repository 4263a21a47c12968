"""ACE-compatible feature encoder: 11 plain convs, output stride 8.

Layer names and shapes follow the published ACE table, so a plain state dict with keys
`<name>.weight` / `<name>.bias` loads strictly. `width` scales every channel count (rounded to a
multiple of 8) for a cheaper variant that no published weight file fits.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from usvc.model.errors import ModelError, first_line

# Transitional: usvc/model/head.py imports this name; it goes once head.py imports first_line from
# usvc.model.errors.
_first_line = first_line

log = logging.getLogger(__name__)

OUTPUT_STRIDE = 8

# (name, in channels, out channels, kernel, stride) at width 1.0; order is the forward order.
LAYERS: tuple[tuple[str, int, int, int, int], ...] = (
    ("conv1", 1, 32, 3, 1),
    ("conv2", 32, 64, 3, 2),
    ("conv3", 64, 128, 3, 2),
    ("conv4", 128, 256, 3, 2),
    ("res1_conv1", 256, 256, 3, 1),
    ("res1_conv2", 256, 256, 1, 1),
    ("res1_conv3", 256, 256, 3, 1),
    ("res2_conv1", 256, 512, 3, 1),
    ("res2_conv2", 512, 512, 1, 1),
    ("res2_conv3", 512, 512, 3, 1),
    ("res2_skip", 256, 512, 1, 1),
)


def _scaled(channels: int, width: float) -> int:
    """Channel count at a width multiplier; the 1-channel image input is never scaled."""
    if channels == 1:
        return 1
    return max(8, int(round(channels * width / 8.0)) * 8)


def layer_specs(width: float = 1.0) -> list[tuple[str, int, int, int, int]]:
    """The encoder table at a width multiplier: (name, in, out, kernel, stride)."""
    if not width > 0:
        raise ValueError(f"encoder width multiplier must be positive, got {width}")
    return [(n, _scaled(i, width), _scaled(o, width), k, s) for n, i, o, k, s in LAYERS]


class Encoder(nn.Module):
    """Image (B, 1, H, W), normalised luma -> features (B, C, ceil(H/8), ceil(W/8)).

    The convs are direct attributes (no Sequential prefixes) so ACE-style state dict keys match.
    """

    OUTPUT_STRIDE = OUTPUT_STRIDE

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        self.width = float(width)
        specs = layer_specs(self.width)
        for name, cin, cout, k, stride in specs:
            setattr(self, name, nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, bias=True))
        self.out_channels: int = specs[-1][2]

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.conv1(image))
        x = F.relu(self.conv2(x))
        x = F.relu(self.conv3(x))
        r = F.relu(self.conv4(x))
        x = F.relu(self.res1_conv1(r))
        x = F.relu(self.res1_conv2(x))
        x = F.relu(self.res1_conv3(x))
        r = r + x
        x = F.relu(self.res2_conv1(r))
        x = F.relu(self.res2_conv2(x))
        x = F.relu(self.res2_conv3(x))
        return x + self.res2_skip(r)  # no ReLU: features can be negative


def _conv_out(n: int, k: int, stride: int) -> int:
    return (n + 2 * (k // 2) - k) // stride + 1


def feature_size(height: int, width: int) -> tuple[int, int]:
    """Feature map size for an image: ceil(H/8) x ceil(W/8) with this padding scheme."""
    for _, _, _, k, s in LAYERS[:4]:
        height, width = _conv_out(height, k, s), _conv_out(width, k, s)
    return height, width


def encoder_flops(height: int, width: int, width_mult: float = 1.0) -> float:
    """FLOPs (2 x multiply-adds of all convs, biases and ReLUs ignored) for one image."""
    h, w = height, width
    total = 0.0
    for name, cin, cout, k, s in layer_specs(width_mult):
        if name in ("conv1", "conv2", "conv3", "conv4"):
            h, w = _conv_out(h, k, s), _conv_out(w, k, s)
        total += 2.0 * h * w * cout * cin * k * k
    return total


def cell_centers(
    h_cells: int, w_cells: int, convention: Literal["colmap", "opencv"] = "colmap"
) -> torch.Tensor:
    """Pixel position (x, y) of every feature cell, as a (2, h_cells, w_cells) float32 tensor.

    ACE assigns cell (i, j) the pixel (8j + 4, 8i + 4) in OpenCV's integer-pixel convention
    (pixel centres at integers). COLMAP puts pixel centres at +0.5, so the same position is
    (8j + 4.5, 8i + 4.5). The default returns COLMAP coordinates because the rest of the project
    (poses, intrinsics, keypoints) is in COLMAP's convention; `convention="opencv"` gives ACE's
    numbers. What matters is that mapping and relocalization use the same positions.
    """
    offset = {"colmap": 4.5, "opencv": 4.0}
    if convention not in offset:
        raise ValueError(f"convention must be 'colmap' or 'opencv', got {convention!r}")
    ys = torch.arange(h_cells, dtype=torch.float32) * OUTPUT_STRIDE + offset[convention]
    xs = torch.arange(w_cells, dtype=torch.float32) * OUTPUT_STRIDE + offset[convention]
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack((grid_x, grid_y))


def encoder_fingerprint(encoder: nn.Module) -> str:
    """sha256 over (name, shape, values) of the state dict in sorted key order.

    Values are hashed after rounding to fp16, so a half-cast copy of an encoder keeps its
    identity (a map trained with the fp32 encoder stays usable with the fp16 one).
    """
    digest = hashlib.sha256()
    for name, tensor in sorted(encoder.state_dict().items()):
        t = tensor.detach().to("cpu", torch.float32).to(torch.float16).contiguous()
        digest.update(name.encode())
        digest.update(repr(tuple(t.shape)).encode())
        digest.update(t.numpy().tobytes())
    return digest.hexdigest()


def _short_list(names: list[str], limit: int = 6) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _read_state_dict(path: Path) -> Mapping[str, object]:
    if path.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file
        except ImportError as exc:
            raise ModelError(
                f"{path}: reading .safetensors needs the 'safetensors' package, which is not "
                "installed (pip install safetensors, or convert the file to a torch state dict)"
            ) from exc
        try:
            return load_file(str(path), device="cpu")
        except Exception as exc:
            raise ModelError(f"{path}: cannot read encoder weights ({first_line(exc)})") from exc
    from usvc.model.safe_load import load_tensors

    return load_tensors(path, "encoder weights")


def check_state_dict(path: Path, state: object, model: nn.Module, what: str) -> None:
    """Raise ModelError unless `state` has exactly the model's keys with the model's shapes."""
    if not isinstance(state, Mapping):
        raise ModelError(f"{path}: {what} is a {type(state).__name__}, not a state dict")
    expected = model.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [str(k) for k in state if k not in expected]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing {_short_list(missing)}")
        if unexpected:
            parts.append(f"unexpected {_short_list(unexpected)}")
        raise ModelError(f"{path}: {what} keys do not match ({'; '.join(parts)})")
    for key, ref in expected.items():
        value = state[key]
        if not isinstance(value, torch.Tensor):
            kind = type(value).__name__
            raise ModelError(f"{path}: {what} entry {key} is a {kind}, not a tensor")
        if tuple(value.shape) != tuple(ref.shape):
            raise ModelError(
                f"{path}: {what} entry {key} has shape {list(value.shape)}, "
                f"expected {list(ref.shape)}"
            )
        if value.is_floating_point() != ref.is_floating_point():  # e.g. BatchNorm's integer counter
            raise ModelError(f"{path}: {what} entry {key} has dtype {value.dtype}, expected {ref.dtype}")


def load_encoder_weights(path: str | Path, width: float = 1.0) -> Encoder:
    """Load a plain state dict (torch or .safetensors) strictly into a frozen, eval-mode Encoder.

    Only tensors are deserialised (`weights_only=True`), so a weight file cannot run code.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: encoder weights file does not exist")
    state = _read_state_dict(path)
    encoder = Encoder(width=width)
    check_state_dict(path, state, encoder, "encoder weights")
    encoder.load_state_dict(state, strict=True)
    encoder.eval().requires_grad_(False)
    n_params = sum(p.numel() for p in encoder.parameters())
    log.info("loaded encoder %s (width %g, %.2f M params)", path, width, n_params / 1e6)
    return encoder

