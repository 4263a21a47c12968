"""The multi-view bundle loss (paper eq. 6-8) over whole keypoint groups.

For every observation a of keypoint j in the batch, the head's coordinate y_a (predicted from the
feature of that one view) is projected into every view b that observes j, and compared with
b's observed position u_b: L_j = sum_a sum_b |pi(y_a; h_b) - u_b|^2. The pairs with a == b are
the ordinary reprojection terms at the keypoint's pixel; the pairs with a != b are what single-view
training lacks: they fix the depth along a's ray to where the other views saw the point.

Forms: "squared" is eq. 7 as printed (squared L2 pixel error; points behind or too close to view b
get ACE's invalid-prediction term instead, since their projection is meaningless). "tanh" is
ACE's robust form (L1 pixel error e, loss tau * tanh(e / tau) with the reprojection loss's
threshold schedule): early in training most predictions are hundreds of pixels off in the other
views, and a squared error lets those few pairs dominate the gradient. Both are averaged over
pairs, so lambda_B = 1 weighs one pair like one pixel sample of L_pi.
"""

from __future__ import annotations

import numpy as np
import torch

from usvc.train.options import BUNDLE_FORMS
from usvc.train.reprojection_loss import project_samples, reprojection_loss

FORMS = BUNDLE_FORMS


def group_pairs(group_sizes) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) index pairs over observations laid out group after group: all n_g^2 pairs per group
    (host arrays: the trainer draws them a block of steps at a time, with the groups)."""
    sizes = np.asarray(group_sizes, dtype=np.int64)
    starts = np.cumsum(sizes) - sizes
    counts = sizes * sizes
    group = np.repeat(np.arange(len(sizes)), counts)
    local = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    n = sizes[group]
    return starts[group] + local // n, starts[group] + local % n


def _squared(pred: torch.Tensor, pixels: torch.Tensor, R: torch.Tensor, t: torch.Tensor, K: torch.Tensor,
             K_inv: torch.Tensor, depth_min: float, depth_max: float, invalid_depth: float) -> tuple[torch.Tensor, dict]:
    z, proj, invalid = project_samples(pred.float(), pixels, R, t, K, K_inv, depth_min, invalid_depth)
    err2 = ((proj - pixels) ** 2).sum(dim=1)
    valid = (z >= depth_min) & (z <= depth_max)
    loss = torch.where(valid, err2, invalid).mean()
    with torch.no_grad():
        err = err2.sqrt()
        stats = {"valid_fraction": valid.float().mean(),
                 "reproj_median": torch.where(valid, err, torch.full_like(err, float("nan"))).nanmedian()}
    return loss, stats


def bundle_loss(pred: torch.Tensor, group_sizes: torch.Tensor, pixels: torch.Tensor, R: torch.Tensor,
                t: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor, threshold: float, *, form: str,
                depth_min: float, depth_max: float, invalid_depth: float,
                max_reproj: float,
                pairs: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean pair loss over the groups. Observation rows (pred, pixels, and their view's R, t, K)
    are laid out group after group, `group_sizes` long each. `form` and the bounds come from
    `TrainOptions` through the trainer (as in `reprojection_loss`); none has a default here.
    `pairs`: `group_pairs(group_sizes)` already on pred's device (the trainer draws them on the
    host a block at a time, so that the step reads nothing back from the device)."""
    if form not in FORMS:
        raise ValueError(f"bundle loss form must be one of {FORMS}, got {form!r}")
    if pairs is None:
        a, b = (torch.from_numpy(x).to(pred.device) for x in group_pairs(group_sizes.cpu().numpy()))
    else:
        a, b = pairs
    # index_select, not pred[a]: every observation appears in many pairs, and on CPU the gradient
    # of advanced indexing adds repeated rows in thread-timing order (different bits every run);
    # index_select's gradient adds them in index order.
    pred_a = torch.index_select(pred, 0, a)
    if form == "squared":
        return _squared(pred_a, pixels[b], R[b], t[b], K[b], K_inv[b], depth_min, depth_max, invalid_depth)
    return reprojection_loss(pred_a, pixels[b], R[b], t[b], K[b], K_inv[b], threshold, depth_min=depth_min,
                             depth_max=depth_max, max_reproj=max_reproj, invalid_depth=invalid_depth)
