"""The "circle" schedule of the reprojection loss's soft-clamp threshold (ACE).

tau(t) = (1 - w(t)) * start + end,  w(t) = 1 - sqrt(1 - (t / T)^2).

``start`` is the part of the threshold that decays and ``end`` the floor, so tau(0) = start + end
(51 px with train's defaults, 50 + 1) and tau(T) = end (1 px). The quarter-circle keeps the threshold wide for
most of training, letting coarse predictions still pull towards the pixel, and tightens it fast
at the end, when the map only needs refining.
"""

from __future__ import annotations

import math

import torch


def circle_threshold(
    t: int | float | torch.Tensor, total: int, start: float, end: float
) -> float | torch.Tensor:
    """Threshold in pixels at iteration ``t`` of ``total``; t is clamped to [0, total]. ``start``
    and ``end`` are `TrainOptions.threshold_start` and `threshold_end` (no defaults here).

    Returns a float for a scalar t and a tensor (same device, floating dtype) for a tensor t.
    1 - w(t) is evaluated as sqrt((T - t)(T + t)) / T, which stays accurate in fp32 near T.
    """
    if total <= 0:
        raise ValueError(f"total iterations must be positive, got {total}")
    if isinstance(t, torch.Tensor):
        left = (total - t.to(torch.promote_types(t.dtype, torch.float32))).clamp(0.0, total)
        return torch.sqrt(left * (2 * total - left)) / total * start + end
    left = min(max(total - float(t), 0.0), float(total))
    return math.sqrt(left * (2 * total - left)) / total * start + end
