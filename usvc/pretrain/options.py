"""Options of encoder pretraining (`usvc pretrain-encoder`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PretrainOptions:
    encoder_width: float = 1.0
    n_scenes: int = 32
    first_seed: int = 1000
    frames_per_scene: int = 40
    head_width: int = 256
    iterations: int = 1500
    batch: int = 8  # crops per iteration, each from a different room
    crop_h: int = 120
    crop_w: int = 160
    scale_min: float = 1 / 1.5
    scale_max: float = 1.5
    lr: float = 1e-3
    weight_decay: float = 1e-4
    loss_clamp: float = 2.0  # metres; a cell this wrong pulls no harder
    seed: int = 0
    threads: int = 0  # torch CPU threads, 0 = torch's default
    objective: str = "contrastive"  # contrastive (cell matching across views) | regression (one head per room)
    pair_max_gap: int = 3  # contrastive: the second view is at most this many frames away
    positive_radius: float = 0.05  # contrastive: cells whose surface points are this close match (m)
    negative_radius: float = 0.3  # contrastive: cells nearer than this (but not the match) are ignored
    temperature: float = 0.07
    init_weights: str = ""  # start from this encoder file (e.g. a shipped encoder) instead of random weights
    real_scenes: str = ""  # comma-separated scene folders (data/<scene>): their mapping images and SfM tracks join the corpus
    real_holdout_every: int = 0  # withhold the mapping images the buffer withholds with buffer.holdout_every
