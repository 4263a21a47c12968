"""What a query answers when its learned pose is wrong: refinement by features from a perturbed prior.

Every query photo of a scene is localized as the relocalize stage does it (the photo file and its
camera, distortion included; the default options; --ransac-seed as the stage's seed), except that the learned pose (the dense RANSAC-PnP's answer on the map's scene
coordinates) is replaced by one turned by D degrees about a random axis and moved by S times the
scene's radius (the median distance of its mapping cameras from their centroid) in a random
direction, for each --perturb D:S. The prior keeps its inlier count, so it looks as confident as
the real one (with --weak it has 5 inliers: below min_confidence, so the matches to every landmark
compete too). The relocalizer then does what it always does: guided passes from that prior, the
matches to every landmark and SIFT + PnP's evidence where those fail. Per perturbation the report
gives the figures of `usvc.core.pose_errors.summarize` against the ground truth (the rel
thresholds at a 1.5 m median depth), the photos refused, which evidence gave each answer
(`refine_path`), and how many answers are bit for bit those of the unperturbed run (the first,
0:0, always run). Writes results/benchmarks/accuracy_wrong_prior_<scene>[_weak].json. Run (nothing
else heavy):

    python -m benchmarks.accuracy wrong-prior --scene-dir data/office --perturb 10:0.1 30:0.3 60:1 120:2
"""

from __future__ import annotations

import argparse
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from benchmarks._report import report_name, scene_of, write_report
from usvc.core.geometry import camera_centers
from usvc.core.pose_errors import summarize
from usvc.core.scene import Camera
from usvc.core.scene_file import read_scene_h5
from usvc.metrics.paired import query_errors
from usvc.pipeline.paths import ScenePaths
from usvc.relocalize import relocalizer as relocalizer_module
from usvc.relocalize.pnp import PnPResult
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer
from usvc.sfm.tracks_file import read_median_depth

FIGURES = ("acc_rel_5cm_5deg", "acc_rel_2cm_2deg", "acc_rel_1cm_1deg", "median_trans_rel_cm", "median_rot_deg")


def perturbed_pose(R: np.ndarray, t: np.ndarray, degrees: float, shift: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) (world to camera) turned by `degrees` about a random axis through the camera centre
    and its centre moved by `shift` (scene units) in a random direction."""
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    turn = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    centre = camera_centers(R, t) + shift * direction / np.linalg.norm(direction)
    R2 = turn @ R
    return R2, -R2 @ centre


def scene_radius(paths: ScenePaths) -> float:
    """The median distance of the mapping cameras from their centroid (scene units)."""
    centres = np.array([camera_centers(f.R, f.t) for f in read_scene_h5(paths.scene_file).split("train")
                        if f.R is not None])
    return float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))


def run(reloc: Relocalizer, photos: list[tuple[Path, Camera]], names: list[str], degrees: float, shift: float, weak: bool,
        seed: int) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[dict], int]:
    """Every photo localized with its learned pose perturbed; (answers by name, a record per photo,
    how many learned poses were perturbed)."""
    rng = np.random.default_rng(seed)
    solve = relocalizer_module.solve_pnp
    count = [0]

    def perturbed(*args, **kwargs) -> PnPResult:
        res = solve(*args, **kwargs)
        if not res.success or (degrees == 0 and shift == 0 and not weak):
            return res
        count[0] += 1
        R, t = perturbed_pose(res.R, res.t, degrees, shift, rng)
        return PnPResult(True, R, t, res.inlier_mask, 5 if weak else res.num_inliers, res.seconds)

    relocalizer_module.solve_pnp = perturbed  # the dense PnP of `Relocalizer._learned_pose`
    try:
        answers, records = {}, []
        for name, (photo, camera) in zip(names, photos):
            est = reloc.localize(photo, camera)
            if est.success:
                answers[name] = (est.R, est.t)
            records.append({"name": name, "answered": bool(est.success), "path": est.refine_path,
                            "feature_inliers": int(est.feature_inliers), "hypotheses": est.feature_hypotheses,
                            "rejected": est.rejected})
    finally:
        relocalizer_module.solve_pnp = solve
    return answers, records, count[0]


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene-dir", type=Path, required=True)
    ap.add_argument("--perturb", nargs="+", default=["10:0.1", "30:0.3", "60:1", "120:2"],
                    help="DEGREES:SHIFT pairs, SHIFT in scene radii")
    ap.add_argument("--weak", action="store_true", help="the perturbed prior has 5 inliers (below min_confidence)")
    ap.add_argument("--seed", type=int, default=0, help="the random axes and directions")
    ap.add_argument("--ransac-seed", type=int, default=0, help="the relocalizer's seed (the stage's `seed`)")
    ap.add_argument("--option", nargs="*", default=[], metavar="KEY=VALUE",
                    help="relocalize options other than the defaults, e.g. features_retrieval_images=0")


def run(args: argparse.Namespace) -> None:
    perturbations = [(0.0, 0.0)]
    for item in args.perturb:
        try:
            deg, shift = (float(v) for v in item.split(":"))
        except ValueError:
            raise SystemExit(f"--perturb {item!r}: expected DEGREES:SHIFT, e.g. 30:0.3") from None
        perturbations.append((deg, shift))
    paths = ScenePaths.of_scene_dir(args.scene_dir)
    scene = read_scene_h5(paths.scene_file)
    names = [f.name for f in scene.split("test")]
    photos = [(f.image_path, f.camera) for f in scene.split("test")]
    radius, median_depth = scene_radius(paths), read_median_depth(paths.tracks_file)
    options = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or key not in RelocalizeOptions.__dataclass_fields__:
            raise SystemExit(f"--option {item!r}: expected KEY=VALUE with KEY a relocalize option")
        options[key] = yaml.safe_load(value)
    reloc = Relocalizer(paths.map_file, options=RelocalizeOptions(**options), device="cpu", seed=args.ransac_seed)
    rows, reference = [], None
    for degrees, shift in perturbations:
        answers, records, perturbed_count = run(reloc, photos, names, degrees, shift, args.weak and degrees + shift > 0,
                                                args.seed)
        if degrees + shift > 0 and perturbed_count == 0:
            raise SystemExit("no learned pose was perturbed: the relocalizer no longer calls solve_pnp by that name")
        errors = query_errors(scene, answers, "wrong_prior")
        summary = summarize(errors.rot_deg, errors.trans, scene.metric_scale, median_depth, errors.failed)
        for record, rot, trans in zip(records, errors.rot_deg, errors.trans):  # rel cm: at a 1.5 m median depth
            record.update(rot_deg=float(rot) if np.isfinite(rot) else None,
                          trans_rel_cm=float(150 * trans / median_depth) if np.isfinite(trans) else None)
        reference = answers if reference is None else reference
        same = sum(n in answers and n in reference and np.array_equal(answers[n][0], reference[n][0])
                   and np.array_equal(answers[n][1], reference[n][1]) for n in names)
        paths_used = sorted({r["path"] for r in records if r["answered"]})
        row = {"degrees": degrees, "shift_radii": shift, "perturbed": perturbed_count,
               **{k: summary.get(k) for k in FIGURES}, "refused": sum(not r["answered"] for r in records),
               "paths": {p: sum(r["path"] == p for r in records if r["answered"]) for p in paths_used},
               "same_as_unperturbed": int(same), "queries": records}
        rows.append(row)
        print(f"{degrees:5g} deg {shift:4g} radii: rel (5cm,5deg) {100 * row['acc_rel_5cm_5deg']:.1f} % (2cm,2deg) "
              f"{100 * row['acc_rel_2cm_2deg']:.1f} % (1cm,1deg) {100 * row['acc_rel_1cm_1deg']:.1f} %, median "
              f"{row['median_trans_rel_cm']:.3f} rel cm; refused {row['refused']}; paths {row['paths']}; "
              f"same as unperturbed {same} of {len(names)}")
    name = report_name(args, scene_of(args.scene_dir), "weak" if args.weak else None)
    report = {"scene": scene.name, "queries": len(names), "weak": args.weak, "seed": args.seed, "options": options,
              "scene_radius": radius, "rows": rows}
    print(f"-> {write_report(name, report)}")

