"""How well an encoder's cells match across two views of a room it never saw (a quick,
head-free proxy for what a frozen SCR encoder must provide: distinctive, stable features)."""

from __future__ import annotations

import numpy as np
import torch

from usvc.model.encoder import Encoder
from usvc.model.preprocess import INPUT_MEAN, INPUT_STD
from usvc.pretrain.options import PretrainOptions
from usvc.pretrain.pairs import cell_correspondences, crop_view, pair_frames
from usvc.pretrain.pretrain_data import CorpusScene, build_corpus

HELD_OUT_SEEDS = 5000  # corpus rooms use 1000+, the miniature scene 0


@torch.inference_mode()
def matching_accuracy(encoder: Encoder, rooms: list[CorpusScene], pairs_per_room: int = 8, seed: int = 0,
                      positive_radius: float = 0.05) -> float:
    """Fraction of cells whose nearest feature in the other view is the cell at the same surface point."""
    opts = PretrainOptions(scale_min=0.8, scale_max=1.25, crop_h=240, crop_w=320)
    rng = np.random.default_rng(seed)
    hits = total = 0
    encoder.eval()
    for room in rooms:
        for _ in range(pairs_per_room):
            views = [crop_view(room, f, opts, rng) for f in pair_frames(room, PretrainOptions(pair_max_gap=3), rng)]
            x = torch.from_numpy((np.stack([v[0] for v in views])[:, None] - INPUT_MEAN) / INPUT_STD).float()
            fa, fb = (torch.nn.functional.normalize(f.flatten(1).T, dim=1) for f in encoder(x))
            _, match, anchor, ok_b = cell_correspondences(torch.from_numpy(views[0][1]),
                                                          torch.from_numpy(views[1][1]), positive_radius)
            sim = fa[anchor] @ fb.T
            sim[:, ~ok_b] = -2.0
            hits += int((sim.argmax(1) == match[anchor]).sum())
            total += int(anchor.sum())
    return hits / max(total, 1)


def held_out_matching(encoder: Encoder, opts: PretrainOptions, rooms: int = 2) -> dict[str, float]:
    """Top-1 cell matching of `encoder` and of a random encoder of the same width, on rooms
    outside the corpus: the number that says whether pretraining bought anything."""
    held_out = build_corpus(rooms, HELD_OUT_SEEDS, 12)
    torch.manual_seed(opts.seed)
    random_init = Encoder(encoder.width)
    return {"pretrained": round(matching_accuracy(encoder, held_out, 4), 4),
            "random_init": round(matching_accuracy(random_init, held_out, 4), 4)}
