"""Training cost of the bundle loss: seconds per iteration, single vs multiview, same buffer.

Times `train_head` for a few hundred iterations on a real buffer with keypoint tuples, once with
train.bundle_weight=0 (method=single) and once with the configured bundle sampling, and prints
seconds per iteration, the ratio and the projected time of a full run. Writes the same figures,
with the buffer, the command line and the machine context, to
results/benchmarks/train_bundle_cost_<scene>.json (<scene>: the folder holding the buffer's
buffer/ folder, data/<scene>/buffer/buffer.h5; else the buffer file's stem). Run it on an otherwise
idle machine: python -m benchmarks.train bundle-cost --buffer data/mini/buffer/buffer.h5 [--iterations 300]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import torch
from hydra import compose, initialize_config_dir

from benchmarks._report import ROOT, report_name, scene_of, write_report
from usvc.buffer.buffer_file import read_buffer
from usvc.pipeline.config import register_configs
from usvc.train.trainer import TrainOptions, train_head


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--buffer", type=Path, required=True)
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    register_configs()
    with initialize_config_dir(version_base=None, config_dir=str(ROOT / "conf")):
        cfg = compose("config")
    buf = read_buffer(args.buffer)
    full = TrainOptions(**cfg.train)
    rows = {}
    for method, weight in (("single", 0.0), ("multiview", full.bundle_weight or 1.0)):
        opts = replace(full, iterations=args.iterations, bundle_weight=weight)
        t0 = time.perf_counter()
        train_head(buf, 1.0, opts, head_width=cfg.model.head_width, head_blocks=cfg.model.head_blocks)
        per_it = (time.perf_counter() - t0) / args.iterations
        rows[method] = {"seconds_per_iteration": per_it, "projected_full_run_s": per_it * full.iterations}
    rows["multiview_over_single"] = rows["multiview"]["seconds_per_iteration"] / rows["single"]["seconds_per_iteration"]
    result = {"threads": args.threads, "iterations": args.iterations, **rows}
    print(json.dumps(result, indent=1))
    write_report(report_name(args, scene_of(args.buffer, "buffer")), {"buffer": str(args.buffer), **result})

