"""`usvc` command line: localize one photo against a map, and rebuild the shipped encoders."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import fields
from pathlib import Path

from usvc.errors import UsvcError
from usvc.model.errors import ModelError

log = logging.getLogger("usvc")


def _pretrain(args: argparse.Namespace) -> int:
    from usvc.training.encoder_file import save_encoder_weights
    from usvc.training.pretrain import PretrainOptions, pretrain_encoder

    known = {f.name for f in fields(PretrainOptions)}
    overrides = {}
    for item in args.set or []:
        key, _, value = item.partition("=")
        if key not in known:
            raise UsvcError(f"pretrain-encoder: unknown option {key!r}; known: {', '.join(sorted(known))}")
        kind = type(getattr(PretrainOptions(), key))
        overrides[key] = kind(value)
    opts = PretrainOptions(encoder_width=args.width, **overrides)
    encoder, provenance = pretrain_encoder(opts, device=args.device)
    provenance["command"] = " ".join(["usvc", *sys.argv[1:]])
    record = save_encoder_weights(Path(args.out), encoder, provenance)
    print(json.dumps({k: record[k] for k in ("file", "width", "fingerprint", "megabytes",
                                             "loss_first_100", "loss_last_100", "train_seconds")}))
    return 0


def _localize(args: argparse.Namespace) -> int:
    """Localize each photo; the first bad input stops the run with one line on stderr (exit 1).

    Intrinsics and photo paths are checked before the map is loaded, so a typo fails in
    milliseconds rather than after the network is built.
    """
    intrinsics: float | list[float] | None = args.focal if args.focal is not None else args.intrinsics
    if intrinsics is None:
        raise UsvcError("intrinsics are missing: give --focal F (pixels, principal point at the "
                        "image centre) or --intrinsics fx fy cx cy")
    for photo in args.photos:
        if not Path(photo).is_file():
            raise UsvcError(f"image not found: {photo}")

    import torch

    from usvc.relocalizer import Relocalizer, RelocalizeOptions

    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise UsvcError(f"--device {args.device}: CUDA is not available to this torch build")
    options = RelocalizeOptions(backend=args.backend, max_error_px=args.max_error_px, refine=not args.no_refine)
    relocalizer = Relocalizer(args.map, args.encoder_weights, options, device=args.device)
    results = []
    for photo in args.photos:
        record = {"name": photo, **relocalizer.localize(photo, intrinsics).to_json()}
        if args.json_list:
            results.append(record)
        else:
            print(json.dumps(record), flush=True)
    if args.json_list:
        print(json.dumps(results, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usvc", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at DEBUG level")
    sub = parser.add_subparsers(dest="command", required=True)

    pre = sub.add_parser("pretrain-encoder", help="pretrain an encoder on generated rooms (rebuilds weights/)")
    pre.add_argument("--width", type=float, default=1.0, help="channel multiplier (0.5 = model=small)")
    pre.add_argument("--out", required=True, help="weight file to write (.pt); provenance goes to .json beside it")
    pre.add_argument("--device", default="cpu")
    pre.add_argument("--set", action="append", metavar="KEY=VALUE",
                     help="override a PretrainOptions field, e.g. --set iterations=2000")
    pre.set_defaults(run=_pretrain)

    loc = sub.add_parser("localize", help="estimate the camera pose of photos against a trained map")
    loc.add_argument("--map", required=True, help="map file written by the train stage (.pt)")
    loc.add_argument("--encoder-weights",
                     help="encoder the map was trained on (default: the shipped one of the map's width)")
    intr = loc.add_mutually_exclusive_group()
    intr.add_argument("--focal", type=float, help="focal length in pixels of the photo as given")
    intr.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                      help="pinhole intrinsics in pixels (COLMAP convention) of the photo as given")
    loc.add_argument("--backend", choices=("opencv", "pycolmap"), default="opencv",
                     help="RANSAC-PnP solver")
    loc.add_argument("--max-error-px", type=float, default=10.0,
                     help="RANSAC inlier threshold in pixels at a 480 px short side (scaled to the map's working size)")
    loc.add_argument("--no-refine", action="store_true",
                     help="skip keypoint-guided refinement (method=single); on by default when the map has keypoints")
    loc.add_argument("--device", default="cpu")
    loc.add_argument("--json-list", action="store_true",
                     help="print one JSON list at the end instead of one JSON object per line")
    loc.add_argument("photos", nargs="+", metavar="PHOTO")
    # Library INFO logs (map/encoder loaded) would bury the JSON and the one-line errors.
    loc.set_defaults(run=_localize, log_level=logging.WARNING)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else getattr(args, "log_level", logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.run(args))
    except (UsvcError, ModelError) as err:
        print(f"usvc {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
