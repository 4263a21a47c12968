"""GraphAdamW is torch's AdamW with the rate and beta1 as device tensors: the same update."""

from __future__ import annotations

import pytest
import torch

from usvc.train.graph_adamw import GraphAdamW


@torch.no_grad()
def _step_each(opt: GraphAdamW) -> None:
    """GraphAdamW's update written one parameter at a time: what its foreach kernels compute."""
    opt.steps.add_(1.0)
    correction1 = 1.0 - opt.beta1 ** opt.steps
    correction2_sqrt = (1.0 - opt.beta2 ** opt.steps).sqrt()
    step_size = opt.lr / correction1
    decay = 1.0 - opt.lr * opt.weight_decay
    for p, m, v in zip(opt.params, opt.exp_avg, opt.exp_avg_sq):
        if p.grad is None:
            continue
        g = p.grad
        p.mul_(decay)
        m.add_((g - m).mul_(1.0 - opt.beta1))
        v.mul_(opt.beta2).addcmul_(g, g, value=1.0 - opt.beta2)
        denom = (v.sqrt() / correction2_sqrt).add_(opt.eps)
        p.sub_(step_size * m / denom)


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


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_foreach_update_is_the_one_at_a_time_update_bit_for_bit(dtype):
    """`step` (multi-tensor kernels) against the update written one parameter at a time:
    the same bits at every step while the rate and beta1 move, a parameter without gradient left alone."""
    g = torch.Generator().manual_seed(1)
    start = [torch.randn(33, 17, generator=g, dtype=dtype), torch.randn(17, generator=g, dtype=dtype),
             torch.randn(4, 4, generator=g, dtype=dtype)]
    ours = [torch.nn.Parameter(p.clone()) for p in start]
    each = [torch.nn.Parameter(p.clone()) for p in start]
    a, b = GraphAdamW(ours, lr=3e-3), GraphAdamW(each, lr=3e-3)
    for it in range(30):
        lr, beta1 = 3e-3 * (1 + it) / 30, 0.95 - 0.1 * it / 30
        a.set_schedule(lr, beta1)
        b.set_schedule(lr, beta1)
        for i, (x, y) in enumerate(zip(ours, each)):
            grad = None if i == 2 and it % 3 == 0 else torch.randn(x.shape, generator=g, dtype=dtype)
            x.grad, y.grad = (None, None) if grad is None else (grad.clone(), grad.clone())
        a.step()
        _step_each(b)
        for x, y in zip(ours, each):
            assert torch.equal(x.detach(), y.detach())
        for m, n in zip(a.exp_avg + a.exp_avg_sq, b.exp_avg + b.exp_avg_sq):
            assert torch.equal(m, n)
    assert max(float((x.detach() - p).abs().max()) for x, p in zip(ours, start)) > 1e-2


def test_the_update_reads_nothing_back_from_the_device():
    """A captured step cannot read a tensor's value back to the host. On the meta device (tensors
    without data) any such read raises: a foreach op given a tensor where it takes a number (a lerp
    weight, say) converts it that way."""
    params = [torch.nn.Parameter(torch.empty(5, 3, device="meta")), torch.nn.Parameter(torch.empty(3, device="meta"))]
    for p in params:
        p.grad = torch.empty_like(p)
    opt = GraphAdamW(params, lr=0.1)
    opt.set_schedule(0.05, 0.9)
    opt.step()
    _step_each(opt)
