"""usvc: camera relocalization by scene coordinate regression with multi-view training constraints.

`from usvc import Relocalizer` is resolved lazily, so importing a light submodule (errors,
config) does not pull in torch.
"""

from __future__ import annotations

from typing import Any

__all__ = ["PoseEstimate", "RelocalizeOptions", "Relocalizer"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from usvc.relocalize import relocalizer

        return getattr(relocalizer, name)
    raise AttributeError(f"module 'usvc' has no attribute {name!r}")
