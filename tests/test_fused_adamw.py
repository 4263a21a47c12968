"""FusedAdamW is torch.optim.AdamW(fused=True) without torch.optim: the same bits, a lighter start."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from test_graph_adamw import step_beside

from usvc.train import fused_adamw, trainer
from usvc.train.fused_adamw import FusedAdamW
from usvc.train.options import TrainOptions

pytestmark = pytest.mark.skipif(not fused_adamw.available(), reason="this torch has no fused AdamW kernel")


def test_every_step_is_torchs_fused_adamw_bit_for_bit_while_the_rate_and_beta1_move():
    g = torch.Generator().manual_seed(0)
    start = [torch.randn(33, 17, generator=g), torch.randn(17, generator=g), torch.randn(4, generator=g)]
    ours = [torch.nn.Parameter(p.clone()) for p in start]
    theirs = [torch.nn.Parameter(p.clone()) for p in start]
    mine = FusedAdamW(ours, lr=5e-3, weight_decay=0.01)
    reference = torch.optim.AdamW(theirs, lr=5e-3, weight_decay=0.01, fused=True)
    sched = torch.optim.lr_scheduler.OneCycleLR(reference, max_lr=5e-3, total_steps=40, pct_start=0.3)
    for step in range(40):
        # a parameter without a gradient is left alone, its step count too
        step_beside(mine, reference, sched, ours, theirs, g, skip=lambda i: i == 2 and step % 3 == 0)
        for a, b in zip(ours, theirs):
            assert torch.equal(a.detach(), b.detach()), step
    for i, p in enumerate(theirs):
        state = reference.state[p]
        assert torch.equal(mine.exp_avg[i], state["exp_avg"]) and torch.equal(mine.exp_avg_sq[i], state["exp_avg_sq"])
        assert float(mine.steps[i]) == float(state["step"])
    assert float(mine.steps[2]) == 26  # 40 steps less the 14 without a gradient
    moved = max(float((a.detach() - p).abs().max()) for a, p in zip(ours, start))
    assert moved > 1e-2  # a real trajectory, not a standstill


def test_zero_grad_and_parameters_without_gradient():
    p, frozen = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(2), requires_grad=False)
    opt = FusedAdamW([p, frozen], lr=0.1)
    assert len(opt.params) == 1
    opt.step()  # no gradient yet: nothing moves, no state
    assert torch.equal(p.detach(), torch.ones(3)) and opt.steps[0] is None
    p.grad = torch.ones(3)
    opt.zero_grad(set_to_none=False)
    assert torch.equal(p.grad, torch.zeros(3))
    opt.zero_grad()
    assert p.grad is None
    with pytest.raises(ValueError, match="require gradients"):
        FusedAdamW([frozen], lr=0.1)


def test_the_cpu_trainer_uses_it():
    opts = TrainOptions(iterations=10)
    assert isinstance(trainer._optimizer(opts, [torch.nn.Parameter(torch.ones(2))], "cpu"), FusedAdamW)


def test_training_loads_no_torch_compiler():
    """Building a torch.optim optimizer imports torch._dynamo (seconds); a CPU training run must not."""
    code = ("import sys, torch\n"
            "from usvc.train import trainer\n"
            "from usvc.train.options import TrainOptions\n"
            "opts = TrainOptions(iterations=5)\n"
            "p = torch.nn.Parameter(torch.ones(3))\n"
            "opt = trainer._optimizer(opts, [p], 'cpu')\n"
            "lrs, betas = trainer.schedule_values(opts)\n"
            "p.grad = torch.ones(3)\n"
            "opt.step()\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_deterministic_kernels_for_cuda_training_load_no_torch_compiler():
    """Training on CUDA turns torch's deterministic kernels on (and back off) without importing
    torch's compiler, which torch.use_deterministic_algorithms does (seconds of a GPU start)."""
    code = ("import sys, torch\n"
            "from usvc.train import trainer\n"
            "assert not torch.are_deterministic_algorithms_enabled()\n"
            "with trainer._deterministic('cuda'):\n"
            "    on = torch.are_deterministic_algorithms_enabled()\n"
            "    warn = torch.is_deterministic_algorithms_warn_only_enabled()\n"
            "print(on, warn, torch.are_deterministic_algorithms_enabled(),\n"
            "      'torch._dynamo' in sys.modules or 'torch._inductor' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["True", "True", "False", "False"]
