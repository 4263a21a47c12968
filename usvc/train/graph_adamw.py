"""AdamW whose learning rate and beta1 live on the device, so that a CUDA graph of the training
step reads each step's values there: the one-cycle schedule moves both every step (torch's
OneCycleLR cycles beta1 between 0.95 and 0.85 against the rate), and torch's own AdamW takes a
tensor beta1 only as a number read back to the host, which a captured step cannot do.

The update is torch's AdamW (decoupled weight decay, bias corrections with the current beta1
and the step count, eps outside the square root), written with tensor scalars and multi-tensor
(foreach) kernels, none of which reads a value back: tests/test_graph_adamw.py holds it to
`torch.optim.AdamW` step for step.
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
        """One update of every parameter with a gradient, as multi-tensor (foreach) kernels: a dozen
        launches for the whole head instead of a dozen per parameter (on a GPU each launch costs a
        few microseconds even replayed in a graph). Per element the same operations, in the same
        order, as the update written one parameter at a time (tests/test_graph_adamw.py holds the
        two to the same bits)."""
        self.steps.add_(1.0)
        correction1 = 1.0 - self.beta1 ** self.steps
        correction2_sqrt = (1.0 - self.beta2 ** self.steps).sqrt()
        step_size = self.lr / correction1
        decay = 1.0 - self.lr * self.weight_decay
        live = [(p, m, v) for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq) if p.grad is not None]
        if not live:
            return
        params, exp_avg, exp_avg_sq = (list(x) for x in zip(*live))
        grads = [p.grad for p in params]
        torch._foreach_mul_(params, decay)
        moved = torch._foreach_sub(grads, exp_avg)  # m + (1 - beta1)(g - m): torch's lerp below 0.5,
        torch._foreach_mul_(moved, 1.0 - self.beta1)  # spelt out (a foreach lerp reads a tensor weight
        torch._foreach_add_(exp_avg, moved)  # back to the host, which a captured step cannot)
        torch._foreach_mul_(exp_avg_sq, self.beta2)
        torch._foreach_addcmul_(exp_avg_sq, grads, grads, value=1.0 - self.beta2)
        denom = torch._foreach_sqrt(exp_avg_sq)
        torch._foreach_div_(denom, correction2_sqrt)
        torch._foreach_add_(denom, self.eps)
        update = torch._foreach_mul(exp_avg, step_size)
        torch._foreach_div_(update, denom)
        torch._foreach_sub_(params, update)
