"""One module per pipeline stage (`python -m stages.<name> scene=<scene> [overrides]`).

Importing the package sets the BLAS/OpenMP thread variables from `threads=` on the command line
(default auto) before any stage imports numpy or torch; `stage_main` then sets torch's and
OpenCV's pools from the composed config.
"""

import sys

from usvc.pipeline.threads import export_to_env, resolve, setting_from_argv

try:
    export_to_env(resolve(setting_from_argv(sys.argv[1:])))
except ValueError:
    pass  # a bad value is reported by the config validation, naming the key

# `python -m stages.<stage> --help`: the stage's options and their meaning (Hydra's: --hydra-help).
_module = next((a for a in sys.orig_argv if a.startswith("stages.")), "")
if ("--help" in sys.argv[1:] or "-h" in sys.argv[1:]) and _module.count(".") == 1:
    from usvc.pipeline.stage_help import pipeline_stages, stage_help

    if _module.split(".")[1] in pipeline_stages():
        print(stage_help(_module.split(".")[1], [a for a in sys.argv[1:] if a not in ("--help", "-h")]))
        sys.exit(0)
