"""How close are SfM poses of an unposed capture (``scene.format=images``) to the capture's given poses?

Both arguments are prepared scene folders of the same photos (same split): one imported with its
poses, one posed by SfM in the prepare stage. Photos are matched by name, or, when the two scenes
name them differently (``images/0000.jpg`` against ``0000.jpg``), by file name; a file name that
two photos of one scene share is refused as ambiguous. A similarity (Umeyama, on the
mapping photos' camera centres) brings the SfM frame into the given one; the report gives
rotation and centre errors per split, centre errors also as a fraction of the scene extent
(median distance of the centres from their mean). With ``--relocalized``, query poses that the
SfM-posed scene's map produced are mapped by the same similarity into the given frame and scored
against the given poses (the usual 5° / 3 % of median depth rule). Prints the JSON, writes it to
``--out`` when given, and with the command line and the machine context to
results/benchmarks/accuracy_sfm_posing_<scene>.json (<scene>: the SfM-posed scene, data/<scene>/prepared).

Run: python -m benchmarks.accuracy sfm-posing --given data/office/prepared --sfm data/office_photos/prepared
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path, PurePosixPath

import numpy as np

from benchmarks._report import report_name, scene_of, write_out, write_report
from usvc.core.errors import UsvcError
from usvc.core.pose_errors import rotation_error_deg, summarize, translation_error
from usvc.core.poses_file import read_poses_txt
from usvc.core.scene import Frame
from usvc.core.scene_file import read_scene_h5
from usvc.metrics.alignment import align_and_compare
from usvc.pipeline.paths import SCENE_H5, TRACKS_H5
from usvc.sfm.tracks_file import read_median_depth


def _file_name(name: str) -> str:
    return PurePosixPath(name.replace("\\", "/")).name


def _file_names(names: list[str], which: str, shared_with: set[str]) -> dict[str, str]:
    """{file name: name}; a file name of two photos is an error when the other scene has it too."""
    out: dict[str, str] = {}
    for name in sorted(names):
        base = _file_name(name)
        if base in out and base in shared_with:
            raise UsvcError(f"the {which} scene has two photos named {base!r} ({out[base]} and {name}): "
                            "cannot match the two scenes' photos by file name")
        out.setdefault(base, name)
    return out


def match_photos(given: list[Frame], sfm: list[Frame]) -> tuple[dict[str, str], str]:
    """({SfM-posed photo's name: given photo's name}, "name" or "file name") for the photos both
    scenes hold: by name when every SfM-posed photo's name is a given one, else by file name."""
    given_names, sfm_names = [f.name for f in given], [f.name for f in sfm]
    if set(sfm_names) <= set(given_names):
        return {n: n for n in sfm_names}, "name"
    given_bases, sfm_bases = {_file_name(n) for n in given_names}, {_file_name(n) for n in sfm_names}
    by_given = _file_names(given_names, "given", sfm_bases)
    by_sfm = _file_names(sfm_names, "SfM-posed", given_bases)
    names = {by_sfm[b]: by_given[b] for b in by_sfm if b in by_given}
    if not names:
        example = f" (e.g. given {given_names[0]!r}, SfM-posed {sfm_names[0]!r})" if given_names and sfm_names else ""
        raise UsvcError(f"the two scenes share no photo by name or file name{example}: are they of the same capture?")
    return names, "file name"


def _summary(rot: np.ndarray, centre: np.ndarray, extent: float) -> dict:
    return {"n": int(len(rot)),
            "median_rot_deg": float(np.median(rot)), "max_rot_deg": float(np.max(rot)),
            "median_centre": float(np.median(centre)), "max_centre": float(np.max(centre)),
            "median_centre_pct_extent": float(100 * np.median(centre) / extent),
            "max_centre_pct_extent": float(100 * np.max(centre) / extent)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--given", type=Path, required=True, help="prepared scene with the capture's poses")
    parser.add_argument("--sfm", type=Path, required=True, help="prepared scene posed by SfM")
    parser.add_argument("--relocalized", type=Path, action="append", default=[],
                        help="poses.txt of the SfM-posed scene's relocalize stage (repeatable, e.g. one per seed): "
                             "scored against the given poses after the same similarity")
    parser.add_argument("--given-sfm", type=Path, help="the given scene's sfm folder (median depth for the 3 %% rule)")
    parser.add_argument("--out", type=Path, help="write the JSON here too")


def run(args: argparse.Namespace) -> None:
    parser = args.parser
    given, sfm = read_scene_h5(args.given / SCENE_H5), read_scene_h5(args.sfm / SCENE_H5)
    try:
        names, matched_by = match_photos(given.frames, sfm.frames)
    except UsvcError as e:
        parser.exit(2, f"error: {e}\n")
    posed_by_sfm = len(sfm.frames)
    sfm = replace(sfm, frames=[replace(f, name=names[f.name]) for f in sfm.frames if f.name in names])
    mapping = {f.name for f in sfm.frames if f.split == "train"}
    errors = align_and_compare(sfm.frames, given.frames, fit_on=mapping)
    is_map = np.array([n in mapping for n in errors.names])
    report = {"given": str(args.given), "sfm": str(args.sfm), "photos": len(given.frames),
              "posed_by_sfm": posed_by_sfm, "matched_by": matched_by, "shared": len(sfm.frames),
              "scale_given_per_sfm": errors.scale, "extent": errors.extent,
              "mapping": _summary(errors.rotation_deg[is_map], errors.center_error[is_map], errors.extent),
              "query": _summary(errors.rotation_deg[~is_map], errors.center_error[~is_map], errors.extent)}
    if args.relocalized:
        if args.given_sfm is None:
            parser.error("--relocalized needs --given-sfm (the median scene depth of the given poses)")
        depth = read_median_depth(args.given_sfm / TRACKS_H5)
        truth = {f.name: f for f in given.split("test")}
        runs = []
        for path in args.relocalized:
            poses = {names.get(n, n): pose for n, pose in read_poses_txt(path).items()}
            rot, tr = [], []
            for name, f in truth.items():
                if name not in poses:
                    rot.append(np.inf), tr.append(np.inf)
                    continue
                R, t = errors.similarity.pose(*poses[name])
                rot.append(float(rotation_error_deg(R, f.R))), tr.append(float(translation_error(R, t, f.R, f.t)))
            runs.append({"poses": str(path), **summarize(rot, tr, given.metric_scale, depth, None, 0.0)})
        report["relocalized_in_given_frame"] = runs
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        write_out(args.out, text + "\n")
    write_report(report_name(args, scene_of(args.sfm, "prepared")), report)

