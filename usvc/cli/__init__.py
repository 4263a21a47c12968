"""`usvc` command line: build a map from a folder of photos, localize photos against a map (and
export the poses), and rebuild the shipped encoders."""

# The localize command is `localize` (its photos' arguments `photo_args`, their decoding ahead
# `photo_prefetch`, its files `exports`); `python -m usvc.cli` runs `__main__`. This docstring is
# the parser's description (`usvc --help`).

from __future__ import annotations

import argparse
import importlib.metadata
import json
import logging
import sys
from dataclasses import fields
from pathlib import Path

from usvc.cli.localize import localize
from usvc.core.errors import UsvcError
from usvc.core.precision import PRECISIONS
from usvc.pipeline import threads
from usvc.pipeline.logs import quiet_third_party
from usvc.relocalize.options import FINAL, PRIORS, REFINE, RelocalizeOptions


def _pretrain(args: argparse.Namespace) -> int:
    from usvc.pretrain.encoder_file import save_encoder_weights
    from usvc.pretrain.pretrain import PretrainOptions, pretrain_encoder

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


def _map(args: argparse.Namespace) -> int:
    """Add the scene to the checkout around the working directory, then run its pipeline."""
    from usvc.pipeline.paths import ScenePaths
    from usvc.prepare.new_scene import NewSceneOptions, add_scene, find_checkout, repro

    checkout = find_checkout(Path.cwd())
    opts = NewSceneOptions(args.name, args.format, args.split_n, args.working_width, args.metric_scale,
                           exif_focal=not args.no_exif)
    added = add_scene(Path(args.source), checkout, opts)  # all or nothing, Ctrl-C included
    print(json.dumps(added))
    if args.no_run:
        return 0
    try:
        code = repro(checkout, args.name)
    except KeyboardInterrupt:  # the scene is added by now: say so rather than "nothing written"
        print(f"usvc map: interrupted; scene {args.name!r} is added, `dvc repro metrics@{args.name}` goes on",
              file=sys.stderr)
        return 130
    if code == 0:
        paths = ScenePaths(checkout / "data", checkout / "results", args.name)
        print(f"map: {paths.map_file}; metrics: {paths.metrics('metrics')}", file=sys.stderr)
    else:  # the scene stays added: say how to go on with it, since `usvc map --name` again finds it taken
        print(f"usvc map: the pipeline of scene {args.name!r} stopped (the reason is above); the scene stays added: "
              f"fix the cause and run `dvc repro metrics@{args.name}`, or remove conf/scene/{args.name}.yaml, "
              f"data/raw/{args.name} and its line in params.yaml to map it afresh", file=sys.stderr)
    return code


def _version() -> str:
    try:
        return importlib.metadata.version("usvc")
    except importlib.metadata.PackageNotFoundError:
        import usvc

        return str(getattr(usvc, "__version__", "unknown"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usvc", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at DEBUG level")
    parser.add_argument("--threads", default="auto",
                        help="torch/OpenCV/BLAS threads: auto (the cores divided by the usvc jobs running side "
                             "by side) or a number")
    parser.add_argument("--version", action="version", version=f"usvc {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    pre = sub.add_parser("pretrain-encoder", help="pretrain an encoder on generated rooms (rebuilds weights/), or fine-tune one on real captures")
    pre.add_argument("--width", type=float, default=1.0, help="channel multiplier (0.5 = model=small)")
    pre.add_argument("--out", required=True, help="weight file to write (.pt); provenance goes to .json beside it")
    pre.add_argument("--device", default="cpu")
    pre.add_argument("--set", action="append", metavar="KEY=VALUE",
                     help="override a PretrainOptions field, e.g. --set iterations=2000")
    pre.set_defaults(run=_pretrain)

    mp = sub.add_parser("map", help="add a folder of photos (or a posed capture) as a scene and build its map")
    mp.add_argument("source", metavar="PHOTOS", help="folder of photos (format images) or of a capture")
    mp.add_argument("--name", required=True,
                    help="scene name: lower-case letters, digits, _, starting with a letter (not a config "
                         "name of conf/, a keyword, or base_*)")
    mp.add_argument("--format", default="images",
                    help="images (photos only, posed by SfM; default) | llff | transforms | colmap | ace | 7scenes | cambridge")
    mp.add_argument("--split-n", type=int, default=8, help="every N-th photo is a query, never trained on")
    mp.add_argument("--working-width", type=int, default=640,
                    help="images are resized to this width, 64 to 16384 px (0 keeps it)")
    mp.add_argument("--metric-scale", type=float, help="metres per scene unit (finite, > 0), when the poses are metric")
    mp.add_argument("--no-exif", action="store_true",
                    help="ignore the photos' EXIF focal lengths (SfM estimates the focal length; for wrong EXIF)")
    mp.add_argument("--no-run", action="store_true", help="only add the scene; run `dvc repro metrics@NAME` later")
    mp.set_defaults(run=_map)

    loc = sub.add_parser("localize", help="estimate the camera pose of photos against a trained map")
    loc.add_argument("--map", required=True, help="map file written by the train stage (.pt)")
    loc.add_argument("--encoder-weights",
                     help="encoder the map was trained on (default: the shipped one of the map's width)")
    intr = loc.add_mutually_exclusive_group()
    intr.add_argument("--focal", type=float,
                      help="focal length in pixels of the photo as shown (EXIF orientation applied)")
    intr.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                      help="pinhole intrinsics in pixels (COLMAP convention) of the photo as shown")
    intr.add_argument("--camera", nargs="+", metavar=("MODEL", "PARAM"),
                      help="a COLMAP camera model and its parameters in COLMAP order, e.g. OPENCV fx fy cx cy "
                           "k1 k2 p1 p2 (distortion is undone before localizing). Without any of these the "
                           "focal length comes from the photo's EXIF, else it is estimated with the pose")
    loc.add_argument("--no-exif", action="store_true",
                     help="ignore the photos' EXIF focal lengths: without --focal/--intrinsics/--camera the focal "
                          "length is estimated with the pose")
    loc.add_argument("--backend", choices=("opencv", "pycolmap"), default="opencv",
                     help="RANSAC-PnP solver")
    loc.add_argument("--max-error-px", type=float, default=10.0,
                     help="RANSAC inlier threshold in pixels at a 480 px short side (scaled to the map's working "
                          "size), at most 100")
    loc.add_argument("--min-confidence", type=float,
                     help="answers with a smaller inlier fraction of the cells are failures (default: the "
                          "calibrated relocalize.min_confidence, see docs/confidence.md; 0 keeps every pose)")
    loc.add_argument("--focal-tolerance", type=float,
                     help="refuse a pose when the given focal length differs by more than this (relative) from "
                          "the one the map implies (default: relocalize.focal_tolerance; 0 = no check)")
    loc.add_argument("--refine", choices=REFINE, default="features",
                     help="features (default): the photo's SIFT matched to the map's landmarks, guided by the "
                          "learned pose; keypoints: the paper's keypoint-guided refinement; none: the learned pose")
    loc.add_argument("--no-refine", action="store_true", help="the same as --refine none")
    loc.add_argument("--prior", choices=PRIORS, default="learned",
                     help="with --refine features: learned (default): the learned pose guides matching first, the "
                          "photo is matched as SIFT + PnP matches it when that leads nowhere; none: SIFT + PnP's "
                          "evidence alone (needs landmarks with observations)")
    loc.add_argument("--final", choices=FINAL, default=RelocalizeOptions.features_final,
                     help="with --refine features: confirmed (default): the guided answer's matches weighted by "
                          "the mapping images whose SIFT + PnP matching finds them (the baseline's precision); "
                          "guided: the guided passes' answer alone (faster); images: SIFT + PnP's per-image "
                          "matches around it instead")
    loc.add_argument("--landmarks", help="the map's landmarks.h5 (default: found beside the map: landmarks.h5 in "
                                         "its folder, else ../landmarks/landmarks.h5)")
    loc.add_argument("--device", default="auto", help="torch device: auto (CUDA where torch sees one) | cpu | cuda | cuda:N")
    loc.add_argument("--precision", choices=PRECISIONS, default="auto",
                     help="the network's products: auto = bf16 where the device runs it natively and faster, "
                          "else fp32 (any map runs at either)")
    loc.add_argument("--workers", type=int, default=1,
                     help="photos localized at a time, each with --threads divided among them (default 1): "
                          "for many photos on many cores, or with the network on a GPU; same answers as one "
                          "at a time with that many threads")
    loc.add_argument("--processes", action="store_true",
                     help="with --workers N: N worker processes instead of threads (each loads the map, in "
                          "seconds, then shares no interpreter lock: for folders of hundreds of photos)")
    loc.add_argument("--json-list", action="store_true",
                     help="print one JSON list at the end instead of one JSON object per line")
    loc.add_argument("--out-dir", help="also write the results here (files replaced atomically at the end)")
    loc.add_argument("--format", action="append", metavar="FORMAT[,FORMAT]",
                     help="what --out-dir gets (repeatable; default all): jsonl (queries.jsonl), poses "
                          "(poses.txt), colmap (cameras.txt, images.txt, points3D.txt: a COLMAP text model), "
                          "nerfstudio (transforms.json); failed photos are only in queries.jsonl")
    loc.add_argument("photos", nargs="*", metavar="PHOTO", help="image files and/or folders of images")
    # Library INFO logs (map/encoder loaded) would bury the JSON and the one-line errors.
    loc.set_defaults(run=localize, log_level=logging.WARNING)

    from usvc.serve.command import add_parser as add_serve_parser

    add_serve_parser(sub)  # `usvc serve`: usvc/serve/
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else getattr(args, "log_level", logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    quiet_third_party(verbose=args.verbose)
    try:
        try:
            n = threads.resolve(args.threads)
        except ValueError as err:
            raise UsvcError(f"--threads: {err}") from None
        threads.export_to_env(n)  # torch and OpenCV pools are set where a command loads them
        args.threads = n
        return int(args.run(args))
    except (UsvcError, OSError) as err:  # UsvcError covers ModelError (bad map/weights files)
        print(f"usvc {args.command}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # output files are written atomically, at the end
        print(f"usvc {args.command}: interrupted, nothing written", file=sys.stderr)
        return 130
