"""`usvc serve`: a localization service over HTTP/JSON (FastAPI on uvicorn).

Maps are registered by name at start (`maps.MapRegistry`), each loaded once; `POST
/v1/maps/{name}/localize` answers a photo with the record `usvc localize --format jsonl` writes
(`app.create_app`). Limits, the bounded queue and the per-request time limit are `ServeOptions`;
docs/serve.md is the API and operations page.
"""

from __future__ import annotations

from usvc.serve.maps import MapRegistry
from usvc.serve.options import ServeOptions

__all__ = ["MapRegistry", "ServeOptions", "create_app"]


def __getattr__(name: str):  # the app pulls in FastAPI: only when asked for
    if name == "create_app":
        from usvc.serve.app import create_app

        return create_app
    raise AttributeError(name)
