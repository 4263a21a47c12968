"""Two methods' poses on one scene's queries, compared query by query (usvc/metrics/paired.py).

Reads two poses files (`name qw qx qy qz tx ty tz` lines, as the relocalize stage writes
data/<scene>/relocalize/poses.txt and `baseline-sift --poses-dir` writes SIFT + PnP's; a query
missing from a file is unanswered) and the scene's ground truth, and reports every figure of the
metrics stage for both, their difference (a - b) with a paired bootstrap interval over the
queries, and on how many queries each is the closer with the sign test's p-value. With few
queries, an interval that holds 0 says the split cannot tell the two apart at that figure.
Writes results/benchmarks/accuracy_compare_poses_<scene>_<a-name>_vs_<b-name>.json.
Run: python -m benchmarks.accuracy compare-poses --scene office --a data/office/relocalize/poses.txt \
       --b baseline_poses/poses_seed0.txt [--a-name usvc --b-name sift_pnp] [--resamples 10000] [override ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks._report import report_name, write_report
from usvc.core.poses_file import read_poses_txt
from usvc.core.scene_file import read_scene_h5
from usvc.metrics.paired import paired_comparison, query_errors
from usvc.pipeline.config import compose_for_script
from usvc.pipeline.logs import script_logging
from usvc.pipeline.stage import scene_paths
from usvc.sfm.tracks_file import read_median_depth


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="scene config name (conf/scene/<name>.yaml)")
    parser.add_argument("--a", type=Path, required=True, help="the first method's poses file")
    parser.add_argument("--b", type=Path, required=True, help="the second method's poses file")
    parser.add_argument("--a-name", default="a", help="the first method's name in the report")
    parser.add_argument("--b-name", default="b", help="the second method's name in the report")
    parser.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples of the queries")
    parser.add_argument("--level", type=float, default=0.95, help="the intervals' coverage")
    parser.add_argument("--seed", type=int, default=0, help="the resampling's seed")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. data_dir=...")


def run(args: argparse.Namespace) -> None:
    script_logging()  # bad input (a UsvcError) then ends the script in one line
    cfg = compose_for_script(args.scene, args.overrides)
    paths = scene_paths(cfg)
    scene = read_scene_h5(paths.scene_file)
    median_depth = read_median_depth(paths.tracks_file)
    a = query_errors(scene, read_poses_txt(args.a), str(args.a))
    b = query_errors(scene, read_poses_txt(args.b), str(args.b))
    result = paired_comparison(a, b, scene.metric_scale, median_depth, args.resamples, args.level, args.seed)
    report = {"scene": scene.name, "a": {"name": args.a_name, "poses": str(args.a)},
              "b": {"name": args.b_name, "poses": str(args.b)}, **result}
    print(f"{scene.name}: {args.a_name} (a) against {args.b_name} (b), {result['queries']} queries, "
          f"{100 * args.level:g} % paired bootstrap intervals of a - b")
    for key, fig in result["figures"].items():
        lo, hi = fig["interval"]
        print(f"  {key:22s} {_fmt(fig['a']):>9s} {_fmt(fig['b']):>9s}  a-b {_fmt(fig['difference']):>9s}"
              f"  [{_fmt(lo)}, {_fmt(hi)}]")
    ratio = result["median_translation_over"]
    print(f"  median translation a / b {_fmt(ratio['value'])}  [{_fmt(ratio['interval'][0])}, "
          f"{_fmt(ratio['interval'][1])}]")
    pq = result["per_query"]
    print(f"  closer: a on {pq['a_closer']}, b on {pq['b_closer']}, equal {pq['equal']}; sign test p = "
          f"{pq['sign_test_p']:.3g}; median translation ratio a/b {_fmt(pq['median_translation_ratio'])}")
    name = report_name(args, scene.name, f"{args.a_name}_vs_{args.b_name}")
    print(f"-> {write_report(name, report)}")

