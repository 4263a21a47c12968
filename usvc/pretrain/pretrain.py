"""Encoder pretraining, ACE-style: one shared encoder, one small head per room, many rooms.

Because a head has to regress coordinates of its own room, the shared encoder is pushed to
produce features that tell places apart, which is what a frozen encoder must give a new scene.
The corpus has exact depth, so the loss is the Euclidean distance to the true coordinate of
each cell (faster to converge on a CPU than the reprojection loss; the head stage still trains
with the reprojection loss). Crops are scale-augmented and aligned to the 8 px cell grid.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from usvc.core.errors import UsvcError
from usvc.model.encoder import Encoder, load_encoder_weights
from usvc.model.head import Head
from usvc.model.preprocess import INPUT_MEAN, INPUT_STD
from usvc.pretrain.feature_eval import held_out_matching
from usvc.pretrain.options import PretrainOptions
from usvc.pretrain.pairs import cell_correspondences, crop_view, pair_frames
from usvc.pretrain.pretrain_data import CorpusScene, build_corpus
from usvc.pretrain.real_corpus import real_corpus_scene

log = logging.getLogger(__name__)


def contrastive_loss(fa: torch.Tensor, fb: torch.Tensor, xa: torch.Tensor, xb: torch.Tensor,
                     opts: PretrainOptions) -> torch.Tensor:
    """InfoNCE between cells of two views of one room: a cell's positive is the cell of the other
    view whose surface point is nearest (within `positive_radius`); cells of the other view
    farther than `negative_radius` are its negatives. No head and no room memorised: this asks
    the encoder directly for what a frozen SCR encoder must give, distinctive and
    viewpoint-stable local features."""
    fa = torch.nn.functional.normalize(fa.flatten(1).T, dim=1)  # (Na, C)
    fb = torch.nn.functional.normalize(fb.flatten(1).T, dim=1)
    dist, match, anchor, ok_b = cell_correspondences(xa, xb, opts.positive_radius)
    if int(anchor.sum()) == 0:
        return fa.sum() * 0.0
    logits = fa[anchor] @ fb.T / opts.temperature
    ignore = (dist[anchor] < opts.negative_radius) | ~ok_b[None, :]
    ignore[torch.arange(len(logits)), match[anchor]] = False
    logits = logits.masked_fill(ignore, float("-inf"))
    return torch.nn.functional.cross_entropy(logits, match[anchor])


def _contrastive_batch(corpus: list[CorpusScene], opts: PretrainOptions, rng: np.random.Generator,
                       encoder: Encoder, device: str) -> torch.Tensor:
    crops, targets = [], []
    for _ in range(max(1, opts.batch // 2)):
        scene = corpus[int(rng.integers(len(corpus)))]
        for frame in pair_frames(scene, opts, rng):
            crop, target = crop_view(scene, frame, opts, rng)
            crops.append(crop)
            targets.append(target)
    x = torch.from_numpy((np.stack(crops)[:, None] - INPUT_MEAN) / INPUT_STD).float().to(device)
    y = torch.from_numpy(np.stack(targets)).to(device)  # (B, h, w, 3)
    feats = encoder(x)
    losses = [contrastive_loss(feats[k], feats[k + 1], y[k], y[k + 1], opts) for k in range(0, len(crops), 2)]
    return torch.stack(losses).mean()


@torch.inference_mode()
def calibrate_feature_scale(encoder: Encoder, corpus: list[CorpusScene], seed: int = 0, frames: int = 16) -> float:
    """Rescale the output so features vary by ~1 per channel across cells; returns the factor.

    The contrastive loss sees only normalised features, so their scale is arbitrary, while the
    head's first layer and its optimiser expect inputs of order one. The output is
    relu(res2_conv3(.)) + res2_skip(.), positively homogeneous in those two layers, so scaling
    both layers' weights and biases by c scales the features by exactly c.
    """
    rng = np.random.default_rng(seed)
    stds = []
    for _ in range(frames):
        scene = corpus[int(rng.integers(len(corpus)))]
        gray = scene.gray[int(rng.integers(len(scene.gray)))]
        x = torch.from_numpy((gray[None, None] - INPUT_MEAN) / INPUT_STD).float()
        f = encoder(x.to(next(encoder.parameters()).device))[0].flatten(1)
        stds.append(f.std(dim=1).mean().item())
    c = 1.0 / max(float(np.mean(stds)), 1e-12)
    for layer in (encoder.res2_conv3, encoder.res2_skip):
        layer.weight.mul_(c)
        layer.bias.mul_(c)
    log.info("feature scale: per-channel std across cells %.4g -> 1 (factor %.4g)", float(np.mean(stds)), c)
    return c


def pretrain_encoder(opts: PretrainOptions, device: str = "cpu") -> tuple[Encoder, dict[str, Any]]:
    """Train an encoder from scratch on the generated corpus; returns it and its provenance."""
    if opts.objective not in ("regression", "contrastive"):
        raise UsvcError(f"pretrain objective must be 'regression' or 'contrastive', got {opts.objective!r}")
    if opts.threads > 0:
        torch.set_num_threads(opts.threads)
    torch.manual_seed(opts.seed)
    rng = np.random.default_rng(opts.seed)
    t0 = time.perf_counter()
    corpus = build_corpus(opts.n_scenes, opts.first_seed, opts.frames_per_scene) if opts.n_scenes > 0 else []
    real = [real_corpus_scene(Path(d), opts.real_holdout_every) for d in opts.real_scenes.split(",") if d]
    if real and opts.objective != "contrastive":
        raise UsvcError("real_scenes need objective=contrastive (a real capture has no dense coordinates)")
    corpus = corpus + real
    if not corpus:
        raise UsvcError("pretrain corpus is empty: set n_scenes > 0 or real_scenes")
    corpus_seconds = time.perf_counter() - t0

    if opts.init_weights:
        encoder = load_encoder_weights(opts.init_weights, opts.encoder_width).to(device).train().requires_grad_(True)
    else:
        encoder = Encoder(opts.encoder_width).to(device).train()
    heads = torch.nn.ModuleList()
    for scene in (corpus if opts.objective == "regression" else []):
        head = Head(in_channels=encoder.out_channels, width=opts.head_width, num_blocks=1)
        head.set_scene_center(scene.center)
        heads.append(head)
    heads.to(device).train()
    params = list(encoder.parameters()) + list(heads.parameters())
    optim = torch.optim.AdamW(params, lr=opts.lr, weight_decay=opts.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=opts.lr, total_steps=opts.iterations, pct_start=0.1)

    history: list[float] = []
    batch = min(opts.batch, len(corpus))
    t1 = time.perf_counter()
    bar = tqdm(range(opts.iterations), desc="pretrain", unit="it")
    for it in bar:
        if opts.objective == "contrastive":
            loss = _contrastive_batch(corpus, opts, rng, encoder, device)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            sched.step()
            history.append(float(loss.detach()))
            if it % 100 == 0:
                log.info("pretrain it %d/%d loss %.4f (mean of last 100: %.4f)", it, opts.iterations,
                         history[-1], float(np.mean(history[-100:])))
            continue
        scene_ids = rng.choice(len(corpus), size=batch, replace=False)
        crops, targets = [], []
        for sid in scene_ids:
            crop, target = crop_view(corpus[sid], int(rng.integers(len(corpus[sid].gray))), opts, rng)
            crops.append(crop)
            targets.append(target)
        x = torch.from_numpy((np.stack(crops)[:, None] - INPUT_MEAN) / INPUT_STD).float().to(device)
        y = torch.from_numpy(np.stack(targets)).permute(0, 3, 1, 2).to(device)  # (B, 3, h, w)
        feats = encoder(x)
        pred = torch.cat([heads[int(sid)](feats[b:b + 1]) for b, sid in enumerate(scene_ids)])
        dist = (pred - y).norm(dim=1)
        valid = torch.isfinite(dist)
        loss = dist[valid].clamp(max=opts.loss_clamp).mean()
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        sched.step()
        history.append(float(loss.detach()))
        if it % 20 == 0:
            bar.set_postfix(loss=f"{np.mean(history[-50:]):.3f}")
        if it % 100 == 0:
            log.info("pretrain it %d/%d loss %.4f (mean of last 100: %.4f)", it, opts.iterations,
                     history[-1], float(np.mean(history[-100:])))
    train_seconds = time.perf_counter() - t1
    encoder.eval().requires_grad_(False)
    feature_scale = calibrate_feature_scale(encoder, corpus, opts.seed)

    matching = held_out_matching(encoder, opts)
    window = max(1, min(100, len(history)))
    provenance = {
        "options": asdict(opts),
        "corpus": {"rooms": len(corpus), "frames": int(sum(len(s.gray) for s in corpus)),
                   "room_seeds": [int(s.seed) for s in corpus], "generator": "usvc.pretrain.pretrain_data"},
        "loss_first_100": float(np.mean(history[:window])),
        "loss_last_100": float(np.mean(history[-window:])),
        "loss_curve": [float(np.mean(history[i:i + 50])) for i in range(0, len(history), 50)],
        "held_out_matching_top1": matching,
        "feature_scale_applied": feature_scale,
        "corpus_seconds": round(corpus_seconds, 1),
        "train_seconds": round(train_seconds, 1),
        "device": device,
        "torch": torch.__version__,
    }
    log.info("pretrained encoder width %g: loss %.3f -> %.3f in %.0f s", opts.encoder_width,
             provenance["loss_first_100"], provenance["loss_last_100"], train_seconds)
    return encoder, provenance
