"""How well a map predicts its scene keypoints: the diagnostic behind single vs multiview.

The bundle loss exists to put the coordinate predicted from a keypoint's feature at the
keypoint's triangulated position X_k (multi-view), where the reprojection loss only constrains
it to the observing ray. This reads the buffer's keypoint tuples (k, d_k, view, u_obs), runs a
map's head on d_k, and prints, per map, the 3D error |y - X_k| (in units of the median scene
depth) and the reprojection error into the observing view (px), medians and 90th percentiles, one
JSON line per map. Writes the buffer and every map's line, with the command line and the machine
context, to results/benchmarks/accuracy_keypoints_<scene>.json (<scene>: the folder holding the
buffer's buffer/ folder, data/<scene>/buffer/buffer.h5; else the buffer file's stem).
Run: python -m benchmarks.accuracy keypoints --buffer data/mini/buffer/buffer.h5 MAP [MAP ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import torch

from benchmarks._report import report_name, scene_of, write_report
from usvc.buffer.buffer_file import read_buffer
from usvc.relocalize.relocalizer import Relocalizer


@torch.inference_mode()
def keypoint_errors(map_path: Path, buffer_path: Path) -> dict[str, float]:
    buf = read_buffer(buffer_path)
    if not buf.has_keypoints:
        raise SystemExit(f"{buffer_path} holds no keypoint tuples")
    reloc = Relocalizer(map_path)
    head = reloc.regressor.head
    pred = np.concatenate([head.forward_flat(torch.from_numpy(buf.kp_features[i:i + 65536]).float()).double().numpy()
                           for i in range(0, len(buf.kp_features), 65536)])
    X = buf.keypoint_xyz[buf.kp_id].astype(np.float64)
    depth = float(reloc.metadata.get("median_depth", 1.0))
    err3d = np.linalg.norm(pred - X, axis=1) / depth
    v = buf.kp_view
    cam = np.einsum("nij,nj->ni", buf.view_R_world_to_cam[v], pred) + buf.view_t_world_to_cam[v]
    uv = np.einsum("nij,nj->ni", buf.view_K[v], cam)
    front = cam[:, 2] > 1e-6
    reproj = np.full(len(pred), np.inf)
    reproj[front] = np.linalg.norm(uv[front, :2] / uv[front, 2:] - buf.kp_pixels[front], axis=1)
    return {"map": str(map_path), "method": reloc.metadata.get("method", "?"), "observations": int(len(pred)),
            "err3d_rel_median": float(np.median(err3d)), "err3d_rel_p90": float(np.percentile(err3d, 90)),
            "reproj_px_median": float(np.median(reproj)), "reproj_px_p90": float(np.percentile(reproj, 90))}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--buffer", type=Path, required=True)
    parser.add_argument("maps", type=Path, nargs="+")


def run(args: argparse.Namespace) -> None:
    rows = []
    for m in args.maps:
        rows.append(keypoint_errors(m, args.buffer))
        print(json.dumps(rows[-1]), flush=True)
    write_report(report_name(args, scene_of(args.buffer, "buffer")), {"buffer": str(args.buffer), "maps": rows})

