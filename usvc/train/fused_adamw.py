"""AdamW as torch's fused CPU kernel, driven without `torch.optim`.

`torch.optim.AdamW(fused=True)` runs one kernel over each parameter (elementwise, so the same bits
for any thread count). Building any `torch.optim` optimizer also loads torch's compiler
(`torch._dynamo`, about two seconds on a 2-core CPU) on every training run, for an optimizer whose
step it never compiles. This class keeps the same state (first and second moments, a float32 step
count per parameter) and calls the same kernel with the same arguments, so the update is torch's bit
for bit (tests/test_fused_adamw.py holds it to `torch.optim.AdamW(fused=True)` over a schedule).
The rate and beta1 are set before each step (`set_schedule`), as the one-cycle schedule moves both.
"""

from __future__ import annotations

import torch

from usvc.train.graph_adamw import GraphAdamW


def available() -> bool:
    """Whether this torch has the fused AdamW kernel (the trainer falls back to torch.optim's
    AdamW where it does not)."""
    return callable(getattr(torch, "_fused_adamw_", None))


class FusedAdamW:
    """AdamW over `params` (those that require gradients), one fused kernel call per step."""

    def __init__(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 weight_decay: float = 0.01) -> None:
        self.params = [p for p in params if p.requires_grad]
        if not self.params:
            raise ValueError("FusedAdamW needs parameters that require gradients")
        self.lr, self.beta1 = float(lr), float(betas[0])
        self.beta2, self.eps, self.weight_decay = float(betas[1]), float(eps), float(weight_decay)
        # torch.optim's fused state: moments like the parameter, the step count a float32 scalar
        # on the parameter's device; created on a parameter's first step, as torch does.
        self.exp_avg: list[torch.Tensor | None] = [None] * len(self.params)
        self.exp_avg_sq: list[torch.Tensor | None] = [None] * len(self.params)
        self.steps: list[torch.Tensor | None] = [None] * len(self.params)

    def set_schedule(self, lr: float, beta1: float) -> None:
        """This step's rate and beta1."""
        self.lr, self.beta1 = float(lr), float(beta1)

    zero_grad = GraphAdamW.zero_grad  # every parameter's gradient to None (or zeros)

    @torch.no_grad()
    def step(self) -> None:
        live = [i for i, p in enumerate(self.params) if p.grad is not None]
        if not live:
            return
        for i in live:
            if self.steps[i] is None:
                p = self.params[i]
                self.exp_avg[i] = torch.zeros_like(p, memory_format=torch.preserve_format)
                self.exp_avg_sq[i] = torch.zeros_like(p, memory_format=torch.preserve_format)
                self.steps[i] = torch.zeros((), dtype=torch.float32, device=p.device)
        # torch.optim groups the tensors by device and dtype; the head's are all one group.
        groups: dict[tuple, list[int]] = {}
        for i in live:
            groups.setdefault((self.params[i].device, self.params[i].dtype), []).append(i)
        for members in groups.values():
            steps = [self.steps[i] for i in members]
            torch._foreach_add_(steps, 1)
            torch._fused_adamw_(
                [self.params[i] for i in members], [self.params[i].grad for i in members],
                [self.exp_avg[i] for i in members], [self.exp_avg_sq[i] for i in members], [], steps,
                amsgrad=False, lr=self.lr, beta1=self.beta1, beta2=self.beta2, weight_decay=self.weight_decay,
                eps=self.eps, maximize=False, grad_scale=None, found_inf=None)
