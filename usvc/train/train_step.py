"""One training step of the head and how the loop runs it.

A step is the forward pass on a batch of buffer cells (and, for the bundle loss, on its keypoint
groups), ACE's reprojection loss, the bundle loss, backward and the optimizer's step; it returns
its statistics as one device tensor and reads nothing back. The loop runs it eagerly (the CPU), or
on a GPU step by step on a side stream for a few steps and then captured once as a CUDA graph and
replayed (`StepRunner`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from usvc.buffer.buffer_file import TrainingBuffer
from usvc.core.precision import autocast
from usvc.model.head import Head
from usvc.train.bundle_loss import bundle_loss
from usvc.train.options import TrainOptions
from usvc.train.reprojection_loss import reprojection_loss

log = logging.getLogger(__name__)


@dataclass
class DeviceBuffer:
    """The buffer on the training device, sent once (no copy on the CPU): features stay fp16 there
    and batches are cast; each view's camera as float32 (its intrinsics inverted on the host)."""

    feats: torch.Tensor
    pixels: torch.Tensor
    view: torch.Tensor
    K: torch.Tensor
    K_inv: torch.Tensor
    R_world_to_cam: torch.Tensor
    t_world_to_cam: torch.Tensor
    kp_feats: torch.Tensor | None = None  # the keypoint observations of the bundle loss, where it runs
    kp_pixels: torch.Tensor | None = None
    kp_view: torch.Tensor | None = None

    @classmethod
    def of(cls, buf: TrainingBuffer, device: str, keypoints: bool) -> DeviceBuffer:
        K_host = torch.from_numpy(buf.view_K).float()
        out = cls(feats=torch.from_numpy(buf.features).to(device),
                  pixels=torch.from_numpy(buf.pixels).float().to(device),
                  view=torch.from_numpy(buf.view_index.astype(np.int64)).to(device),
                  K=K_host.to(device), K_inv=torch.linalg.inv(K_host).to(device),
                  R_world_to_cam=torch.from_numpy(buf.view_R_world_to_cam).float().to(device),
                  t_world_to_cam=torch.from_numpy(buf.view_t_world_to_cam).float().to(device))
        if keypoints:
            out.kp_feats = torch.from_numpy(buf.kp_features).to(device)
            out.kp_pixels = torch.from_numpy(buf.kp_pixels).float().to(device)
            out.kp_view = torch.from_numpy(buf.kp_view.astype(np.int64)).to(device)
        return out


class TrainStep:
    """Forward, losses, backward and the optimizer's step on one batch (gradients already cleared):
    `step(idx, rows, mask)` (buffer rows; keypoint groups and their mask, empty without the bundle
    loss) gives the step's statistics as one device tensor: total loss, pixel loss, valid fraction,
    median reprojection, bundle loss, bundle median reprojection. The reprojection threshold is read
    from `tau` on the device, refilled by the loop every step (a graph reads it there)."""

    def __init__(self, head: Head, optim, data: DeviceBuffer, opts: TrainOptions, precision: str, device: str,
                 median_depth: float) -> None:
        self.head, self.optim, self.data, self.opts = head, optim, data, opts
        self.precision, self.device = precision, device
        self.depth_min, self.depth_max = opts.depth_min_rel * median_depth, opts.depth_max_rel * median_depth
        self.invalid_depth = opts.invalid_depth_rel * median_depth
        self.tau = torch.zeros((), device=device)
        self.nan = torch.full((), float("nan"), device=device)
        self.bundle = data.kp_feats is not None

    def __call__(self, idx: torch.Tensor, rows: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        d, opts, batch = self.data, self.opts, self.opts.batch_size
        v = d.view[idx]
        x = d.feats[idx].float()
        if self.bundle:
            x = torch.cat([x, d.kp_feats[rows.flatten()].float()])
        with autocast(self.precision, self.device, cache=False):
            pred = self.head.forward_flat(x)
        pix_loss, stats = reprojection_loss(
            pred[:batch], d.pixels[idx], d.R_world_to_cam[v], d.t_world_to_cam[v], d.K[v], d.K_inv[v], self.tau,
            depth_min=self.depth_min, depth_max=self.depth_max, max_reproj=opts.max_reproj_px,
            invalid_depth=self.invalid_depth)
        loss = opts.reproj_weight * pix_loss
        b_loss = b_px = self.nan
        if self.bundle:
            kv = d.kp_view[rows]
            b_loss, b_stats = bundle_loss(
                pred[batch:].reshape(*rows.shape, 3), mask, d.kp_pixels[rows], d.R_world_to_cam[kv],
                d.t_world_to_cam[kv], d.K[kv], d.K_inv[kv], self.tau, form=opts.bundle_loss,
                depth_min=self.depth_min, depth_max=self.depth_max, invalid_depth=self.invalid_depth,
                max_reproj=opts.max_reproj_px)
            loss = loss + opts.bundle_weight * b_loss
            b_px = b_stats["reproj_median"]
        loss.backward()
        self.optim.step()
        return torch.stack([loss.detach(), pix_loss.detach(), stats["valid_fraction"], stats["reproj_median"],
                            b_loss.detach(), b_px]).float()


class _StepGraph:
    """One training step captured as a CUDA graph and replayed: its inputs are copied into the
    graph's own tensors first. Captured after a few steps run normally on a side stream (the
    optimizer's state exists by then), as torch's whole-network capture does."""

    WARMUP = 3

    def __init__(self, step, example: tuple[torch.Tensor, ...]) -> None:
        self.inputs = tuple(torch.empty_like(x) for x in example)
        for mine, x in zip(self.inputs, example):
            mine.copy_(x)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.out = step(*self.inputs)

    def replay(self, *inputs: torch.Tensor) -> torch.Tensor:
        for mine, x in zip(self.inputs, inputs):
            mine.copy_(x)
        self.graph.replay()
        return self.out


def capture(step, example: tuple[torch.Tensor, ...]) -> _StepGraph:
    """The one place the loop waits for the device outside the block's read: capturing a graph
    synchronises once."""
    return _StepGraph(step, example)


class StepRunner:
    """Runs `step` for step `it` of the loop: eagerly; or, on a GPU with `train.cuda_graph` and
    AdamW, on a side stream for the first _StepGraph.WARMUP steps (as torch's capture recipe asks),
    then captured once and replayed (step by step where the capture fails). `note` says which."""

    def __init__(self, step: TrainStep, optim, device: str, opts: TrainOptions) -> None:
        self.step, self.optim, self.device = step, optim, device
        self.graphed = device.startswith("cuda") and opts.cuda_graph and opts.optimizer == "adamw"
        self.graph: _StepGraph | None = None
        self.note = f"not captured (fewer than {_StepGraph.WARMUP + 1} steps)" if self.graphed else "off"
        self.side = torch.cuda.Stream(device) if self.graphed else None

    def __call__(self, it: int, inputs: tuple[torch.Tensor, ...]) -> torch.Tensor:
        if self.graph is None and self.graphed and it >= _StepGraph.WARMUP:
            self.optim.zero_grad(set_to_none=True)
            try:
                self.graph = capture(self.step, inputs)
                self.note = "captured"
            except RuntimeError as exc:  # a torch or driver without what capture needs: step by step
                log.warning("training step by step: the CUDA graph capture failed (%s)", exc)
                self.graphed, self.note = False, f"capture failed: {exc}"
        if self.graph is not None:
            return self.graph.replay(*inputs)
        if self.graphed:  # the steps before the capture, on a side stream
            self.side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(self.side):
                self.optim.zero_grad(set_to_none=True)
                out = self.step(*inputs)
            torch.cuda.current_stream(self.device).wait_stream(self.side)
            return out
        self.optim.zero_grad(set_to_none=True)
        return self.step(*inputs)
