"""Time one relocalization query, split into encoder forward, head and RANSAC-PnP, per model and size.

Every model of conf/model/ (default, small, small_real, xfeat) runs as its config composes it: the
encoder its weights name (shipped in the packages), the head's configured layout (default: 512
wide, the others 256). PnP runs through `solve_pnp` on what a good map would give:
the cell centres of a PINHOLE camera (f = 0.82 x width) looking at a tilted plane 1.5-3 m away,
1 cm 3D noise, 30 % of the cells replaced by points drawn from the box of the others. Each number
is the median over --runs queries after --warmup untimed ones; "total" is the median of the
per-query sums, so it need not equal the sum of the medians. GFLOP/s is the encoder's only
(`encoder_flops` over its median time). Prints a table; writes its rows (unrounded), the setup,
the command line and the machine context to results/benchmarks/query_models_<device>[_bf16].json
(<device>: cpu or cuda, the one that ran; `_bf16` added when the network ran at bf16). Run:
python -m benchmarks.query models [--runs 20] [--device cuda] [--sizes 320x240 640x480]
    [--models small] [--precision auto|bf16|fp32]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from benchmarks._report import ROOT, report_name, write_report
from usvc.core.pose_errors import rotation_error_deg
from usvc.core.precision import PRECISIONS, autocast, resolve_precision
from usvc.core.scene import Camera
from usvc.model.encoder import cell_centers, encoder_flops, feature_size
from usvc.model.head import Head
from usvc.model.options import ModelOptions
from usvc.model.preprocess import normalise
from usvc.pipeline.config import compose_for_script, group_options
from usvc.relocalize.pnp import solve_pnp
from usvc.weights import load_configured_encoder

MODELS = tuple(sorted(p.stem for p in (ROOT / "conf" / "model").glob("*.yaml")))


def model_options(name: str) -> ModelOptions:
    """conf/model/<name>.yaml as the stages compose it (a model file sets only what differs)."""
    return group_options(compose_for_script("mini", [f"model={name}"]), "model")
OUTLIER_RATIO = 0.3
POINT_NOISE_M = 0.01


def ace_median(values: list[float]) -> float:
    """Element ⌊N/2⌋ of the sorted list, the median rule the evaluation uses."""
    return float(np.sort(values)[len(values) // 2])


def plane_scene(h_cells: int, w_cells: int, camera: Camera, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cell-centre pixels, their world points (30 % outliers) and the true world-to-camera R, t."""
    uv = cell_centers(h_cells, w_cells, "colmap").permute(1, 2, 0).reshape(-1, 2).double().numpy()
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    rays = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], -1)
    normal = np.array([0.3, -0.2, 1.0])  # plane normal . X = 2 in the camera frame: 1.5-3 m deep
    x_cam = rays * (2.0 / (rays @ normal))[:, None]
    R = Rotation.random(random_state=rng).as_matrix()
    t = -R @ rng.uniform(-5.0, 5.0, 3)
    x_world = (x_cam - t) @ R + rng.normal(0.0, POINT_NOISE_M, x_cam.shape)
    outlier = rng.permutation(len(uv)) < round(OUTLIER_RATIO * len(uv))
    lo, hi = x_world[~outlier].min(0), x_world[~outlier].max(0)
    x_world[outlier] = rng.uniform(lo, hi, (int(outlier.sum()), 3))
    return uv, x_world, R, t


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.inference_mode()
def time_queries(encoder: torch.nn.Module, head: Head, width: int, height: int, runs: int, warmup: int,
                 device: torch.device, precision: str = "fp32") -> dict[str, float]:
    """Median ms of each stage over `runs` queries, plus how many PnP solves found the true pose."""
    rng = np.random.default_rng(0)
    image = normalise(rng.random((height, width), dtype=np.float32)).to(device)
    camera = Camera("PINHOLE", width, height, (0.82 * width, 0.82 * width, width / 2, height / 2))
    uv, xyz, R_true, _ = plane_scene(*feature_size(height, width), camera, rng)
    times: dict[str, list[float]] = {"encoder": [], "head": [], "pnp": [], "total": []}
    solved = 0
    for k in range(warmup + runs):
        sync(device)
        t0 = time.perf_counter()
        with autocast(precision, device.type):
            features = encoder(image)
            sync(device)
            t1 = time.perf_counter()
            coords = head(features)[0].float().permute(1, 2, 0).double().cpu().numpy()  # as Relocalizer does
        t2 = time.perf_counter()
        # The network output is garbage for random weights; PnP gets the synthetic plane instead.
        assert coords.shape[:2] == feature_size(height, width)
        result = solve_pnp(uv, xyz, camera, max_error_px=10.0, seed=k)
        t3 = time.perf_counter()
        if k < warmup:
            continue
        solved += bool(result.success and rotation_error_deg(result.R, R_true) < 1.0)
        for key, seconds in zip(times, (t1 - t0, t2 - t1, t3 - t2, t3 - t0)):
            times[key].append(seconds * 1e3)
    return {**{key: ace_median(v) for key, v in times.items()}, "solved": solved}


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, e.g. 640x480, got {text!r}") from None
    return w, h


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (falls back to cpu if unavailable)")
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[(320, 240), (640, 480)],
                    metavar="WxH")
    ap.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    ap.add_argument("--precision", choices=PRECISIONS, default="auto",
                    help="the network's products (relocalize.precision); auto as the Relocalizer resolves it")


def run(args: argparse.Namespace) -> None:
    if args.runs < 1:
        args.parser.error("--runs must be at least 1")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(f"note: --device {args.device} requested but CUDA is not available; using cpu")
        device = torch.device("cpu")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    precision = resolve_precision(args.precision, device.type)
    load = os.getloadavg()[0]  # before the runs, as printed
    print(f"device {device} ({name}), torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{os.cpu_count()} cores, load avg {load:.1f}; "
          f"median of {args.runs} runs after {args.warmup} warm-up; PnP: opencv, "
          f"{OUTLIER_RATIO:.0%} outliers; network at {precision}")
    header = (f"{'model':<10} {'weights':<18} {'size':>8} {'encoder ms':>10} {'head ms':>8} {'pnp ms':>8} "
              f"{'total ms':>9} {'GFLOP':>6} {'GFLOP/s':>8} {'pnp ok':>7}")
    print(header)
    print("-" * len(header))
    rows = []
    for model in args.models:
        opts = model_options(model)
        encoder, weights = load_configured_encoder(opts.encoder_width, opts.encoder_weights, opts.encoder)
        source = Path(weights).name
        head = Head(encoder.out_channels, opts.head_width, opts.head_blocks).eval().requires_grad_(False)
        encoder.to(device)
        head.to(device)
        for w, h in args.sizes:
            r = time_queries(encoder, head, w, h, args.runs, args.warmup, device, precision)
            # the FLOP count is the ACE layout's; XFeat's backbone has none here
            gflop = encoder_flops(h, w, opts.encoder_width) / 1e9 if opts.encoder == "ace" else None
            rate = gflop / r["encoder"] * 1e3 if gflop is not None else None
            solved = f"{int(r['solved'])}/{args.runs}"
            print(f"{model:<10} {source[:18]:<18} {f'{w}x{h}':>8} {r['encoder']:>10.1f} {r['head']:>8.1f} "
                  f"{r['pnp']:>8.1f} {r['total']:>9.1f} {gflop or float('nan'):>6.1f} {rate or float('nan'):>8.1f} "
                  f"{solved:>7}")
            rows.append({"model": model, "encoder": opts.encoder, "weights": source,
                         "encoder_width": opts.encoder_width, "head_width": opts.head_width,
                         "head_blocks": opts.head_blocks, "size": f"{w}x{h}", "encoder_ms": r["encoder"],
                         "head_ms": r["head"], "pnp_ms": r["pnp"], "total_ms": r["total"], "encoder_gflop": gflop,
                         "encoder_gflops_per_s": rate, "pnp_solved": int(r["solved"]), "runs": args.runs})
    write_report(report_name(args, None, device.type, "bf16" if precision == "bf16" else None), {
        "device": str(device), "precision": precision, "device_name": name, "torch_threads": torch.get_num_threads(),
        "cores": os.cpu_count(), "load_avg_1min_before": load, "runs": args.runs, "warmup": args.warmup,
        "median_rule": "element N//2 of the sorted values", "pnp_backend": "opencv", "outlier_ratio": OUTLIER_RATIO,
        "point_noise_m": POINT_NOISE_M, "rows": rows})

