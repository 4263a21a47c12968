"""Bundle loss (eq. 6-8): pairs cover every (observation, observing view) of a group, the loss is
zero at the true point, and its cross-view terms fix depth, which single-view reprojection cannot."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from usvc.train.bundle_loss import bundle_loss, group_pairs
from usvc.train.group_sampler import GroupSampler
from usvc.train.reprojection_loss import reprojection_loss

K = torch.tensor([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
# ACE's absolute bounds (metres): the losses have no defaults of their own (the trainer passes
# TrainOptions' bounds times the median depth), and these tests are written for ACE's values.
ACE = {"depth_min": 0.1, "depth_max": 1000.0, "max_reproj": 1000.0, "invalid_depth": 10.0}


def _views(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cameras on an arc 3 m from the origin, looking at it (world-to-camera)."""
    Rs, ts = [], []
    for a in np.linspace(-0.4, 0.4, n):
        c, s = np.cos(a), np.sin(a)
        R = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float32)
        centre = torch.tensor([3 * np.sin(a), 0.0, -3 * np.cos(a)], dtype=torch.float32)
        Rs.append(R), ts.append(-R @ centre)
    return torch.stack(Rs), torch.stack(ts)


def _observe(X: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    p = R @ X + t
    return (K @ p)[:2] / p[2]


def test_group_pairs_are_all_ordered_pairs_within_each_group():
    a, b = group_pairs(torch.tensor([2, 1, 3]))
    pairs = set(zip(a.tolist(), b.tolist()))
    expected = {(i, j) for g in ([0, 1], [2], [3, 4, 5]) for i in g for j in g}
    assert pairs == expected and len(a) == 4 + 1 + 9


@pytest.mark.parametrize("form", ["tanh", "squared"])
def test_zero_at_the_true_point_and_positive_off_it(form):
    R, t = _views(4)
    X = torch.tensor([0.1, -0.2, 0.3])
    uv = torch.stack([_observe(X, R[i], t[i]) for i in range(4)])
    Kb, Kinv = K.expand(4, 3, 3), torch.linalg.inv(K).expand(4, 3, 3)
    args = (torch.tensor([4]), uv, R, t, Kb, Kinv, 10.0)
    loss, stats = bundle_loss(X.expand(4, 3).clone(), *args, form=form, **ACE)
    assert float(loss) < 1e-6 and float(stats["valid_fraction"]) == 1.0
    off, _ = bundle_loss((X + torch.tensor([0.0, 0.0, 0.2])).expand(4, 3).clone(), *args, form=form, **ACE)
    assert float(off) > 0.1


@pytest.mark.parametrize("form", ["tanh", "squared"])
def test_cross_view_pairs_fix_depth_along_the_ray_where_reprojection_cannot(form):
    """A prediction on view 0's ray at the wrong depth has zero single-view reprojection loss in
    view 0; descending the bundle loss (the other views see it too) brings it to the true point."""
    R, t = _views(3)
    X = torch.tensor([0.0, 0.0, 0.0])
    uv = torch.stack([_observe(X, R[i], t[i]) for i in range(3)])
    centre0 = -R[0].T @ t[0]
    wrong = centre0 + 1.3 * (X - centre0)  # same pixel in view 0, 30 % too deep
    Kb, Kinv = K.expand(3, 3, 3), torch.linalg.inv(K).expand(3, 3, 3)
    single, _ = reprojection_loss(wrong[None], uv[:1], R[:1], t[:1], Kb[:1], Kinv[:1], 10.0, **ACE)
    assert float(single) < 1e-4
    y = wrong.clone().requires_grad_(True)
    opt = torch.optim.Adam([y], lr=0.01)
    for _ in range(300):
        # 50 px: the start of the training threshold schedule (tanh saturates beyond it)
        loss, _ = bundle_loss(torch.stack([y, y, y]), torch.tensor([3]), uv, R, t, Kb, Kinv, 50.0, form=form,
                              **ACE)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(torch.linalg.norm(y.detach() - X)) < 0.1 * float(torch.linalg.norm(wrong - X))


def test_unknown_form_is_rejected():
    with pytest.raises(ValueError, match="form"):
        bundle_loss(torch.zeros(1, 3), torch.tensor([1]), torch.zeros(1, 2), torch.eye(3)[None],
                    torch.ones(1, 3), K[None], K[None], 1.0, form="l1", **ACE)


def test_sampler_takes_whole_groups_capped_and_skips_single_view_groups():
    # keypoint 0: 5 obs in 5 views; keypoint 1: 2 obs in one view (no multi-view constraint); keypoint 2: 3 obs
    kp_id = np.array([0, 0, 0, 0, 0, 1, 1, 2, 2, 2])
    kp_view = np.array([0, 1, 2, 3, 4, 7, 7, 1, 2, 5])
    sampler = GroupSampler(kp_id, kp_view, groups_per_batch=2, obs_per_group=4, rng=np.random.default_rng(0))
    assert sampler.num_groups == 2
    seen = set()
    for _ in range(6):
        rows, sizes = sampler.next()
        assert sorted(sizes.tolist()) == [3, 4] and len(rows) == 7
        groups = np.split(kp_id[rows], np.cumsum(sizes)[:-1])
        assert all(len(set(g.tolist())) == 1 for g in groups)
        assert 1 not in kp_id[rows]
        seen.update(rows.tolist())
    assert seen == {0, 1, 2, 3, 4, 7, 8, 9}  # every observation of a capped group gets its turn
    with pytest.raises(ValueError, match="sorted"):
        GroupSampler(kp_id[::-1], kp_view, 2, 4, np.random.default_rng(0))


@pytest.mark.parametrize("form", ["tanh", "squared"])
def test_gradient_is_the_same_bits_every_time(form, monkeypatch):
    """Every observation appears in many pairs; its gradient must be summed in a fixed order. With
    `pred[a]` (advanced indexing) two CPU threads added repeated rows in timing order, and two
    2-thread training runs diverged. The pairs are shuffled here (same pairs, any order) so that
    such a race shows on every run instead of now and then."""
    import usvc.train.bundle_loss as bl

    real_pairs = bl.group_pairs

    def shuffled_pairs(sizes):
        a, b = real_pairs(sizes)
        order = np.random.default_rng(1).permutation(len(a))
        return a[order], b[order]

    monkeypatch.setattr(bl, "group_pairs", shuffled_pairs)
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        g = torch.Generator().manual_seed(0)
        sizes = torch.full((60,), 40)
        n = int(sizes.sum())
        R, t = _views(n)
        pred = (torch.randn(n, 3, generator=g) * 0.3).requires_grad_(True)
        uv = torch.rand(n, 2, generator=g) * 200 + 20
        args = (sizes, uv, R, t, K.expand(n, 3, 3), torch.linalg.inv(K).expand(n, 3, 3), 50.0)
        grads = []
        for _ in range(20):
            pred.grad = None
            loss, _ = bl.bundle_loss(pred, *args, form=form, **ACE)
            loss.backward()
            grads.append(pred.grad.clone())
        assert all(torch.equal(grads[0], other) for other in grads[1:])
    finally:
        torch.set_num_threads(previous)
