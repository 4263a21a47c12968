"""usvc's benchmarks: four families of questions, each one entry point with a subcommand per question.

    python -m benchmarks.query SUBCOMMAND ...     # what a query costs: speed, models, before-after, cli, folder,
                                                  #   serve-load
    python -m benchmarks.train SUBCOMMAND ...     # what training costs: throughput, profile, bundle-cost,
                                                  #   side-by-side, busy-machine, splat-render
    python -m benchmarks.pipeline SUBCOMMAND ...  # whole pipelines: time, fresh, device, scaling,
                                                  #   triangulation
    python -m benchmarks.accuracy SUBCOMMAND ...  # how right the answers are: baseline-sift, compare-poses,
                                                  #   confidence, diagnose-map, focal, keypoints, pnp-solvers,
                                                  #   sfm-posing, wrong-prior

Run from the checkout's root (`python -m benchmarks.<family> --help` lists the subcommands,
`... <subcommand> --help` their options). Every subcommand writes its figures to
`results/benchmarks/<family>_<subcommand>[_<scene>][_<variant>].json` (`_report.py`: the naming
rule, the command line and the machine context); `USVC_BENCHMARK_DIR` sends them elsewhere.
"""
