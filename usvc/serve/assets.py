"""The page's and the API docs' scripts and styles, served by the service itself (no CDN: the page
and /docs work offline): plotly.js from the `plotly` package, Swagger UI 5 (it reads FastAPI's
OpenAPI 3.1) from the files the `fastapi-offline` package ships.

`add_offline_docs(app)` adds GET /docs (Swagger UI on those assets) and GET /static/{asset}; the
app is made with `docs_url=None, redoc_url=None`. Each file is read once and kept, with its gzip.
"""

from __future__ import annotations

import gzip
import threading
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, Response
from starlette.concurrency import run_in_threadpool

from usvc.serve.errors import ApiError

CACHE_CONTROL = "public, max-age=604800"  # a week: the files change only with the installed packages


@dataclass(frozen=True)
class Asset:
    package: str  # the Python package that ships the file
    parts: tuple[str, ...]  # its path inside the package
    media_type: str


JS = "text/javascript; charset=utf-8"
ASSETS: dict[str, Asset] = {
    "plotly.min.js": Asset("plotly", ("package_data", "plotly.min.js"), JS),
    "swagger-ui-bundle.js": Asset("fastapi_offline", ("static", "swagger-ui-bundle.js"), JS),
    "swagger-ui.css": Asset("fastapi_offline", ("static", "swagger-ui.css"), "text/css; charset=utf-8"),
    "favicon.png": Asset("fastapi_offline", ("static", "favicon.png"), "image/png"),
}


def asset_path(asset: Asset) -> Path:
    """The file in the installed package."""
    return Path(str(resources.files(asset.package).joinpath(*asset.parts)))


class AssetStore:
    """Each asset's bytes and gzip, read on first request and then kept."""

    def __init__(self) -> None:
        self._kept: dict[str, tuple[bytes, bytes]] = {}
        self._lock = threading.Lock()

    def get(self, name: str) -> tuple[bytes, bytes]:
        asset = ASSETS.get(name)
        if asset is None:
            raise ApiError("not_found", f"no such file: /static/{name[:70]}")
        with self._lock:
            if name not in self._kept:
                try:
                    data = asset_path(asset).read_bytes()
                except (OSError, ImportError) as exc:
                    raise ApiError("internal", f"/static/{name}: the {asset.package} package's file is "
                                   f"missing ({type(exc).__name__}); reinstall usvc's dependencies") from None
                self._kept[name] = data, gzip.compress(data, compresslevel=6, mtime=0)
            return self._kept[name]

    def response(self, name: str, accept_encoding: str) -> Response:
        data, packed = self.get(name)
        headers = {"Cache-Control": CACHE_CONTROL, "X-Content-Type-Options": "nosniff", "Vary": "Accept-Encoding"}
        if "gzip" in accept_encoding.lower() and ASSETS[name].media_type != "image/png":
            return Response(packed, media_type=ASSETS[name].media_type, headers={**headers, "Content-Encoding": "gzip"})
        return Response(data, media_type=ASSETS[name].media_type, headers=headers)


def add_offline_docs(app: FastAPI) -> AssetStore:
    """GET /static/{name} (ASSETS) and GET /docs: Swagger UI on the served copies."""
    store = AssetStore()

    @app.get("/static/{name}", include_in_schema=False)
    async def static(name: str, request: Request) -> Response:
        # read and compressed once, off the event loop
        return await run_in_threadpool(store.response, name, request.headers.get("accept-encoding", ""))

    @app.get("/docs", include_in_schema=False)
    async def docs(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "").rstrip("/")
        return get_swagger_ui_html(openapi_url=root + (app.openapi_url or "/openapi.json"),
                                   title=f"{app.title} - API", swagger_js_url=root + "/static/swagger-ui-bundle.js",
                                   swagger_css_url=root + "/static/swagger-ui.css",
                                   swagger_favicon_url=root + "/static/favicon.png")

    return store
