"""Options of head training (the `train` config group): ACE's reprojection loss L_pi plus the
multi-view bundle loss, lambda_pi L_pi + lambda_B L_B (paper eq. 8)."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import in_range, non_negative, one_of, positive
from usvc.core.precision import PRECISIONS

OPTIMIZERS = ("adamw", "adabelief")
SCHEDULES = ("one_cycle", "constant")
BUNDLE_FORMS = ("tanh", "squared")


@dataclass
class TrainOptions:
    """Head training with ACE's reprojection loss plus the multi-view bundle loss (paper eq. 8).
    Depth bounds are in units of the median scene depth."""

    iterations: int = 0  # optimiser steps; 0 = passes over the buffer (steps_for), so training grows with the buffer
    passes: float = 3.90625  # iterations=0: passes x buffer cells / batch_size steps (500 on the smallest buffer, 262,144 cells; train=long: 4x, train=full: 12x)
    batch_size: int = 2048  # buffer cells per step
    optimizer: str = "adamw"  # adamw | adabelief
    lr: float = 5e-3  # peak learning rate of the one-cycle schedule, or the constant one
    schedule: str = "one_cycle"  # one_cycle | constant
    warmup_fraction: float = 0.3  # one_cycle: fraction of the steps spent rising to lr
    weight_decay: float = 0.01  # decoupled weight decay
    threshold_start: float = 50.0  # reprojection threshold tau (px) goes from threshold_start + threshold_end ...
    threshold_end: float = 1.0  # ... down to threshold_end over training (ACE's circle schedule)
    depth_min_rel: float = 0.05  # predictions nearer than this (x the median scene depth) are invalid
    depth_max_rel: float = 500.0  # predictions farther than this (x the median depth) are invalid
    invalid_depth_rel: float = 5.0  # invalid predictions are pulled to this depth (x the median depth) on their pixel ray
    max_reproj_px: float = 1000.0  # reprojection errors above this count as invalid
    reproj_weight: float = 1.0  # lambda_pi (paper eq. 8)
    bundle_weight: float = 0.25  # lambda_B (paper eq. 8, where it is 1.0); 0 = ACE-style single-view training; the method group sets it (single: 0)
    bundle_loss: str = "tanh"  # tanh (ACE's soft clamp, sharing the threshold schedule) | squared (eq. 7 as printed)
    bundle_groups_per_batch: int = 64  # whole keypoint groups mixed into every batch of pixel samples
    bundle_obs_per_group: int = 16  # observations drawn per group (all of them when fewer)
    precision: str = "auto"  # the head's products: auto (bf16 where native and faster, else fp32) | bf16 | fp32
    report_every: int = 100  # steps between reads of the statistics from the device (progress, divergence check); none in between
    validate_every: int = 500  # held-out reprojection every this many steps, when the buffer has held-out views (buffer.holdout_every > 0); 0 = never
    cuda_graph: bool = True  # on CUDA with adamw: each step (forward, losses, backward, optimizer) replayed as one captured graph; false = step by step

    def problems(self) -> list[str]:
        out = one_of(self, "optimizer", OPTIMIZERS) + one_of(self, "schedule", SCHEDULES)
        out += one_of(self, "bundle_loss", BUNDLE_FORMS) + one_of(self, "precision", PRECISIONS)
        out += non_negative(self, "validate_every", "iterations")
        out += positive(self, "passes", "batch_size", "report_every", "lr", "reproj_weight", "bundle_groups_per_batch",
                        "bundle_obs_per_group")
        out += in_range(self, "warmup_fraction", 0.0, 1.0, high_open=True)
        if self.passes == float("inf"):
            out.append("passes=inf must be finite")
        if self.bundle_weight < 0:
            out.append(f"bundle_weight={self.bundle_weight!r} must be >= 0")
        if not 0 < self.depth_min_rel < self.invalid_depth_rel < self.depth_max_rel:
            out.append("need 0 < depth_min_rel < invalid_depth_rel < depth_max_rel")
        return out

    def steps_for(self, cells: int) -> int:
        """Optimiser steps on a buffer of `cells`: `iterations` when set, else `passes` over it."""
        return self.iterations or max(1, round(self.passes * cells / self.batch_size))
