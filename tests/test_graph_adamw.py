"""GraphAdamW is torch's AdamW with the rate and beta1 as device tensors: the same update."""

from __future__ import annotations

import pytest
import torch

from usvc.train.graph_adamw import GraphAdamW


def step_beside(mine, reference, sched, ours, theirs, g: torch.Generator, skip=lambda i: False) -> None:
    """One step of `mine` and of torch's `reference` on the same random gradients, at the rate and
    beta1 torch's scheduler gives this step; parameter i gets no gradient where skip(i)."""
    group = reference.param_groups[0]
    mine.set_schedule(group["lr"], group["betas"][0])
    for i, (a, b) in enumerate(zip(ours, theirs)):
        if skip(i):
            a.grad = b.grad = None
            continue
        grad = torch.randn(a.shape, generator=g) * 0.1
        a.grad, b.grad = grad.clone(), grad.clone()
    mine.step()
    reference.step()
    sched.step()


def test_every_step_is_torchs_adamw_while_the_rate_and_beta1_move():
    g = torch.Generator().manual_seed(0)
    start = [torch.randn(7, 5, generator=g), torch.randn(5, generator=g)]
    ours = [torch.nn.Parameter(p.clone()) for p in start]
    theirs = [torch.nn.Parameter(p.clone()) for p in start]
    mine = GraphAdamW(ours, lr=3e-3, weight_decay=0.01)
    reference = torch.optim.AdamW(theirs, lr=3e-3, weight_decay=0.01)
    sched = torch.optim.lr_scheduler.OneCycleLR(reference, max_lr=3e-3, total_steps=40, pct_start=0.3)
    for _ in range(40):
        step_beside(mine, reference, sched, ours, theirs, g)
        for a, b in zip(ours, theirs):
            torch.testing.assert_close(a.detach(), b.detach(), rtol=1e-5, atol=1e-6)
    moved = max(float((a.detach() - p).abs().max()) for a, p in zip(ours, start))
    assert moved > 1e-2  # the test followed a real trajectory, not a standstill


def test_zero_grad_and_parameters_without_gradient():
    p, frozen = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(2), requires_grad=False)
    opt = GraphAdamW([p, frozen], lr=0.1)
    assert len(opt.params) == 1
    p.grad = torch.ones(3)
    opt.zero_grad(set_to_none=False)
    assert torch.equal(p.grad, torch.zeros(3))
    opt.step()  # a zero gradient: only the weight decay moves it
    torch.testing.assert_close(p.detach(), torch.full((3,), 1 - 0.1 * 0.01))
    opt.zero_grad()
    assert p.grad is None
    opt.step()  # no gradient: nothing moves but the step count
    assert float(opt.steps) == 2
    with pytest.raises(ValueError, match="parameters"):
        GraphAdamW([frozen], lr=0.1)
