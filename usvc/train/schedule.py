"""The schedules of head training: the learning rate and beta1 of every step, and the "circle"
schedule of the reprojection loss's soft-clamp threshold (ACE).

The rate and beta1 follow torch's OneCycleLR (the default) or stay constant; they are worked out
here in closed form, with OneCycleLR's own arithmetic (tests/test_train_device.py holds the two
equal, value for value), because building any torch optimizer or scheduler loads torch's compiler
(torch._dynamo), seconds of every training run's start.

The threshold:

tau(t) = (1 - w(t)) * start + end,  w(t) = 1 - sqrt(1 - (t / T)^2).

``start`` is the part of the threshold that decays and ``end`` the floor, so tau(0) = start + end
(51 px with train's defaults, 50 + 1) and tau(T) = end (1 px). The quarter-circle keeps the threshold wide for
most of training, letting coarse predictions still pull towards the pixel, and tightens it fast
at the end, when the map only needs refining.
"""

from __future__ import annotations

import math

import torch

ONE_CYCLE_DIV = 25.0  # OneCycleLR's defaults: start at lr / 25, end at that / 1e4,
ONE_CYCLE_FINAL_DIV = 1e4
BETA1_LOW, BETA1_HIGH = 0.85, 0.95  # and beta1 cycled between these against the rate
CONSTANT_BETA1 = 0.9  # AdamW's default beta1, kept by the constant schedule


def _annealing_cos(start: float, end: float, pct: float) -> float:
    """Cosine from `start` to `end` as pct goes 0 -> 1 (OneCycleLR's, operation for operation)."""
    return end + (start - end) / 2.0 * (math.cos(math.pi * pct) + 1)


def one_cycle(lr: float, steps: int, warmup_fraction: float) -> tuple[list[float], list[float]]:
    """(rate, beta1) of each of `steps` steps under torch's OneCycleLR(max_lr=lr,
    total_steps=steps, pct_start=warmup_fraction) with its defaults (cosine, two phases): the rate
    rises from lr / 25 to lr over the warm-up and falls to lr / 2.5e5 by the last step; beta1 falls
    from 0.95 to 0.85 and rises back against it."""
    if steps < 1:
        raise ValueError(f"the one-cycle schedule needs at least one step, got {steps}")
    initial = lr / ONE_CYCLE_DIV
    phases = ((float(warmup_fraction * steps) - 1, initial, lr, BETA1_HIGH, BETA1_LOW),
              (float(steps - 1), lr, initial / ONE_CYCLE_FINAL_DIV, BETA1_LOW, BETA1_HIGH))
    lrs, beta1s = [], []
    for step in range(steps):
        start = 0.0
        for i, (end, lr_from, lr_to, b_from, b_to) in enumerate(phases):
            if step <= end or i == len(phases) - 1:
                pct = (step - start) / (end - start) if end != start else 1.0
                lrs.append(_annealing_cos(lr_from, lr_to, pct))
                beta1s.append(_annealing_cos(b_from, b_to, pct))
                break
            start = end
    return lrs, beta1s


def rate_and_beta1(schedule: str, lr: float, steps: int, warmup_fraction: float) -> tuple[list[float], list[float]]:
    """Every step's learning rate and beta1: `one_cycle` (above) or `constant` (lr, and 0.9)."""
    if schedule == "one_cycle":
        return one_cycle(lr, steps, warmup_fraction)
    if schedule == "constant":
        return [lr] * steps, [CONSTANT_BETA1] * steps
    raise ValueError(f"unknown schedule {schedule!r} (one_cycle | constant)")


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
