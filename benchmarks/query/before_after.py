"""Time the default query step of the code at a git revision against this tree's, on the same photos, back to back, and check that both give the same answers.

`--before REV` is checked out into a temporary git worktree. Each run is a child process with one
tree first on its PYTHONPATH (`_revision_run.py`): it localizes every query photo of the scene with
the scene's own map (given intrinsics, `relocalize.refine=features`, OpenCV's SIFT unless
--extractor colmap), --passes times after 2 warm-up photos, and reports the seconds and the answers
(pose, refusal). Per scene and size the runs alternate before/after --rounds times, so that a
machine whose speed drifts affects both alike. Writes
results/benchmarks/query_before_after[_<variant>].json: per scene and size, each run's median
seconds per query, the median over the runs, and how many answers are the same, bit for bit (not
counted where `--before-scene-dir` gives the revision other folders). Run (nothing else heavy running):
python -m benchmarks.query before-after --before HEAD~3 --scene-dir data/mini data/office data/bird --size own 640x480
`--final guided` times both trees' guided passes alone (a tree from before the last pass has no other).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks._report import ROOT, report_name, scene_of, write_report

CHILD = Path(__file__).resolve().parent / "_revision_run.py"


def _run(tree: Path, scene_dir: Path, size: str, passes: int, extractor: str, final: str, tmp: Path) -> dict:
    out = tmp / "run.json"
    cmd = [sys.executable, str(CHILD), str(tree), str(scene_dir.resolve()), size, str(passes), extractor, final,
           str(out)]
    path = os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p)
    proc = subprocess.run(cmd, cwd=tmp, env={**os.environ, "PYTHONPATH": path}, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"a run in {tree} failed:\n{proc.stderr[-3000:]}")
    return json.loads(out.read_text())


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--before", required=True, help="git revision of the code to compare with this tree's")
    ap.add_argument("--scene-dir", type=Path, nargs="+", required=True)
    ap.add_argument("--size", nargs="+", default=["own"], help="'own' (the photos as prepared) and/or WxH")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--extractor", choices=["opencv", "colmap"], default="opencv")
    ap.add_argument("--final", choices=["default", "confirmed", "guided", "images"], default="default",
                    help="relocalize.features_final in both trees (a tree without it ends with the guided passes)")
    ap.add_argument("--before-scene-dir", type=Path, nargs="+",
                    help="the scene folders the revision reads instead, one per --scene-dir (the same map, its "
                         "landmarks in the format that code reads); its answers are then not compared")


def run(args: argparse.Namespace) -> None:
    before_dirs = args.before_scene_dir or args.scene_dir
    if len(before_dirs) != len(args.scene_dir):
        args.parser.error(f"--before-scene-dir: {len(before_dirs)} folders for {len(args.scene_dir)} --scene-dir")
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        before = tmp / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(before), args.before],
                       check=True)
        try:
            for scene_dir, before_dir in zip(args.scene_dir, before_dirs):
                for size in args.size:
                    runs: dict[str, list[dict]] = {"before": [], "after": []}
                    for _ in range(args.rounds):
                        for which, tree, folder in (("before", before, before_dir), ("after", ROOT, scene_dir)):
                            runs[which].append(_run(tree, folder, size, args.passes, args.extractor, args.final, tmp))
                    ms = {k: [r["median_ms"] for r in v] for k, v in runs.items()}
                    same = sum(a == b for a, b in zip(runs["before"][0]["answers"], runs["after"][0]["answers"])) \
                        if before_dir == scene_dir else None
                    row = {"scene": scene_of(scene_dir), "size": size, "queries": runs["after"][0]["queries"],
                           "threads": runs["after"][0]["threads"], "before_ms": ms["before"], "after_ms": ms["after"],
                           "before_median_ms": statistics.median(ms["before"]),
                           "after_median_ms": statistics.median(ms["after"]), "answers_same": same}
                    rows.append(row)
                    print(f"{row['scene']:8s} {size:8s} before {row['before_median_ms']:.0f} ms  after "
                          f"{row['after_median_ms']:.0f} ms  same answers {same} of {row['queries']}")
                    if before_dir != scene_dir:
                        row["before_scene_dir"] = str(before_dir)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(before)], check=False)
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", args.before], capture_output=True, text=True)
    write_report(report_name(args), {"before": rev.stdout.strip(), "extractor": args.extractor,
                                     "final": args.final, "rows": rows})

