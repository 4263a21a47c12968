"""What training costs: `python -m benchmarks.train SUBCOMMAND [options]`.

Reports: results/benchmarks/train_<subcommand>[_<scene>][_<variant>].json.
"""

SUBCOMMANDS = {  # subcommand: (module, what it measures)
    "throughput": ("throughput", "the head's training, iterations per second, against the CPU's product peak"),
    "profile": ("step_profile", "where a training step's time goes on a device (torch's profiler)"),
    "bundle-cost": ("bundle_cost", "seconds per iteration with the bundle loss against without it"),
    "side-by-side": ("side_by_side", "two `train` stages side by side against one alone, under a thread setting"),
    "busy-machine": ("busy_machine", "a `train` stage alone, beside a busy loop and beside a second stage"),
    "splat-render": ("splat_render", "the 3DGS rasteriser: ms per render and per render + backward"),
}
