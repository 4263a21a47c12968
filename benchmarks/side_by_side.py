"""Two `train` stages side by side against one alone, under a thread setting.

Copies the scene's buffer and SfM tracks into a scratch data folder under two names, times one
`python -m stages.train` run alone, then two started together, and writes
`results/benchmarks/side_by_side_<threads>.json` with each wall time and the ratio (side by side
over alone). With `threads=auto` each of the two takes half the cores; with the core count (what
every process took before the thread policy) they fight. Run it on an otherwise idle machine:

    python benchmarks/side_by_side.py --scene mini --iterations 600 --threads auto
    python benchmarks/side_by_side.py --scene mini --iterations 600 --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _command(scene: str, name: str, data: Path, iterations: int, threads: str) -> list[str]:
    return [sys.executable, "-m", "stages.train", f"scene={scene}", f"scene.name={name}", f"data_dir={data}",
            f"results_dir={data / 'results'}", f"hydra.run.dir={data / 'logs' / name}",
            f"train.iterations={iterations}", f"threads={threads}"]


def _run_together(commands: list[list[str]], env: dict[str, str]) -> list[float]:
    start = time.perf_counter()
    procs = [subprocess.Popen(c, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for c in commands]
    ends = [0.0] * len(procs)
    pending = set(range(len(procs)))
    while pending:
        for i in list(pending):
            if procs[i].poll() is not None:
                ends[i] = time.perf_counter() - start
                pending.discard(i)
        time.sleep(0.05)
    for p in procs:
        if p.returncode != 0:
            raise SystemExit(f"train failed: {p.stderr.read().strip().splitlines()[-1:]}")
    return ends


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mini")
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--threads", default="auto")
    args = parser.parse_args()
    src = ROOT / "data" / args.scene
    for sub in ("buffer", "sfm"):
        if not (src / sub).is_dir():
            raise SystemExit(f"{src / sub} is missing: run the pipeline up to the buffer stage first")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    with tempfile.TemporaryDirectory(prefix="usvc-side-by-side-") as tmp:
        data = Path(tmp)
        for name in ("a", "b"):
            for sub in ("buffer", "sfm"):
                shutil.copytree(src / sub, data / name / sub)
        alone = _run_together([_command(args.scene, "a", data, args.iterations, args.threads)], env)[0]
        pair = _run_together([_command(args.scene, n, data, args.iterations, args.threads) for n in ("a", "b")], env)
    result = {"scene": args.scene, "iterations": args.iterations, "threads": args.threads,
              "cpus": len(os.sched_getaffinity(0)), "alone_seconds": round(alone, 1),
              "side_by_side_seconds": [round(t, 1) for t in pair],
              "ratio": round(max(pair) / alone, 2)}
    out = ROOT / "results" / "benchmarks" / f"side_by_side_{args.threads}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
