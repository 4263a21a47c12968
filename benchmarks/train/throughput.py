"""How close head training runs to the CPU's matrix-multiply peak, and what that bounds.

Training is a stream of dense products through the head (forward and backward). This measures
(1) the single-precision matrix-multiply rate of this CPU at the head's own shapes (a batch of
samples times a width x width weight), (2) the iterations per second of `train_head` on a scene's
buffer with the configured options, and (3) the arithmetic each iteration needs (multiply-adds
of every head layer for every sample, times three for forward and backward). From these it
writes `results/benchmarks/train_throughput_<scene>.json`: the achieved rate as a fraction of the
peak, and the fewest seconds the configured training could take if it ran at the peak.

    python -m benchmarks.train throughput --scene mini --iterations 300
    python -m benchmarks.train throughput --scene mini --iterations 30 train.precision=bf16

`train.precision` decides the training's precision (the machine's `auto` unless overridden); the
peak is that precision's product rate; both product rates are reported. The report goes to
`train_throughput_<scene>.json`, or `train_throughput_<scene>_bf16.json` for a bf16 run.

Run it on an otherwise idle machine, after the pipeline has built the scene's buffer.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import torch

from benchmarks._report import report_name, write_report
from usvc.buffer.buffer_file import read_buffer
from usvc.core.precision import cpu_has_native_bf16, product_seconds, resolve_precision
from usvc.model.head import Head
from usvc.pipeline import threads as thread_policy
from usvc.pipeline.config import compose_for_script
from usvc.pipeline.stage import scene_paths
from usvc.sfm.tracks_file import read_median_depth
from usvc.train.trainer import TrainOptions, train_head


def matmul_gflops(rows: int, width: int, repeats: int = 300, dtype: torch.dtype = torch.float32) -> float:
    """Sustained GFLOP/s of a (rows x width) @ (width x width) product in `dtype` on this CPU: the
    best of five blocks of `repeats / 5` products (the precision probe's timing)."""
    block = max(1, repeats // 5)
    return 2.0 * rows * width * width * block / product_seconds(dtype, block, rows, width, blocks=5) / 1e9


def head_macs_per_sample(in_channels: int, width: int, blocks: int) -> int:
    """Multiply-adds of one sample through the head: every layer's weight count."""
    head = Head(in_channels=in_channels, width=width, num_blocks=blocks)
    return sum(p.numel() for name, p in head.named_parameters() if name.endswith("weight"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="mini")
    parser.add_argument("--iterations", type=int, default=300, help="iterations to time (not the configured count)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. model.head_width=192")


def run(args: argparse.Namespace) -> None:
    cfg = compose_for_script(args.scene, args.overrides)
    threads = thread_policy.apply(thread_policy.resolve(cfg.threads))
    paths = scene_paths(cfg)
    buffer_file = paths.buffer_file
    if not buffer_file.is_file():
        raise SystemExit(f"{buffer_file} is missing: run the pipeline up to the buffer stage first")
    buf = read_buffer(buffer_file)
    median_depth = read_median_depth(paths.tracks_file)
    configured = TrainOptions(**cfg.train)
    head_width, head_blocks = cfg.model.head_width, cfg.model.head_blocks
    timed = dataclasses.replace(configured, iterations=args.iterations)
    steps = configured.steps_for(len(buf.features))  # `iterations: 0` means passes over this buffer

    samples = configured.batch_size + (configured.bundle_groups_per_batch * configured.bundle_obs_per_group
                                       if configured.bundle_weight > 0 else 0)
    macs = head_macs_per_sample(buf.features.shape[1], head_width, head_blocks)
    gflop_per_iteration = 3 * 2 * samples * macs / 1e9  # forward, and backward's two products per layer
    precision = resolve_precision(configured.precision)
    peak32 = matmul_gflops(samples, head_width)
    peak16 = matmul_gflops(samples, head_width, repeats=30, dtype=torch.bfloat16)
    peak = peak16 if precision == "bf16" else peak32

    start = time.perf_counter()
    train_head(buf, median_depth, timed, head_width=head_width, head_blocks=head_blocks, seed=cfg.seed)
    seconds = time.perf_counter() - start
    per_second = args.iterations / seconds
    achieved = per_second * gflop_per_iteration
    result = {
        "scene": args.scene, "overrides": args.overrides, "threads": threads, "cpu": platform.processor()
        or platform.machine(), "cpus": len(os.sched_getaffinity(0)), "torch": torch.__version__,
        "samples_per_iteration": samples, "head_macs_per_sample": macs,
        "gflop_per_iteration": round(gflop_per_iteration, 2), "timed_iterations": args.iterations,
        "iterations_per_second": round(per_second, 2), "achieved_gflops": round(achieved, 1),
        "precision": precision, "native_bf16": cpu_has_native_bf16(),
        "matmul_fp32_gflops": round(peak32, 1), "matmul_bf16_gflops": round(peak16, 1),
        "matmul_peak_gflops": round(peak, 1), "fraction_of_peak": round(achieved / peak, 3),
        "configured_iterations": steps,
        "configured_train_seconds_at_this_rate": round(steps / per_second, 1),
        "configured_train_seconds_at_peak": round(steps * gflop_per_iteration / peak, 1),
    }
    write_report(report_name(args, args.scene, "bf16" if precision == "bf16" else None), result)
    print(json.dumps(result, indent=1))

