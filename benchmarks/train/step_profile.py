"""Where a training step's time goes on a device: torch's profiler over a short `train_head` run.

Per step: the device kernels launched (on CUDA; a captured step's kernels are recorded inside its
graph too), the operators torch ran, the operators that took the most time on the device (on the
CPU: on the host) with their counts per step, and the host's time drawing a step's batches. On a
GPU this says whether a step is bound by its kernels' number (launch-bound: many kernels of a few
microseconds), by a few slow kernels, or by the host (device time well below the step's wall). It
writes `results/benchmarks/train_profile_<scene>_<device>.json`, and `pipeline device` adds the
same record to its report.

    python -m benchmarks.train profile --scene mini --device cuda
    python -m benchmarks.train profile --scene mini --device cuda --variant batch8192 -- \
        train.batch_size=8192 train.bundle_groups_per_batch=256
    python -m benchmarks.train profile --scene mini --device cpu --iterations 20

Needs the scene's buffer (the pipeline up to `buffer`; `--data` for another data folder).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from benchmarks._report import ROOT, report_name, write_report


def _self_time_us(row, device: bool) -> float:
    """An averaged row's own time (us) on the device or on the host, whatever torch calls it."""
    names = ("self_device_time_total", "self_cuda_time_total") if device else ("self_cpu_time_total",)
    for name in names:
        value = getattr(row, name, None)
        if value is not None:
            return float(value)
    return 0.0


def host_draw_ms(buf, opts, steps: int = 100) -> float:
    """Host milliseconds a step of drawing the batches takes, as the trainer draws them (a block of
    `steps` at a time: the cells' permutation, the bundle loss's keypoint groups picked in Python).
    The loop draws the next block while the device runs the queued one, so on a GPU this is hidden
    while it stays below the device's time a step."""
    from usvc.train.trainer import batch_draw

    draw = batch_draw(buf, opts, seed=0)
    start = time.perf_counter()
    draw.block(steps, "cpu")
    return 1e3 * (time.perf_counter() - start) / steps


def profile_training(buf, median_depth: float, opts, head_width: int, head_blocks: int, device: str,
                     iterations: int = 60, top: int = 25) -> dict:
    """Profile `iterations` steps of `train_head` (after as many unprofiled ones, so that the
    step's graph is captured and the allocator warm): per-step kernels, operators, wall time,
    and the `top` operators by their own time on the device (host time where it is the CPU)."""
    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    from usvc.train.trainer import train_head

    opts = replace(opts, iterations=iterations, validate_every=0, report_every=min(opts.report_every, iterations))
    on_cuda = device.startswith("cuda")
    train_head(buf, median_depth, opts, head_width=head_width, head_blocks=head_blocks, device=device)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if on_cuda else [])
    with profile(activities=activities) as prof:
        start = time.perf_counter()
        _, summary = train_head(buf, median_depth, opts, head_width=head_width, head_blocks=head_blocks,
                                device=device)
        if on_cuda:
            torch.cuda.synchronize(device)
        wall = time.perf_counter() - start
    events = prof.events()
    kernels = [e for e in events if e.device_type == DeviceType.CUDA]
    operators = [e for e in events if e.device_type == DeviceType.CPU and e.name.startswith("aten::")]
    rows = sorted(prof.key_averages(), key=lambda r: _self_time_us(r, on_cuda), reverse=True)
    table = [{"name": r.key, "per_step": round(r.count / iterations, 2),
              "self_us_per_step": round(_self_time_us(r, on_cuda) / iterations, 1)}
             for r in rows[:top] if _self_time_us(r, on_cuda) > 0]
    kernel_us = sum(float(getattr(e, "device_time", 0.0) or 0.0) for e in kernels)
    return {
        "device": device, "iterations": iterations, "batch_size": opts.batch_size,
        "bundle_groups_per_batch": opts.bundle_groups_per_batch, "precision": summary["precision"],
        "cuda_graph": summary.get("cuda_graph"),
        "wall_ms_per_step": round(1e3 * wall / iterations, 3),
        "train_seconds": round(summary["train_seconds"], 3),
        "samples_per_second": round(summary["samples_per_second"]),
        "kernels_per_step": round(len(kernels) / iterations, 1) if on_cuda else None,
        "kernel_ms_per_step": round(kernel_us / 1e3 / iterations, 3) if on_cuda else None,
        "operators_per_step": round(len(operators) / iterations, 1),
        "host_draw_ms_per_step": round(host_draw_ms(buf, opts), 3),
        "top": table,
    }


def profile_scene(data: Path, scene: str, device: str, overrides: list[str], iterations: int,
                  graphs: tuple[bool, ...] = (True, False)) -> list[dict]:
    """The scene's training step profiled as the `train` stage would run it (its config, its
    buffer), with the step captured as a CUDA graph and without (one record on a CPU)."""
    import usvc  # noqa: F401  (OpenMP's wait policy before torch)
    from usvc.buffer.buffer_file import read_buffer
    from usvc.pipeline.config import compose_for_script, group_options
    from usvc.pipeline.paths import ScenePaths
    from usvc.sfm.tracks_file import read_median_depth

    cfg = compose_for_script(scene, overrides)
    train, model = group_options(cfg, "train"), group_options(cfg, "model")
    paths = ScenePaths(data, data.parent / "results", scene)
    buf, depth = read_buffer(paths.buffer_file), read_median_depth(paths.tracks_file)
    records = []
    for graph in graphs if device.startswith("cuda") else (False,):
        record = profile_training(buf, depth, replace(train, cuda_graph=graph), model.head_width, model.head_blocks,
                                  device, iterations)
        records.append(record)
        print(f"  step profile ({record['cuda_graph'] or device}): {record['wall_ms_per_step']:.2f} ms a step, "
              f"{record['kernels_per_step']} kernels ({record['kernel_ms_per_step']} ms on the device), "
              f"{record['operators_per_step']} operators, the host's draw "
              f"{record['host_draw_ms_per_step']:.2f} ms a step", flush=True)
    return records


def device_or_exit(setting: str) -> str:
    """The torch device `setting` resolves to, or the script's exit with the one line saying why not."""
    from usvc.core.device import resolve_device
    from usvc.core.errors import UsvcError

    try:
        return resolve_device(setting)
    except UsvcError as exc:
        raise SystemExit(str(exc)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="mini")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="data folder holding <scene>/buffer")
    parser.add_argument("--iterations", type=int, default=60, help="steps profiled (after as many unprofiled)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (after --)")


def run(args: argparse.Namespace) -> None:
    device = device_or_exit(args.device)
    if args.iterations < 1:
        raise SystemExit(f"--iterations {args.iterations}: must be >= 1")
    records = profile_scene(args.data.resolve(), args.scene, device, args.overrides, args.iterations)
    path = write_report(report_name(args, args.scene, device.replace(":", "")),
                        {"scene": args.scene, "overrides": args.overrides, "profiles": records})
    print("report:", path)

