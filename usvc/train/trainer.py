"""Head training on the buffer with ACE's reprojection loss (mapping).

Depth bounds and the invalid-prediction depth are given in units of the scene's median depth,
so one configuration serves metric scenes and scenes in arbitrary SfM units alike (ACE's
0.1 m / 10 m / 1000 m at a typical indoor median depth of 2 m are 0.05 / 5 / 500).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
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
from usvc.train.adabelief import AdaBelief
from usvc.train.bundle_loss import bundle_loss
from usvc.train.group_sampler import GroupSampler
from usvc.train.options import TrainOptions
from usvc.train.reprojection_loss import project_samples, reprojection_loss
from usvc.train.schedule import circle_threshold

log = logging.getLogger(__name__)

def mapping_center(buf: TrainingBuffer) -> np.ndarray:
    """Mean camera centre of the mapping images (ACE's scene centre); rolls keep the centre."""
    centres = camera_centers(buf.view_R, buf.view_t)
    _, first = np.unique(buf.view_image, return_index=True)
    return centres[first].mean(axis=0)


@torch.inference_mode()
def heldout_fit(head: Head, buf: TrainingBuffer, precision: str, depth_min: float, device: str = "cpu",
                chunk: int = 16384) -> dict[str, float]:
    """How well the head fits cells it never trained on (a held-out buffer, `buffer.holdout_every`):
    median L1 reprojection error (px) of the cells predicted in front of the camera, and the share
    of all cells within 10 px."""
    errors = []
    Rv, tv = torch.from_numpy(buf.view_R).float(), torch.from_numpy(buf.view_t).float()
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


def _optimizer(opts: TrainOptions, params) -> tuple[torch.optim.Optimizer, Any]:
    if opts.optimizer == "adamw":
        optim: torch.optim.Optimizer = torch.optim.AdamW(params, lr=opts.lr, weight_decay=opts.weight_decay)
    else:
        optim = AdaBelief(params, lr=opts.lr, weight_decay=opts.weight_decay)
    if opts.schedule == "one_cycle":
        sched = torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=opts.lr, total_steps=opts.iterations,
                                                    pct_start=opts.warmup_fraction)
    else:
        sched = torch.optim.lr_scheduler.LambdaLR(optim, lambda _: 1.0)
    return optim, sched


def train_head(buf: TrainingBuffer, median_depth: float, opts: TrainOptions, *, head_width: int,
               head_blocks: int, seed: int = 0, device: str = "cpu",
               heldout: TrainingBuffer | None = None) -> tuple[Head, dict[str, Any]]:
    """Fit a fresh head (`head_width` channels, `head_blocks` residual blocks: the caller passes
    `ModelOptions`' values; no defaults here) to the buffer; returns it and training statistics.
    `seed` fixes the head's initialisation and the batches. The head's products run at
    `opts.precision` (resolved for `device`; the statistics say which); the losses, master weights
    and optimizer state stay fp32. With `heldout` (cells of mapping images the buffer withheld) and
    `opts.validate_every`, the statistics carry the held-out fit over training; it reads the head
    only, so the trained head is the same with or without it."""
    check(opts, "train")
    precision = resolve_precision(opts.precision, device)
    if not (np.isfinite(median_depth) and median_depth > 0):
        raise UsvcError(f"training needs a positive median scene depth, got {median_depth}")
    n = len(buf.features)
    opts = replace(opts, iterations=opts.steps_for(n))
    if n < opts.batch_size:
        raise UsvcError(f"the buffer has {n} cells, fewer than one batch ({opts.batch_size}); "
                        "raise buffer.size or lower train.batch_size")
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
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    head = Head(in_channels=buf.features.shape[1], width=head_width, num_blocks=head_blocks)
    head.set_scene_center(mapping_center(buf))
    head.to(device).train()

    feats = torch.from_numpy(buf.features)  # fp16; batches are cast on the fly
    pixels = torch.from_numpy(buf.pixels).float()
    view = torch.from_numpy(buf.view_index.astype(np.int64))
    Rv = torch.from_numpy(buf.view_R).float()
    tv = torch.from_numpy(buf.view_t).float()
    Kv = torch.from_numpy(buf.view_K).float()
    Kinv = torch.linalg.inv(Kv)
    depth_min, depth_max = opts.depth_min_rel * median_depth, opts.depth_max_rel * median_depth
    invalid_depth = opts.invalid_depth_rel * median_depth

    if sampler is not None:
        kp_feats = torch.from_numpy(buf.kp_features)
        kp_pixels = torch.from_numpy(buf.kp_pixels).float()
        kp_view = torch.from_numpy(buf.kp_view.astype(np.int64))
    bundle_history: list[tuple[float, float]] = []

    optim, sched = _optimizer(opts, head.parameters())
    order = torch.randperm(n, generator=gen)
    cursor = 0
    history: list[tuple[float, float, float]] = []
    validation: list[dict[str, float]] = []
    start = time.perf_counter()
    bar = tqdm(range(opts.iterations), desc="train", unit="it")
    for it in bar:
        if cursor + opts.batch_size > n:
            order, cursor = torch.randperm(n, generator=gen), 0
        idx = order[cursor:cursor + opts.batch_size]
        cursor += opts.batch_size
        v = view[idx]
        x = feats[idx].to(device=device, dtype=torch.float32)
        if sampler is not None:
            rows, sizes = sampler.next()
            rows_t = torch.from_numpy(rows)
            x = torch.cat([x, kp_feats[rows_t].to(device=device, dtype=torch.float32)])
        with autocast(precision, device):
            pred = head.forward_flat(x)
        tau = circle_threshold(it, opts.iterations, opts.threshold_start, opts.threshold_end)
        pix_loss, stats = reprojection_loss(
            pred[:len(idx)], pixels[idx].to(device), Rv[v].to(device), tv[v].to(device), Kv[v].to(device),
            Kinv[v].to(device), tau, depth_min=depth_min, depth_max=depth_max,
            max_reproj=opts.max_reproj_px, invalid_depth=invalid_depth)
        loss = opts.reproj_weight * pix_loss
        if sampler is not None:
            kv = kp_view[rows_t]
            b_loss, b_stats = bundle_loss(
                pred[len(idx):], torch.from_numpy(sizes), kp_pixels[rows_t].to(device), Rv[kv].to(device),
                tv[kv].to(device), Kv[kv].to(device), Kinv[kv].to(device), tau, form=opts.bundle_loss,
                depth_min=depth_min, depth_max=depth_max, invalid_depth=invalid_depth, max_reproj=opts.max_reproj_px)
            loss = loss + opts.bundle_weight * b_loss
            bundle_history.append((float(b_loss.detach()), float(b_stats["reproj_median"])))
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        sched.step()
        if not torch.isfinite(loss):
            raise UsvcError(f"training diverged at iteration {it} (loss {float(loss)}); lower train.lr")
        history.append((float(pix_loss.detach()), float(stats["valid_fraction"]), float(stats["reproj_median"])))
        if heldout is not None and opts.validate_every and ((it + 1) % opts.validate_every == 0
                                                            or it + 1 == opts.iterations):
            fit = heldout_fit(head, heldout, precision, depth_min, device)
            validation.append({"iteration": it + 1, **fit})
            log.debug("iteration %d: held-out median reprojection %.2f px, %.1f %% within 10 px", it + 1,
                      fit["median_reprojection_px"], 100 * fit["within_10px"])
        if it % 50 == 0:
            bar.set_postfix(loss=f"{history[-1][0]:.2f}", valid=f"{history[-1][1]:.2f}",
                            px=f"{history[-1][2]:.1f}", tau=f"{tau:.1f}")
    seconds = time.perf_counter() - start
    head.eval()
    tail = np.array(history[-max(1, len(history) // 20):])
    summary = {
        "iterations": opts.iterations,
        "precision": precision,
        "samples_seen": opts.iterations * opts.batch_size,
        "epochs": round(opts.iterations * opts.batch_size / n, 2),
        "final_loss": float(tail[:, 0].mean()),
        "final_valid_fraction": float(tail[:, 1].mean()),
        "final_reproj_median_px": float(np.nanmean(tail[:, 2])),
        "train_seconds": seconds,
        "samples_per_second": opts.iterations * opts.batch_size / seconds,
        "median_depth": float(median_depth),
        "loss_curve": [float(np.mean([h[0] for h in history[i:i + 100]])) for i in range(0, len(history), 100)],
        "bundle_weight": opts.bundle_weight,
    }
    if validation:
        summary["heldout_cells"] = len(heldout.features)
        summary["heldout_curve"] = validation
    if sampler is not None:
        btail = np.array(bundle_history[-max(1, len(bundle_history) // 20):])
        summary.update({
            "bundle_groups": sampler.num_groups,
            "bundle_group_epochs": round(opts.iterations * sampler.groups_per_batch / sampler.num_groups, 2),
            "final_bundle_loss": float(btail[:, 0].mean()),
            "final_bundle_reproj_median_px": float(np.nanmean(btail[:, 1])),
            "bundle_loss_curve": [float(np.mean([h[0] for h in bundle_history[i:i + 100]]))
                                  for i in range(0, len(bundle_history), 100)],
        })
    log.info("trained head (%s): %d it x %d in %.1f s, final loss %.3f, valid %.3f, median reprojection %.2f px",
             precision, opts.iterations, opts.batch_size, seconds, summary["final_loss"], summary["final_valid_fraction"],
             summary["final_reproj_median_px"])
    return head, summary

