"""Adaptive density control (3DGS section 5.2): clone small Gaussians and split large ones where
the view-space positional gradient is high, prune transparent or oversized ones, and reset
opacities periodically so floaters can be pruned. Adam's moments follow the rows they belong to
(new rows start from zero moments, as in the reference)."""

from __future__ import annotations

import torch

from usvc.gaussians.options import GaussiansOptions
from usvc.splat.gaussians import PARAM_NAMES, quat_to_rotmat


class DensityStats:
    """Running view-space gradient norms and largest screen radius per Gaussian."""

    def __init__(self, n: int, device: torch.device | str = "cpu") -> None:
        self.grad_sum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max_radius = torch.zeros(n, device=device)

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        vis = radii > 0
        # Pixel gradients to NDC gradients (d ndc / d px = 2 / size), so the threshold is the
        # reference's whatever the image size.
        g = means2d_grad * torch.tensor([0.5 * width, 0.5 * height], device=means2d_grad.device)
        self.grad_sum += torch.where(vis, g.norm(dim=-1), torch.zeros_like(radii))
        self.count += vis.float()
        self.max_radius = torch.maximum(self.max_radius, radii.float())

    def mean_grad(self) -> torch.Tensor:
        return self.grad_sum / self.count.clamp(min=1)


def replace_rows(params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Adam, keep: torch.Tensor,
                 extra: dict[str, torch.Tensor]) -> None:
    """Keep rows `keep` (bool mask) of every parameter, append `extra` rows; Adam moments of kept rows
    move with them, appended rows start at zero."""
    for group in optimizer.param_groups:
        old = group["params"][0]
        name = group["name"]
        new = torch.nn.Parameter(torch.cat([old.detach()[keep], extra[name].to(old.dtype)], 0))
        state = optimizer.state.pop(old, None)
        if state:
            n_extra = extra[name].shape[0]
            for key in ("exp_avg", "exp_avg_sq"):
                s = state[key]
                state[key] = torch.cat([s[keep], torch.zeros((n_extra,) + s.shape[1:], dtype=s.dtype, device=s.device)], 0)
            optimizer.state[new] = state
        group["params"][0] = new
        params[name] = new


def densify_and_prune(params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Adam, stats: DensityStats,
                      extent: float, opts: GaussiansOptions, generator: torch.Generator,
                      prune_large: bool) -> dict[str, int]:
    with torch.no_grad():
        n = params["means"].shape[0]
        grads = stats.mean_grad()
        max_scale = torch.exp(params["log_scales"]).max(dim=1).values
        hot = grads >= opts.densify_grad_threshold
        room = max(0, opts.max_gaussians - n)
        clone = hot & (max_scale <= opts.percent_dense * extent)
        split = hot & ~clone
        # Under the cap, favour the Gaussians with the largest gradients.
        if int(clone.sum() + split.sum()) > room:
            order = torch.argsort(torch.where(hot, grads, torch.full_like(grads, -1.0)), descending=True)
            allowed = torch.zeros_like(hot)
            allowed[order[:room]] = True
            clone &= allowed
            split &= allowed
        extra = {k: params[k].detach()[clone] for k in PARAM_NAMES}
        # Split: two children sampled from the parent's Gaussian, scales shrunk by 1.6.
        s_idx = torch.nonzero(split).squeeze(1)
        if len(s_idx):
            scales = torch.exp(params["log_scales"][s_idx]).repeat(2, 1)
            rot = quat_to_rotmat(torch.nn.functional.normalize(params["quats"][s_idx], dim=-1)).repeat(2, 1, 1)
            offset = (rot @ (torch.randn(scales.shape, generator=generator, device=scales.device) * scales)[..., None])[..., 0]
            children = {k: params[k].detach()[s_idx].repeat((2,) + (1,) * (params[k].dim() - 1)) for k in PARAM_NAMES}
            children["means"] = children["means"] + offset
            children["log_scales"] = torch.log(scales / 1.6)
            extra = {k: torch.cat([extra[k], children[k]], 0) for k in PARAM_NAMES}
        opac = torch.sigmoid(params["opacity_logits"])
        prune = split | (opac < opts.min_opacity)
        if prune_large:
            if opts.max_screen_radius > 0:
                prune |= stats.max_radius > opts.max_screen_radius
            prune |= max_scale > opts.max_world_scale * extent
        replace_rows(params, optimizer, ~prune, extra)
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((prune & ~split).sum()),
                "total": int(params["means"].shape[0])}


def reset_opacity(params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Adam, ceiling: float = 0.01) -> None:
    with torch.no_grad():
        logit = torch.logit(torch.tensor(ceiling)).item()
        new_vals = torch.clamp(params["opacity_logits"].detach(), max=logit)
    for group in optimizer.param_groups:
        if group["name"] == "opacity_logits":
            old = group["params"][0]
            new = torch.nn.Parameter(new_vals)
            state = optimizer.state.pop(old, None)
            if state:
                state["exp_avg"] = torch.zeros_like(state["exp_avg"])
                state["exp_avg_sq"] = torch.zeros_like(state["exp_avg_sq"])
                optimizer.state[new] = state
            group["params"][0] = new
            params["opacity_logits"] = new
