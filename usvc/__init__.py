"""usvc: camera relocalization by scene coordinate regression with multi-view training constraints.

`from usvc import Relocalizer` is resolved lazily, so importing a light submodule (errors,
config) does not pull in torch. Importing it sets OpenMP's wait policy (usvc.pipeline.threads)
unless the user set one, so import usvc before torch to have it.
"""

from __future__ import annotations

import os
from typing import Any

from usvc.pipeline.threads import set_wait_policy

# Before torch or numpy load: OpenMP threads sleep at barriers instead of spinning (see threads.py).
set_wait_policy()
# Before CUDA starts: cuBLAS's deterministic workspace, which training's deterministic kernels on
# CUDA need (same seed and device, same map); nothing on a CPU.
os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")

__all__ = ["PoseEstimate", "RelocalizeOptions", "Relocalizer"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from usvc.relocalize import relocalizer

        return getattr(relocalizer, name)
    raise AttributeError(f"module 'usvc' has no attribute {name!r}")
