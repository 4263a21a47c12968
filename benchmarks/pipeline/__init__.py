"""Whole pipelines: `python -m benchmarks.pipeline SUBCOMMAND [options]`.

Reports: results/benchmarks/pipeline_<subcommand>[_<scene>][_<variant>].json.
"""

SUBCOMMANDS = {  # subcommand: (module, what it measures)
    "time": ("stage_times", "each stage of a scene in this checkout: wall seconds and peak memory"),
    "fresh": ("fresh", "a new user's first command: `dvc repro` (or `usvc map PHOTOS`) in a fresh clone"),
    "device": ("device", "every stage of a scene on one device (the GPU path), end to end"),
    "scaling": ("scaling", "every stage of the generated room at several sizes: how a map's cost grows"),
    "triangulation": ("triangulation", "SfM's triangulation with poses: COLMAP's one problem against usvc's groups"),
}
