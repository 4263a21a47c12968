"""Training pairs for encoder pretraining: scale-augmented crops aligned to the cell grid, two
nearby frames of one room, and which cells of the two see the same surface point."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from usvc.model.encoder import OUTPUT_STRIDE
from usvc.pretrain.options import PretrainOptions
from usvc.pretrain.pretrain_data import CorpusScene


def crop_view(scene: CorpusScene, frame: int, opts: PretrainOptions, rng: np.random.Generator
          ) -> tuple[np.ndarray, np.ndarray]:
    """(crop luma (h, w), target xyz per cell (h/8, w/8, 3) with NaN where invalid)."""
    gray = scene.gray[frame]
    H, W = gray.shape
    s = rng.uniform(opts.scale_min, opts.scale_max)
    s = max(s, opts.crop_h / H + 1e-3, opts.crop_w / W + 1e-3)
    nh, nw = int(round(H * s)), int(round(W * s))
    image = cv2.resize(gray, (nw, nh), interpolation=cv2.INTER_LINEAR)
    y0 = int(rng.integers(0, (nh - opts.crop_h) // OUTPUT_STRIDE + 1)) * OUTPUT_STRIDE
    x0 = int(rng.integers(0, (nw - opts.crop_w) // OUTPUT_STRIDE + 1)) * OUTPUT_STRIDE
    crop = image[y0:y0 + opts.crop_h, x0:x0 + opts.crop_w]
    a, b = rng.uniform(0.8, 1.2), rng.uniform(-0.1, 0.1)  # contrast, brightness
    crop = np.clip((crop - 0.5) * a + 0.5 + b, 0.0, 1.0)
    hc, wc = opts.crop_h // OUTPUT_STRIDE, opts.crop_w // OUTPUT_STRIDE
    # Cell centre in the resized image (0-indexed pixel y0 + 8i + 4) -> nearest source pixel.
    ys = np.rint((y0 + OUTPUT_STRIDE * np.arange(hc) + 4 + 0.5) * (H / nh) - 0.5).astype(int)
    xs = np.rint((x0 + OUTPUT_STRIDE * np.arange(wc) + 4 + 0.5) * (W / nw) - 0.5).astype(int)
    target = scene.xyz[frame][np.ix_(np.clip(ys, 0, H - 1), np.clip(xs, 0, W - 1))].astype(np.float32)
    return crop.astype(np.float32), target


def cell_correspondences(xa: torch.Tensor, xb: torch.Tensor, positive_radius: float
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Surface-point distances between the cells of two views, (h, w, 3) each with NaN = no point.

    Returns (dist (Na, Nb) with inf for cells of b without a point, match: the nearest cell of b
    per cell of a, anchor: cells of a whose nearest lies within `positive_radius`, ok_b).
    """
    xa, xb = xa.reshape(-1, 3), xb.reshape(-1, 3)
    ok_a, ok_b = torch.isfinite(xa).all(1), torch.isfinite(xb).all(1)
    dist = torch.cdist(torch.nan_to_num(xa, 1e6), torch.nan_to_num(xb, -1e6))
    dist[:, ~ok_b] = float("inf")
    nearest, match = dist.min(dim=1)
    return dist, match, ok_a & (nearest < positive_radius), ok_b


def pair_frames(scene: CorpusScene, opts: PretrainOptions, rng: np.random.Generator) -> tuple[int, int]:
    """Two nearby frames: of one mapping sequence (synthetic rooms have two of equal length), or a
    frame and one of the frames sharing most tracks with it (real captures)."""
    if scene.partners is not None:
        a = int(rng.choice([i for i, p in enumerate(scene.partners) if len(p)]))
        return a, int(rng.choice(scene.partners[a]))
    seq_len = max(1, len(scene.gray) // 2)
    a = int(rng.integers(len(scene.gray)))
    lo, hi = (a // seq_len) * seq_len, min(len(scene.gray), (a // seq_len + 1) * seq_len)
    b = int(np.clip(a + rng.integers(-opts.pair_max_gap, opts.pair_max_gap + 1), lo, hi - 1))
    return a, b
