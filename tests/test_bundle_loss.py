"""Bundle loss (eq. 6-8): pairs cover every (observation, observing view) of a group, the loss is
zero at the true point, and its cross-view terms fix depth, which single-view reprojection cannot.
Groups come padded to one width with a mask; padding changes nothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from usvc.train.bundle_loss import bundle_loss
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


def _one_group(n: int, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """n observations as one group of width n: (1, n, ...) each, and an all-True mask."""
    return (torch.ones(1, n, dtype=torch.bool), *(x[None] for x in tensors))


def _pairwise(pred, sizes, uv, R, t, Kb, Kinv, tau, form):
    """The definition, pair by pair: every observation a of a group projected into every view b of
    it, through the single-view reprojection loss's formulas (tanh) or eq. 7 (squared)."""
    terms, start = [], 0
    for n in sizes:
        for a in range(start, start + n):
            for b in range(start, start + n):
                p = R[b] @ pred[a] + t[b]
                proj = (Kb[b] @ p)[:2] / p[2].clamp(min=ACE["depth_min"])
                invalid = (p - ACE["invalid_depth"] * (Kinv[b] @ torch.cat([uv[b], torch.ones(1)]))).abs().sum()
                in_front = ACE["depth_min"] <= p[2] <= ACE["depth_max"]
                if form == "squared":
                    terms.append(((proj - uv[b]) ** 2).sum() if in_front else invalid)
                else:
                    e = (proj - uv[b]).abs().sum()
                    terms.append(tau * torch.tanh(e / tau) if in_front and e <= ACE["max_reproj"] else invalid)
        start += n
    return torch.stack(terms).mean()


@pytest.mark.parametrize("form", ["tanh", "squared"])
def test_padded_groups_are_the_pairwise_definition(form):
    """Groups of 3, 1 and 5 observations padded to width 5: the loss is the mean over the 9 + 1 + 25
    pairs of the pair-by-pair definition, whatever the padded slots hold."""
    g = torch.Generator().manual_seed(0)
    sizes, width = [3, 1, 5], 5
    n = sum(sizes)
    R, t = _views(n)
    pred = torch.randn(n, 3, generator=g) * 0.5
    pred[2, 2] = -4.0  # behind its cameras: the invalid-prediction term
    uv = torch.rand(n, 2, generator=g) * 200 + 20
    Kb, Kinv = K.expand(n, 3, 3), torch.linalg.inv(K).expand(n, 3, 3)
    at = torch.zeros(len(sizes), width, dtype=torch.long)
    mask = torch.zeros(len(sizes), width, dtype=torch.bool)
    start = 0
    for line, size in enumerate(sizes):
        at[line] = torch.randint(0, n, (width,), generator=g)  # padding: anything
        at[line, :size] = torch.arange(start, start + size)
        mask[line, :size] = True
        start += size
    loss, stats = bundle_loss(pred[at], mask, uv[at], R[at], t[at], Kb[at], Kinv[at], 30.0, form=form, **ACE)
    expected = _pairwise(pred, sizes, uv, R, t, Kb, Kinv, 30.0, form)
    torch.testing.assert_close(loss, expected, rtol=1e-5, atol=1e-5)
    assert 0.0 < float(stats["valid_fraction"]) < 1.0


def test_the_median_is_nanmedians_without_a_host_read():
    from usvc.train.reprojection_loss import lower_median

    g = torch.Generator().manual_seed(1)
    for n in (1, 2, 7, 100):
        values = torch.rand(n, generator=g)
        valid = torch.rand(n, generator=g) < 0.6
        expected = torch.where(valid, values, torch.full_like(values, float("nan"))).nanmedian()
        got = lower_median(values, valid)
        assert torch.equal(got, expected) or (got.isnan() and expected.isnan())


@pytest.mark.parametrize("form", ["tanh", "squared"])
def test_zero_at_the_true_point_and_positive_off_it(form):
    R, t = _views(4)
    X = torch.tensor([0.1, -0.2, 0.3])
    uv = torch.stack([_observe(X, R[i], t[i]) for i in range(4)])
    Kb, Kinv = K.expand(4, 3, 3), torch.linalg.inv(K).expand(4, 3, 3)
    mask, uv, R, t, Kb, Kinv = _one_group(4, uv, R, t, Kb, Kinv)
    args = (mask, uv, R, t, Kb, Kinv, 10.0)
    loss, stats = bundle_loss(X.expand(1, 4, 3).clone(), *args, form=form, **ACE)
    assert float(loss) < 1e-6 and float(stats["valid_fraction"]) == 1.0
    off, _ = bundle_loss((X + torch.tensor([0.0, 0.0, 0.2])).expand(1, 4, 3).clone(), *args, form=form, **ACE)
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
    group = _one_group(3, uv, R, t, Kb, Kinv)
    for _ in range(300):
        # 50 px: the start of the training threshold schedule (tanh saturates beyond it)
        loss, _ = bundle_loss(torch.stack([y, y, y])[None], *group, 50.0, form=form, **ACE)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(torch.linalg.norm(y.detach() - X)) < 0.1 * float(torch.linalg.norm(wrong - X))


def test_unknown_form_is_rejected():
    with pytest.raises(ValueError, match="form"):
        bundle_loss(torch.zeros(1, 1, 3), torch.ones(1, 1, dtype=torch.bool), torch.zeros(1, 1, 2),
                    torch.eye(3)[None, None], torch.ones(1, 1, 3), K[None, None], K[None, None], 1.0, form="l1", **ACE)


def test_sampler_takes_whole_groups_capped_and_skips_single_view_groups():
    # keypoint 0: 5 obs in 5 views; keypoint 1: 2 obs in one view (no multi-view constraint); keypoint 2: 3 obs
    kp_id = np.array([0, 0, 0, 0, 0, 1, 1, 2, 2, 2])
    kp_view = np.array([0, 1, 2, 3, 4, 7, 7, 1, 2, 5])
    sampler = GroupSampler(kp_id, kp_view, groups_per_batch=2, obs_per_group=4, rng=np.random.default_rng(0))
    assert sampler.num_groups == 2
    seen = set()
    for _ in range(6):
        rows, mask = sampler.next()
        assert rows.shape == mask.shape == (2, 4)  # the same shape every step: padded to obs_per_group
        assert sorted(mask.sum(axis=1).tolist()) == [3, 4]
        assert all(len(set(kp_id[line].tolist())) == 1 for line in rows)  # padding repeats the group's row
        assert 1 not in kp_id[rows]
        seen.update(rows[mask].tolist())
    assert seen == {0, 1, 2, 3, 4, 7, 8, 9}  # every observation of a capped group gets its turn
    with pytest.raises(ValueError, match="sorted"):
        GroupSampler(kp_id[::-1], kp_view, 2, 4, np.random.default_rng(0))


@pytest.mark.parametrize("form", ["tanh", "squared"])
def test_gradient_is_the_same_bits_every_time(form):
    """Every observation appears in many pairs; its gradient must be summed in a fixed order (with
    `pred[a]` gathers two CPU threads once added repeated rows in timing order, and two 2-thread
    training runs diverged). Broadcast pairs reduce over the other view in a fixed order."""
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        g = torch.Generator().manual_seed(0)
        groups, width = 60, 40
        n = groups * width
        R, t = _views(n)
        pred = (torch.randn(groups, width, 3, generator=g) * 0.3).requires_grad_(True)
        uv = torch.rand(groups, width, 2, generator=g) * 200 + 20
        mask = torch.rand(groups, width, generator=g) < 0.8
        Kb, Kinv = K.expand(groups, width, 3, 3), torch.linalg.inv(K).expand(groups, width, 3, 3)
        args = (mask, uv, R.view(groups, width, 3, 3), t.view(groups, width, 3), Kb, Kinv, 50.0)
        grads = []
        for _ in range(20):
            pred.grad = None
            loss, _ = bundle_loss(pred, *args, form=form, **ACE)
            loss.backward()
            grads.append(pred.grad.clone())
        assert all(torch.equal(grads[0], other) for other in grads[1:])
    finally:
        torch.set_num_threads(previous)
