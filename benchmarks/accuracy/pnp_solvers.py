"""Compare the PnP backends on synthetic scenes shaped like dense SCR output.

Each trial: a 640x480 PINHOLE camera (f = 525) at a random pose, an 80x60 grid of cell centres
(8j + 4.5, 8i + 4.5) in COLMAP pixels, a random depth map in 1–4 m, inliers back-projected from
their pixel (half of them from a pixel moved by 1 px Gaussian noise) with 1 cm 3D noise, and
outliers drawn uniformly from the box of the inlier points. Prints one row per backend and
outlier ratio, and writes the rows (unrounded), the trial setup, the command line and the machine
context to results/benchmarks/accuracy_pnp_solvers.json.
Run: python -m benchmarks.accuracy pnp-solvers [--trials 30] [--ratios 0.3 0.6 0.85]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks._report import report_name, write_report
from usvc.core.pose_errors import rotation_error_deg, translation_error
from usvc.core.scene import Camera
from usvc.relocalize.options import BACKENDS
from usvc.relocalize.pnp import solve_pnp


def ace_median(values: np.ndarray) -> float:
    """Element ⌊N/2⌋ of the sorted list, the median rule the evaluation uses."""
    return float(np.sort(values)[len(values) // 2])


CAMERA = Camera("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
PIXEL_NOISE_FRACTION = 0.5
PIXEL_NOISE_PX = 1.0
POINT_NOISE_M = 0.01


def make_trial(rng: np.random.Generator, outlier_ratio: float):
    """Correspondences, true rotation and translation for one synthetic query."""
    i, j = np.mgrid[0:60, 0:80]
    uv = np.stack([8 * j + 4.5, 8 * i + 4.5], -1).reshape(-1, 2).astype(np.float64)
    n = len(uv)
    depth = rng.uniform(1.0, 4.0, n)
    R = Rotation.random(random_state=rng).as_matrix()
    t = -R @ rng.uniform(-5.0, 5.0, 3)  # camera centre in a 10 m box
    noisy = rng.random(n) < PIXEL_NOISE_FRACTION
    uv_src = uv + noisy[:, None] * rng.normal(0.0, PIXEL_NOISE_PX, (n, 2))
    (fx, fy), (cx, cy) = CAMERA.focal, CAMERA.principal_point
    x_cam = np.stack([(uv_src[:, 0] - cx) / fx * depth, (uv_src[:, 1] - cy) / fy * depth, depth], -1)
    x_world = (x_cam - t) @ R + rng.normal(0.0, POINT_NOISE_M, (n, 3))
    outlier = rng.permutation(n) < round(outlier_ratio * n)
    lo, hi = x_world[~outlier].min(0), x_world[~outlier].max(0)
    x_world[outlier] = rng.uniform(lo, hi, (int(outlier.sum()), 3))
    return uv, x_world, R, t


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.3, 0.6, 0.85])
    ap.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> None:

    header = (f"{'backend':<9} {'outliers':>8} {'med rot (deg)':>13} {'med trans (cm)':>14} "
              f"{'<5cm,5deg':>9} {'med ms':>8} {'failed':>6}")
    print(header)
    print("-" * len(header))
    rows = []
    for backend in BACKENDS:
        for ratio in args.ratios:
            rng = np.random.default_rng(args.seed)  # same scenes for every backend
            rot, trans, ms, failed = [], [], [], 0
            for k in range(args.trials):
                uv, xw, R, t = make_trial(rng, ratio)
                res = solve_pnp(uv, xw, CAMERA, max_error_px=10.0, seed=k, backend=backend)
                ms.append(res.seconds * 1e3)
                if not res.success:
                    failed += 1
                    rot.append(np.inf)
                    trans.append(np.inf)
                    continue
                rot.append(rotation_error_deg(res.R, R))
                trans.append(translation_error(res.R, res.t, R, t))
            rot_a, trans_a = np.array(rot), np.array(trans) * 100.0
            within = np.mean((rot_a < 5.0) & (trans_a < 5.0)) * 100.0
            print(f"{backend:<9} {ratio * 100:>7.0f}% {ace_median(rot_a):>13.4f} {ace_median(trans_a):>14.3f} "
                  f"{within:>8.1f}% {ace_median(np.array(ms)):>8.1f} {failed:>6d}")
            rows.append({"backend": backend, "outlier_ratio": ratio, "median_rot_deg": ace_median(rot_a),
                         "median_trans_cm": ace_median(trans_a), "within_5cm_5deg_pct": float(within),
                         "median_ms": ace_median(np.array(ms)), "failed": failed})
    write_report(report_name(args), {
        "trials": args.trials, "seed": args.seed, "ratios": args.ratios,
        "camera": {"model": CAMERA.model, "width": CAMERA.width, "height": CAMERA.height,
                   "params": list(CAMERA.params)},
        "grid": "80x60 cell centres (8j + 4.5, 8i + 4.5)", "depth_m": [1.0, 4.0],
        "pixel_noise_fraction": PIXEL_NOISE_FRACTION, "pixel_noise_px": PIXEL_NOISE_PX, "point_noise_m": POINT_NOISE_M,
        "max_error_px": 10.0, "median_rule": "element N//2 of the sorted values", "rows": rows})

