"""What a query costs: `python -m benchmarks.query SUBCOMMAND [options]`.

Reports: results/benchmarks/query_<subcommand>[_<scene>][_<variant>].json.
"""

SUBCOMMANDS = {  # subcommand: (module, what it measures)
    "speed": ("speed", "real queries of a scene, photo in and pose out, with each refinement"),
    "models": ("models", "one query split into encoder, head and PnP, per configured model and size"),
    "before-after": ("before_after", "the default query step of a git revision against this tree's"),
    "cli": ("cli", "`usvc localize` as a user runs it, one command per photo and one for all"),
    "folder": ("folder", "photos per second for a folder of photos, one at a time and several at once"),
    "serve-load": ("serve_load", "`usvc serve` under N concurrent clients on loopback: throughput, latency, memory"),
}
