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

Layout: groups padded to one width, (G, m) observations with a mask, so that the n^2 pairs of
every group are one broadcast product (no per-pair gathers of cameras, a fixed shape every step:
the trainer can replay a step as one CUDA graph) and each observation's gradient is a sum in a
fixed order (a reduction over b, not scattered adds of repeated rows).
"""

from __future__ import annotations

import torch

from usvc.train.options import BUNDLE_FORMS
from usvc.train.reprojection_loss import lower_median, project_samples

FORMS = BUNDLE_FORMS


def bundle_loss(pred: torch.Tensor, mask: torch.Tensor, pixels: torch.Tensor, R: torch.Tensor,
                t: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor, threshold: float | torch.Tensor, *,
                form: str, depth_min: float, depth_max: float, invalid_depth: float,
                max_reproj: float) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean pair loss over the groups, G groups padded to m observations: pred (G, m, 3), mask
    (G, m) (True where an observation is), pixels (G, m, 2), each observation's view R (G, m, 3, 3),
    t (G, m, 3), K and K_inv (G, m, 3, 3). Pair (a, b) of group g projects pred[g, a] into view
    b's camera; pairs with a masked end are left out of the sum and of the count. Statistics
    (detached 0-dim tensors, no host read): `valid_fraction` of the pairs and the lower median
    pixel error of the valid ones (`reproj_median`). `form` and the bounds come from
    `TrainOptions` through the trainer; none has a default here."""
    if form not in FORMS:
        raise ValueError(f"bundle loss form must be one of {FORMS}, got {form!r}")
    with torch.autocast(device_type=pred.device.type, enabled=False):
        # Pair (g, a, b): observation a's point in view b, broadcast over (group, a, b).
        uv = pixels[:, None]
        z, proj, invalid = project_samples(pred.float()[:, :, None], uv, R[:, None], t[:, None], K[:, None],
                                           K_inv[:, None], depth_min, invalid_depth)
        pair = mask[:, :, None] & mask[:, None, :]
        count = pair.sum().clamp(min=1).float()
        in_front = (z >= depth_min) & (z <= depth_max)
        if form == "squared":
            err2 = ((proj - uv) ** 2).sum(dim=-1)
            valid = in_front
            per_pair = torch.where(valid, err2, invalid)
            with torch.no_grad():
                err = err2.sqrt()
        else:
            err = (proj - uv).abs().sum(dim=-1)
            valid = in_front & (err <= max_reproj)
            tau = threshold.float() if isinstance(threshold, torch.Tensor) else threshold
            per_pair = torch.where(valid, tau * torch.tanh(err / tau), invalid)
        loss = torch.where(pair, per_pair, torch.zeros_like(per_pair)).sum() / count
        with torch.no_grad():
            stats = {"valid_fraction": (pair & valid).sum().float() / count,
                     "reproj_median": lower_median(err.detach(), pair & valid)}
    return loss, stats

