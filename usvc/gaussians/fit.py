"""Fitting a 3DGS model to the mapping images: L1 + D-SSIM with adaptive density control, and
held-out evaluation (PSNR/SSIM on every n-th mapping view, which the fit never sees)."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from pytorch_msssim import ssim
from tqdm import tqdm

from usvc.core.errors import UsvcError
from usvc.core.scene import Frame
from usvc.gaussians.densify import (
    DensityStats,
    densify_and_prune,
    reset_opacity,
)
from usvc.gaussians.options import GaussiansOptions
from usvc.splat.gaussians import PARAM_NAMES, Gaussians
from usvc.splat.rasterize import View, render

log = logging.getLogger(__name__)


@dataclass
class FitImage:
    name: str
    view: View
    rgb: torch.Tensor  # (H, W, 3) in [0, 1]


@dataclass
class FitResult:
    gaussians: Gaussians
    metrics: dict


def load_fit_images(frames: list[Frame], width: int) -> list[FitImage]:
    """Mapping images as float RGB at the fit width, intrinsics scaled to match."""
    out = []
    for f in frames:
        if f.camera.model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise UsvcError(f"{f.name}: Gaussian splatting needs an undistorted pinhole camera, got {f.camera.model}")
        bgr = cv2.imread(str(f.image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise UsvcError(f"cannot read mapping image {f.image_path}")
        h, w = bgr.shape[:2]
        if (w, h) != (f.camera.width, f.camera.height):
            raise UsvcError(f"{f.image_path}: image is {w}x{h} but its camera says {f.camera.width}x{f.camera.height}")
        s = 1.0 if width in (0, w) else width / w
        if s != 1.0:
            bgr = cv2.resize(bgr, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        K = np.asarray(f.camera.K, dtype=np.float64).copy()
        K[:2] *= s
        hh, ww = bgr.shape[:2]
        view = View(torch.tensor(f.R, dtype=torch.float32), torch.tensor(f.t, dtype=torch.float32),
                    torch.tensor(K, dtype=torch.float32), ww, hh)
        rgb = torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).float() / 255.0
        out.append(FitImage(f.name, view, rgb))
    return out


def scene_extent(views: list[View]) -> float:
    """Radius of the camera centres around their mean, x1.1 (3DGS's 'cameras extent')."""
    centres = torch.stack([-v.R.T @ v.t for v in views])
    return 1.1 * float((centres - centres.mean(0)).norm(dim=1).max().clamp(min=1e-6))


def split_holdout(images: list[FitImage], every: int) -> tuple[list[FitImage], list[FitImage]]:
    if every <= 0:
        return images, []
    held = [im for i, im in enumerate(images) if i % every == every - 1]
    train = [im for i, im in enumerate(images) if i % every != every - 1]
    if not train:
        raise UsvcError("no mapping image left to fit after holding out every "
                        f"{every}-th one ({len(images)} images)")
    return train, held


def image_loss(pred: torch.Tensor, gt: torch.Tensor, ssim_weight: float) -> torch.Tensor:
    l1 = (pred - gt).abs().mean()
    if ssim_weight == 0:
        return l1
    s = ssim(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], data_range=1.0, size_average=True)
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - s)


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    mse = float(((pred.detach().clamp(0, 1) - gt) ** 2).mean())
    return 10 * math.log10(1.0 / max(mse, 1e-12))


@torch.no_grad()
def evaluate(g: Gaussians, images: list[FitImage], tile: int = 8) -> dict:
    """Mean PSNR (dB) and SSIM over `images`, each rendered at its own fit resolution."""
    if not images:
        return {"psnr": None, "ssim": None, "views": 0}
    ps, ss = [], []
    for im in images:
        out = render(g, im.view, tile=tile)
        ps.append(psnr(out.rgb, im.rgb))
        ss.append(float(ssim(out.rgb.clamp(0, 1).permute(2, 0, 1)[None], im.rgb.permute(2, 0, 1)[None], data_range=1.0)))
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "views": len(images),
            "psnr_per_view": {im.name: p for im, p in zip(images, ps)}}


def fit_gaussians(init: Gaussians, images: list[FitImage], opts: GaussiansOptions, device: str = "cpu") -> FitResult:
    """Optimise `init` against the non-held-out `images`; returns the model and its metrics."""
    t0 = time.perf_counter()
    torch.manual_seed(opts.seed)
    gen = torch.Generator(device=device).manual_seed(opts.seed)
    order_rng = np.random.default_rng(opts.seed)
    train, held = split_holdout(images, opts.holdout_every)
    train = [FitImage(im.name, im.view.to(device), im.rgb.to(device)) for im in train]
    extent = scene_extent([im.view for im in images])
    params = {k: torch.nn.Parameter(v.detach().clone().to(device)) for k, v in init.tensors().items()}
    if init.sh_degree != opts.sh_degree:
        raise UsvcError(f"initial Gaussians have SH degree {init.sh_degree}, the fit is configured for {opts.sh_degree}")
    lrs = {"means": opts.lr_means * extent, "log_scales": opts.lr_scales, "quats": opts.lr_quats,
           "opacity_logits": opts.lr_opacity, "sh_dc": opts.lr_sh_dc, "sh_rest": opts.lr_sh_rest}
    optimizer = torch.optim.Adam([{"params": [params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES], eps=1e-15)
    stats = DensityStats(len(init), device)
    decay = math.log(opts.lr_means_final / opts.lr_means) / max(opts.iterations, 1)
    order: list[int] = []
    losses = []
    for it in tqdm(range(1, opts.iterations + 1), desc="gaussians", unit="it", mininterval=10):
        optimizer.param_groups[0]["lr"] = lrs["means"] * math.exp(decay * it)
        if not order:
            order = order_rng.permutation(len(train)).tolist()
        im = train[order.pop()]
        g = Gaussians(**params)
        degree = min(opts.sh_degree, it // opts.sh_increase_every) if opts.sh_increase_every > 0 else opts.sh_degree
        out = render(g, im.view, sh_degree=degree, tile=opts.tile)
        loss = image_loss(out.rgb, im.rgb, opts.ssim_weight)
        loss.backward()
        losses.append(loss.item())
        with torch.no_grad():
            if it <= opts.densify_until:
                stats.add(out.means2d.grad, out.radii, im.view.width, im.view.height)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if it <= opts.densify_until and it >= opts.densify_from and it % opts.densify_every == 0:
            past_reset = opts.opacity_reset_every > 0 and it > opts.opacity_reset_every
            info = densify_and_prune(params, optimizer, stats, extent, opts, gen, prune_large=past_reset)
            stats = DensityStats(info["total"], device)
            log.debug("iteration %d: %s", it, info)
        if opts.opacity_reset_every > 0 and it % opts.opacity_reset_every == 0 and it <= opts.densify_until:
            reset_opacity(params, optimizer)
        if it % 500 == 0:
            log.info("gaussians: iteration %d, loss %.4f, %d Gaussians", it, np.mean(losses[-100:]), params["means"].shape[0])
    fit_seconds = time.perf_counter() - t0
    model = Gaussians(**{k: v.detach().cpu() for k, v in params.items()})
    held_metrics = evaluate(model.to(device), [FitImage(i.name, i.view.to(device), i.rgb.to(device)) for i in held], opts.tile)
    train_sample = train[:: max(1, len(train) // 8)]
    train_metrics = evaluate(model.to(device), train_sample, opts.tile)
    metrics = {"gaussians": len(model), "iterations": opts.iterations, "fit_seconds": fit_seconds,
               "width": images[0].view.width, "height": images[0].view.height, "fit_views": len(train),
               "extent": extent, "final_loss": float(np.mean(losses[-100:])),
               "heldout_psnr": held_metrics["psnr"], "heldout_ssim": held_metrics["ssim"], "heldout_views": held_metrics["views"],
               "heldout_psnr_per_view": held_metrics.get("psnr_per_view", {}),
               "train_psnr": train_metrics["psnr"], "train_ssim": train_metrics["ssim"]}
    return FitResult(model, metrics)
