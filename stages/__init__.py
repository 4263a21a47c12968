"""One module per pipeline stage (`python -m stages.<name> scene=<name> [overrides]`).

Importing the package sets the BLAS/OpenMP thread variables from `threads=` on the command line
(default auto) before any stage imports numpy or torch: those pools read them once, when they
load. The stage shell (`usvc.pipeline.stage.Stage`) then sets torch's and OpenCV's pools from
the composed config.
"""

import sys

from usvc.pipeline.threads import export_to_env, resolve, setting_from_argv

try:
    export_to_env(resolve(setting_from_argv(sys.argv[1:])))
except ValueError:
    pass  # a bad value is reported by the config validation, naming the key
