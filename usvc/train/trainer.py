"""Head training on the buffer with ACE's reprojection loss (mapping).

Depth bounds and the invalid-prediction depth are given in units of the scene's median depth,
so one configuration serves metric scenes and scenes in arbitrary SfM units alike (ACE's
0.1 m / 10 m / 1000 m at a typical indoor median depth of 2 m are 0.05 / 5 / 500).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from usvc.buffer.buffer_file import TrainingBuffer
from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers
from usvc.core.options import check
from usvc.core.precision import autocast, resolve_precision
from usvc.model.head import Head
from usvc.train import fused_adamw
from usvc.train.adabelief import AdaBelief
from usvc.train.fused_adamw import FusedAdamW
from usvc.train.graph_adamw import GraphAdamW
from usvc.train.group_sampler import GroupSampler
from usvc.train.options import TrainOptions
from usvc.train.reprojection_loss import project_samples
from usvc.train.schedule import circle_threshold, rate_and_beta1
from usvc.train.train_step import DeviceBuffer, StepRunner, TrainStep

log = logging.getLogger(__name__)

def mapping_center(buf: TrainingBuffer) -> np.ndarray:
    """Mean camera centre of the mapping images (ACE's scene centre); rolls keep the centre."""
    centres = camera_centers(buf.view_R_world_to_cam, buf.view_t_world_to_cam)
    _, first = np.unique(buf.view_image, return_index=True)
    return centres[first].mean(axis=0)


@torch.inference_mode()
def heldout_fit(head: Head, buf: TrainingBuffer, precision: str, depth_min: float, device: str = "cpu",
                chunk: int = 16384) -> dict[str, float]:
    """How well the head fits cells it never trained on (a held-out buffer, `buffer.holdout_every`):
    median L1 reprojection error (px) of the cells predicted in front of the camera, and the share
    of all cells within 10 px."""
    errors = []
    Rv, tv = torch.from_numpy(buf.view_R_world_to_cam).float(), torch.from_numpy(buf.view_t_world_to_cam).float()
    Kv = torch.from_numpy(buf.view_K).float()
    for lo in range(0, len(buf.features), chunk):
        x = torch.from_numpy(buf.features[lo:lo + chunk]).to(device=device, dtype=torch.float32)
        with autocast(precision, device):
            xyz = head.forward_flat(x)
        v = torch.from_numpy(buf.view_index[lo:lo + chunk].astype(np.int64))
        uv = torch.from_numpy(buf.pixels[lo:lo + chunk]).float().to(device)
        K = Kv[v].to(device)
        z, proj, _ = project_samples(xyz.float(), uv, Rv[v].to(device), tv[v].to(device), K, torch.linalg.inv(K),
                                     depth_min, 1.0)
        err = (proj - uv).abs().sum(dim=1)
        errors.append(torch.where(z >= depth_min, err, torch.full_like(err, float("inf"))).cpu())
    err = torch.cat(errors).numpy()
    valid = np.isfinite(err)
    return {"median_reprojection_px": float(np.median(err[valid])) if valid.any() else float("nan"),
            "within_10px": float((err <= 10.0).mean())}


def _optimizer(opts: TrainOptions, params, device: str) -> torch.optim.Optimizer | GraphAdamW | FusedAdamW:
    if opts.optimizer == "adabelief":
        return AdaBelief(params, lr=opts.lr, weight_decay=opts.weight_decay)
    if device.startswith("cuda"):
        # The rate and beta1 (the one-cycle schedule moves both) live on the device and are refilled
        # every step: a step reads nothing from the host, so it can be replayed as a CUDA graph.
        return GraphAdamW(params, lr=opts.lr, weight_decay=opts.weight_decay)
    # Fused: one kernel over each parameter instead of a dozen tensor ops (the update was ~8 % of a
    # CPU step); elementwise, so the same bits for any thread count. Torch's own kernel, called
    # without torch.optim, which would load torch's compiler first (seconds of every start).
    if fused_adamw.available():
        return FusedAdamW(params, lr=opts.lr, weight_decay=opts.weight_decay)
    return torch.optim.AdamW(params, lr=opts.lr, weight_decay=opts.weight_decay, fused=True)


def schedule_values(opts: TrainOptions) -> tuple[list[float], list[float]]:
    """The learning rate and beta1 of every step, as torch's scheduler sets them (one_cycle:
    OneCycleLR, which also cycles beta1 between 0.95 and 0.85 against the rate; constant: lr and
    0.9), worked out once (`usvc.train.schedule`) so that the loop only sets two numbers a step."""
    return rate_and_beta1(opts.schedule, opts.lr, opts.iterations, opts.warmup_fraction)


def _set_schedule(optim: torch.optim.Optimizer | GraphAdamW | FusedAdamW, lr: float, beta1: float) -> None:
    if isinstance(optim, (GraphAdamW, FusedAdamW)):
        optim.set_schedule(lr, beta1)
        return
    for group in optim.param_groups:
        group["lr"], group["betas"] = lr, (beta1, *group["betas"][1:])


def read_back(values: torch.Tensor) -> np.ndarray:
    """The one way the training loop reads the device: every `report_every` steps, the block's
    statistics at once (one synchronisation per block, none per step)."""
    return values.detach().cpu().numpy()


@dataclass
class _Block:
    """A block of training steps drawn on the host and sent to the device in one copy each: the
    pixel samples' buffer rows and, for the bundle loss, each step's keypoint groups padded to one
    width (observation rows and their mask)."""

    idx: torch.Tensor  # (steps, batch) buffer rows
    rows: torch.Tensor | None = None  # (steps, groups, width) keypoint observation rows
    mask: torch.Tensor | None = None  # (steps, groups, width): True where an observation is


def _to_device(array: np.ndarray | torch.Tensor, device: str) -> torch.Tensor:
    """Host indices to the device in one copy that does not wait for the queued steps (pinned)."""
    t = torch.as_tensor(array)
    if device.startswith("cuda"):
        return t.pin_memory().to(device, non_blocking=True)  # no wait for the queued steps
    return t


class _BatchDraw:
    """The batches, drawn on the host from the seed (the same draws whatever the device): a fresh
    permutation of the buffer every pass, and the keypoint groups of the bundle loss."""

    def __init__(self, n: int, batch_size: int, gen: torch.Generator, sampler: GroupSampler | None) -> None:
        self.n, self.batch_size, self.gen, self.sampler = n, batch_size, gen, sampler
        self.order = torch.randperm(n, generator=gen)
        self.cursor = 0

    def block(self, steps: int, device: str) -> _Block:
        idx = []
        for _ in range(steps):
            if self.cursor + self.batch_size > self.n:
                self.order, self.cursor = torch.randperm(self.n, generator=self.gen), 0
            idx.append(self.order[self.cursor:self.cursor + self.batch_size])
            self.cursor += self.batch_size
        block = _Block(idx=_to_device(torch.stack(idx), device))
        if self.sampler is None:
            return block
        rows, mask = zip(*(self.sampler.next() for _ in range(steps)))
        block.rows = _to_device(np.stack(rows), device)
        block.mask = _to_device(np.stack(mask), device)
        return block


def batch_draw(buf: TrainingBuffer, opts: TrainOptions, seed: int) -> _BatchDraw:
    """The batches `train_head` draws for `seed`: the cells' permutations and, with the bundle loss,
    its keypoint groups (one clear error where the buffer has none to give)."""
    sampler = None
    if opts.bundle_weight > 0:
        if not buf.has_keypoints:
            raise UsvcError("train.bundle_weight > 0 (method=multiview) needs keypoint observations in the "
                            "buffer; rebuild it with the buffer stage, or use method=single")
        try:
            sampler = GroupSampler(buf.kp_id, buf.kp_view, opts.bundle_groups_per_batch,
                                   opts.bundle_obs_per_group, np.random.default_rng([seed, 2]))
        except ValueError as exc:
            raise UsvcError(f"bundle loss: {exc}") from exc
    return _BatchDraw(len(buf.features), opts.batch_size, torch.Generator().manual_seed(seed), sampler)


@contextlib.contextmanager
def _deterministic(device: str) -> Iterator[None]:
    """Same seed and device, same map: on CUDA, torch's deterministic kernels (the bundle loss's
    gradient adds repeated rows; atomics would add them in any order). The CPU's are already."""
    if not device.startswith("cuda"):
        yield
        return
    before, warn_only = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    _set_deterministic(True, warn_only=True)
    try:
        yield
    finally:
        _set_deterministic(before, warn_only=warn_only)


def _set_deterministic(mode: bool, warn_only: bool) -> None:
    """torch.use_deterministic_algorithms for eager kernels, the only ones training runs: torch's
    own function also sets its compiler's flag, and importing the compiler for it (torch._inductor,
    torch._dynamo) takes seconds of every training start on a GPU machine."""
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(mode, warn_only=warn_only)


# Columns of the per-step statistics kept on the device: total loss, pixel loss, valid fraction,
# median reprojection, bundle loss, bundle median reprojection.
_TOTAL, _PIX, _VALID, _PX, _BUNDLE, _BUNDLE_PX = range(6)


def train_head(buf: TrainingBuffer, median_depth: float, opts: TrainOptions, *, head_width: int,
               head_blocks: int, seed: int = 0, device: str = "cpu",
               heldout: TrainingBuffer | None = None) -> tuple[Head, dict[str, Any]]:
    """Fit a fresh head (`head_width` channels, `head_blocks` residual blocks: the caller passes
    `ModelOptions`' values; no defaults here) to the buffer; returns it and training statistics.
    `seed` fixes the head's initialisation and the batches. The head's products run at
    `opts.precision` (resolved for `device`; the statistics say which); the losses, master weights
    and optimizer state stay fp32. With `heldout` (cells of mapping images the buffer withheld) and
    `opts.validate_every`, the statistics carry the held-out fit over training; it reads the head
    only, so the trained head is the same with or without it.

    The buffer and the per-view cameras go to `device` once; batches are drawn on the host a block
    of `opts.report_every` steps at a time (the same draws on every device) and sent in one copy,
    the next block while the device runs the queued one; the loop reads nothing back from the
    device but each block's statistics (`read_back`), where the divergence check and the progress
    bar look."""
    check(opts, "train")
    precision = resolve_precision(opts.precision, device)
    if not (np.isfinite(median_depth) and median_depth > 0):
        raise UsvcError(f"training needs a positive median scene depth, got {median_depth}")
    n = len(buf.features)
    opts = replace(opts, iterations=opts.steps_for(n))
    if n < opts.batch_size:
        raise UsvcError(f"the buffer has {n} cells, fewer than one batch ({opts.batch_size}); "
                        "raise buffer.size or lower train.batch_size")
    draw = batch_draw(buf, opts, seed)
    sampler = draw.sampler
    torch.manual_seed(seed)
    head = Head(in_channels=buf.features.shape[1], width=head_width, num_blocks=head_blocks)
    head.set_scene_center(mapping_center(buf))
    head.to(device).train()
    optim = _optimizer(opts, head.parameters(), device)
    step = TrainStep(head, optim, DeviceBuffer.of(buf, device, keypoints=sampler is not None), opts, precision,
                     device, median_depth)
    run = StepRunner(step, optim, device, opts)
    lrs, beta1s = schedule_values(opts)
    steps = torch.full((opts.iterations, 6), float("nan"), device=device)  # per-step statistics, on the device
    history = np.full((opts.iterations, 6), np.nan)
    validation: list[dict[str, float]] = []
    start = time.perf_counter()
    bar = tqdm(total=opts.iterations, desc="train", unit="it")
    with _deterministic(device):
        block = draw.block(min(opts.report_every, opts.iterations), device)
        for lo in range(0, opts.iterations, opts.report_every):
            hi = min(lo + opts.report_every, opts.iterations)
            no_groups = block.idx[:, :0]
            for it in range(lo, hi):
                k = it - lo
                inputs = (block.idx[k], *((block.rows[k], block.mask[k]) if sampler is not None
                                         else (no_groups[k], no_groups[k])))
                tau = circle_threshold(it, opts.iterations, opts.threshold_start, opts.threshold_end)
                step.tau.fill_(tau)
                _set_schedule(optim, lrs[it], beta1s[it])
                steps[it] = run(it, inputs)
                if heldout is not None and opts.validate_every and ((it + 1) % opts.validate_every == 0
                                                                    or it + 1 == opts.iterations):
                    fit = heldout_fit(head, heldout, precision, step.depth_min, device)
                    validation.append({"iteration": it + 1, **fit})
                    log.debug("iteration %d: held-out median reprojection %.2f px, %.1f %% within 10 px", it + 1,
                              fit["median_reprojection_px"], 100 * fit["within_10px"])
            # The next block is drawn while the device works through this one's queued steps (the
            # same draws in the same order: drawing reads nothing the steps write); then the read.
            if hi < opts.iterations:
                block = draw.block(min(hi + opts.report_every, opts.iterations) - hi, device)
            history[lo:hi] = read_back(steps[lo:hi])
            bad = np.flatnonzero(~np.isfinite(history[lo:hi, _TOTAL]))
            if bad.size:
                raise UsvcError(f"training diverged at iteration {lo + int(bad[0])} "
                                f"(loss {history[lo + bad[0], _TOTAL]}); lower train.lr")
            bar.update(hi - lo)
            bar.set_postfix(loss=f"{history[hi - 1, _PIX]:.2f}", valid=f"{history[hi - 1, _VALID]:.2f}",
                            px=f"{history[hi - 1, _PX]:.1f}", tau=f"{tau:.1f}")
    bar.close()
    seconds = time.perf_counter() - start
    head.eval()
    summary = _summary(history, opts, n, precision, seconds, median_depth, sampler,
                       run.note if device.startswith("cuda") else None)
    if validation:
        summary["heldout_cells"] = len(heldout.features)
        summary["heldout_curve"] = validation
    log.info("trained head (%s, %s): %d it x %d in %.1f s, final loss %.3f, valid %.3f, median reprojection %.2f px",
             precision, device, opts.iterations, opts.batch_size, seconds, summary["final_loss"],
             summary["final_valid_fraction"], summary["final_reproj_median_px"])
    return head, summary


def _summary(history: np.ndarray, opts: TrainOptions, n: int, precision: str, seconds: float, median_depth: float,
             sampler: GroupSampler | None, graph_note: str | None) -> dict[str, Any]:
    """The training statistics of `history` (per step, the columns of `TrainStep`): the last 5 %
    of the steps for the final figures, a curve point per 100 steps."""
    tail = history[-max(1, len(history) // 20):]
    summary = {
        "iterations": opts.iterations,
        "precision": precision,
        "samples_seen": opts.iterations * opts.batch_size,
        "epochs": round(opts.iterations * opts.batch_size / n, 2),
        "final_loss": float(tail[:, _PIX].mean()),
        "final_valid_fraction": float(tail[:, _VALID].mean()),
        "final_reproj_median_px": float(np.nanmean(tail[:, _PX])),
        "train_seconds": seconds,
        "samples_per_second": opts.iterations * opts.batch_size / seconds,
        "median_depth": float(median_depth),
        "loss_curve": [float(history[i:i + 100, _PIX].mean()) for i in range(0, len(history), 100)],
        "bundle_weight": opts.bundle_weight,
        "cuda_graph": graph_note,
    }
    if sampler is not None:
        summary.update({
            "bundle_groups": sampler.num_groups,
            "bundle_group_epochs": round(opts.iterations * sampler.groups_per_batch / sampler.num_groups, 2),
            "final_bundle_loss": float(tail[:, _BUNDLE].mean()),
            "final_bundle_reproj_median_px": float(np.nanmean(tail[:, _BUNDLE_PX])),
            "bundle_loss_curve": [float(history[i:i + 100, _BUNDLE].mean()) for i in range(0, len(history), 100)],
        })
    return summary
