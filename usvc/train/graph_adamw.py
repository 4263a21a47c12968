"""AdamW whose learning rate and beta1 live on the device, so that a CUDA graph of the training
step reads each step's values there: the one-cycle schedule moves both every step (torch's
OneCycleLR cycles beta1 between 0.95 and 0.85 against the rate), and torch's own AdamW takes a
tensor beta1 only as a number read back to the host, which a captured step cannot do.

The update is torch's AdamW (decoupled weight decay, bias corrections with the current beta1
and the step count, eps outside the square root), written with tensor scalars:
tests/test_graph_adamw.py holds it to `torch.optim.AdamW` step for step.
"""

from __future__ import annotations

import torch


class GraphAdamW:
    """AdamW over `params` with the rate and beta1 as 0-dim tensors on the parameters' device
    (`set_schedule` refills them before a step), beta2, eps and weight decay as numbers."""

    def __init__(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 weight_decay: float = 0.01) -> None:
        self.params = [p for p in params if p.requires_grad]
        if not self.params:
            raise ValueError("GraphAdamW needs parameters that require gradients")
        device = self.params[0].device
        self.lr = torch.full((), lr, dtype=torch.float32, device=device)
        self.beta1 = torch.full((), betas[0], dtype=torch.float32, device=device)
        self.beta2, self.eps, self.weight_decay = float(betas[1]), float(eps), float(weight_decay)
        self.steps = torch.zeros((), dtype=torch.float32, device=device)
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]

    def set_schedule(self, lr: float, beta1: float) -> None:
        """This step's rate and beta1, written on the device (no copy, no wait)."""
        self.lr.fill_(lr)
        self.beta1.fill_(beta1)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if set_to_none:
                p.grad = None
            elif p.grad is not None:
                p.grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        self.steps.add_(1.0)
        correction1 = 1.0 - self.beta1 ** self.steps
        correction2_sqrt = (1.0 - self.beta2 ** self.steps).sqrt()
        step_size = self.lr / correction1
        decay = 1.0 - self.lr * self.weight_decay
        for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq):
            if p.grad is None:
                continue
            g = p.grad
            p.mul_(decay)
            m.lerp_(g, 1.0 - self.beta1)
            v.mul_(self.beta2).addcmul_(g, g, value=1.0 - self.beta2)
            denom = (v.sqrt() / correction2_sqrt).add_(self.eps)
            p.sub_(step_size * m / denom)
