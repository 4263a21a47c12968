"""Write a lens-distorted copy of a posed pinhole scene and report how well undistortion undoes it.

    python scripts/make_distorted_scene.py --src ../shared/scenes/office --src-format llff \
        --model OPENCV --format transforms --out data/raw/office_opencv

The PSNR of every undistorted image against its original (over the pixels both cover) goes to
``<out>.json`` beside the folder and to stdout.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from usvc.core.atomic import atomic_dir
from usvc.analysis.distorted_scene import DistortOptions, undistortion_psnr, write_distorted_scene
from usvc.core.errors import UsvcError
from usvc.prepare.importers import load_scene


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", required=True)
    ap.add_argument("--src-format", default="llff")
    ap.add_argument("--model", default="OPENCV")
    ap.add_argument("--format", dest="fmt", default="transforms", choices=("transforms", "colmap"))
    ap.add_argument("--coefficients", type=float, nargs="+", help="distortion terms (default: per model)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        scene = load_scene(args.src_format, args.src, "source", "every_nth", 8)
        opts = DistortOptions(args.model, args.fmt, tuple(args.coefficients) if args.coefficients else None)
        out = Path(args.out)
        with atomic_dir(out) as tmp:
            info = write_distorted_scene(scene, tmp, opts)
        fmt_scene = load_scene(args.fmt, out, "distorted", "every_nth", 8)
        by_name = {f.name: f for f in fmt_scene.frames}
        psnr, valid = [], []
        for f in scene.frames:
            d = by_name[f"images/{info['names'][f.name]}"]
            p, v = undistortion_psnr(cv2.imread(str(f.image_path)), f.camera, cv2.imread(str(d.image_path)), d.camera)
            psnr.append(p)
            valid.append(v)
    except UsvcError as e:
        print(f"make_distorted_scene: error: {e}", file=sys.stderr)
        return 1
    report = {k: v for k, v in info.items() if k != "names"}
    report.update(psnr_db_mean=float(np.mean(psnr)), psnr_db_min=float(np.min(psnr)),
                  valid_fraction_mean=float(np.mean(valid)), source=str(args.src))
    Path(f"{out}.json").write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
