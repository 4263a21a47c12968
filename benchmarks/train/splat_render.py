"""Rasteriser cost: milliseconds per render and per render + backward, for a fitted splat.

Renders mapping views of a scene with the Gaussians of its `gaussians` stage at a given width,
on CPU (and on CUDA, with every available backend, when there is a GPU), and prints time per
forward, per forward + backward (what one fitting iteration costs, less the optimiser step), the
tile/Gaussian pairs, and peak process memory; writes the same figures (unrounded), the command line
and the machine context to results/benchmarks/train_splat_render_<scene>_<render width>.json. Run
it on an otherwise idle machine:
    python -m benchmarks.train splat-render --scene mini --width 160 [--views 10]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import torch

from benchmarks._report import report_name, write_report
from usvc.core.scene_file import read_scene_h5
from usvc.gaussians.fit import image_loss, load_fit_images
from usvc.pipeline.paths import ScenePaths
from usvc.splat.gsplat_backend import gsplat_available, render_gsplat
from usvc.splat.ply_file import read_splat_ply
from usvc.splat.rasterize import bin_tiles, project, render


def _time(fn, views, backward: bool, sync) -> float:
    out = []
    for im in views:
        t0 = time.perf_counter()
        res = fn(im.view)
        if backward:
            image_loss(res.rgb, im.rgb, 0.2).backward()
        sync()
        out.append(time.perf_counter() - t0)
    return 1000 * sorted(out)[len(out) // 2]


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene", default="mini")
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--width", type=int, default=0, help="render width (0 = prepared width)")
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--tile", type=int, default=8)


def run(args: argparse.Namespace) -> None:
    paths = ScenePaths.of_scene_dir(Path(args.data_dir) / args.scene)
    g = read_splat_ply(paths.splat_file)
    frames = read_scene_h5(paths.scene_file).split("train")[: args.views]
    views = load_fit_images(frames, args.width)
    v0 = views[0].view
    proj = project(g, v0)
    gid, _, _, _ = bin_tiles(proj, v0.width, v0.height, args.tile)
    print(f"{args.scene}: {len(g)} Gaussians, {int((proj.radii > 0).sum())} visible in view 0, "
          f"{len(gid)} tile pairs, {v0.width}x{v0.height}, {torch.get_num_threads()} CPU threads")
    rows = []
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for dev in devices:
        gd = g.to(dev)
        for t in gd.tensors().values():
            t.requires_grad_(True)
        vd = [type(im)(im.name, im.view.to(dev), im.rgb.to(dev)) for im in views]
        sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
        backends = {"torch": lambda v: render(gd, v, tile=args.tile)}
        if gsplat_available(dev):
            backends["gsplat"] = lambda v: render_gsplat(gd, v)
        for name, fn in backends.items():
            _time(fn, vd[:1], True, sync)  # warm-up
            with torch.no_grad():
                fwd = _time(fn, vd, False, sync)
            both = _time(fn, vd, True, sync)
            print(f"  {dev:4s} {name:6s} forward {fwd:8.1f} ms   forward+backward {both:8.1f} ms   (median of {len(vd)} views)")
            rows.append({"device": dev, "backend": name, "forward_ms": fwd, "forward_backward_ms": both,
                         "views": len(vd)})
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak process memory {peak_mb:.0f} MB")
    write_report(report_name(args, args.scene, v0.width), {
        "scene": args.scene, "data_dir": args.data_dir, "gaussians": len(g),
        "visible_in_view0": int((proj.radii > 0).sum()), "tile_pairs_view0": len(gid), "tile": args.tile,
        "width": v0.width, "height": v0.height, "cpu_threads": torch.get_num_threads(),
        "median_rule": "element N//2 of the sorted times", "rows": rows, "peak_memory_mb": peak_mb})

