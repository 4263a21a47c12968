"""The FastAPI application: `create_app(registry, options)`.

GET / (a page: choose a map, drop a photo, see the camera in the map), GET /healthz, GET /metrics,
GET /v1/maps, GET /v1/maps/{name}/scene, POST /v1/maps/{name}/localize; OpenAPI docs at /docs
(served offline: `usvc.serve.assets`). Every refusal is one JSON error
(`usvc.serve.errors`); docs/serve.md is the API page.
"""

from __future__ import annotations

import hmac
import json
import logging
import shutil
import tempfile
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

import usvc.serve.requests as requests
from usvc.serve.assets import add_offline_docs
from usvc.serve.errors import ApiError, status_reason
from usvc.serve.maps import MapRegistry, ServedMap
from usvc.serve.metrics import Metrics
from usvc.serve.options import ServeOptions
from usvc.serve.page import PAGE
from usvc.serve.photo import check_header, localize_photo
from usvc.serve.processes import ProcessWorkers, WorkerMap
from usvc.serve.scene_view import SceneCache
from usvc.serve.work import WorkPool

log = logging.getLogger("usvc.serve")

LOCALIZE_BODY = {  # OpenAPI: the endpoint reads its body itself (under the limits), in three forms
    "required": True,
    "content": {
        "multipart/form-data": {"schema": {"type": "object", "required": ["photo"], "properties": {
            "photo": {"type": "string", "format": "binary"},
            "focal": {"type": "number", "description": "focal length in px of the photo as shown"},
            "intrinsics": {"type": "string", "description": "fx fy cx cy (px)"},
            "camera": {"type": "string", "description": "COLMAP model and params, e.g. OPENCV fx fy cx cy k1 k2 p1 p2"},
            "no_exif": {"type": "boolean"}, "name": {"type": "string"}}}},
        "application/json": {"schema": {"type": "object", "required": ["photo"], "properties": {
            "photo": {"type": "string", "format": "byte", "description": "the image file, base64"},
            "focal": {"type": "number"}, "intrinsics": {"type": "array", "items": {"type": "number"},
                                                        "minItems": 4, "maxItems": 4},
            "camera": {"type": "object", "properties": {"model": {"type": "string"},
                                                         "params": {"type": "array", "items": {"type": "number"}}}},
            "no_exif": {"type": "boolean"}, "name": {"type": "string"}}}},
        "image/*": {"schema": {"type": "string", "format": "binary"}},
    },
}
ERROR = {"description": "one JSON error: {error, reason, status}"}
LOCALIZE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"description": "the record `usvc localize --format jsonl` writes"},
    400: ERROR, 401: ERROR, 404: ERROR, 408: ERROR, 413: ERROR, 415: ERROR,
    422: {"description": "a refused pose: the error, its reason and the record"}, 503: ERROR, 504: ERROR}


def _error_response(err: ApiError) -> JSONResponse:
    return JSONResponse(err.body(), status_code=err.status, headers=err.headers)


class CountRequests:
    """ASGI middleware: each answer counted by route and status, failures by reason."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500

        async def counted(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, counted)
        finally:
            route = scope.get("route")
            endpoint = getattr(route, "path", None) or "unmatched"
            self.metrics.request(endpoint, status, scope.get("state", {}).get("reason") or status_reason(status))


def create_app(registry: MapRegistry, options: ServeOptions | None = None) -> FastAPI:
    options = (options or ServeOptions()).check()
    metrics = Metrics()
    pool = WorkPool(options.threads, options.queue, options.retry_after_s)
    processes = None
    if options.processes:  # every map again in each worker process, made as the server's was
        processes = ProcessWorkers([WorkerMap(s.name, type(s.relocalizer), s.relocalizer.args) for s in registry],
                                   options.threads, options.process_threads)
    elif options.batch > 1:  # the photos waiting on the threads through the network together
        for served in registry:
            served.relocalizer.batch_network(options.batch)
    workdir = Path(tempfile.mkdtemp(prefix="usvc-serve-"))  # uploads live here for their request only

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        pool.shutdown()
        if processes is not None:
            processes.shutdown()
        shutil.rmtree(workdir, ignore_errors=True)

    app = FastAPI(title="usvc serve", version="1", lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Camera relocalization: a photo's 6-DoF pose in a mapped place (docs/serve.md).")
    app.state.registry, app.state.options, app.state.metrics, app.state.pool = registry, options, metrics, pool
    app.state.workdir, app.state.processes = workdir, processes
    app.add_middleware(CountRequests, metrics=metrics)
    add_offline_docs(app)
    scenes = SceneCache()

    def failed(request: Request, err: ApiError) -> JSONResponse:
        request.state.reason = err.reason
        return _error_response(err)

    @app.exception_handler(ApiError)
    async def api_error(request: Request, err: ApiError) -> JSONResponse:
        return failed(request, err)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, err: StarletteHTTPException) -> JSONResponse:
        reason = status_reason(err.status_code)
        message = {404: f"no such endpoint: {request.method} {request.url.path[:100]}",
                   405: f"{request.method} is not allowed on {request.url.path[:100]}"}.get(err.status_code,
                                                                                             str(err.detail))
        return failed(request, ApiError(reason, message, headers=dict(err.headers or {})))

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, err: RequestValidationError) -> JSONResponse:
        first = err.errors()[0] if err.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ()))
        return failed(request, ApiError("bad_request", f"{where}: {first.get('msg', 'invalid')}"))

    def authorize(request: Request) -> None:
        if options.token is None:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not given:
            raise ApiError("unauthorized", "this server needs 'Authorization: Bearer <token>'",
                           headers={"WWW-Authenticate": "Bearer"})
        if not hmac.compare_digest(given.strip().encode(), options.token.encode()):
            raise ApiError("unauthorized", "wrong token", headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def page() -> HTMLResponse:
        return HTMLResponse(PAGE, headers={"X-Content-Type-Options": "nosniff", "X-Frame-Options": "DENY"})

    @app.get("/healthz", summary="liveness: the maps are loaded and the pool takes work")
    async def healthz() -> dict[str, Any]:
        return {"status": "ok", "maps": registry.names(), **pool.state(), "capacity": pool.capacity}

    @app.get("/metrics", response_class=PlainTextResponse, summary="Prometheus text")
    async def metrics_text(request: Request) -> PlainTextResponse:
        authorize(request)
        return PlainTextResponse(metrics.render(len(registry), **pool.state()),
                                 media_type="text/plain; version=0.0.4; charset=utf-8")

    @app.get("/v1/maps", summary="the maps this server answers for")
    async def list_maps(request: Request) -> dict[str, Any]:
        authorize(request)
        return {"maps": [served.info for served in registry]}

    def served_map(name: str) -> ServedMap:
        served = registry.get(name)
        if served is None:
            raise ApiError("unknown_map", f"no map named {name[:70]!r}; this server has: "
                           f"{', '.join(registry.names()) or 'none'}")
        return served

    @app.get("/v1/maps/{name}/scene", summary="the map's 3D points (subsampled) and mapping cameras, for a view",
             responses={401: ERROR, 404: ERROR})
    async def scene(name: str, request: Request) -> Response:
        authorize(request)
        served = served_map(name)
        data = await run_in_threadpool(scenes.get, served.name, served.relocalizer)  # once per map
        return Response(data, media_type="application/json")

    @app.post("/v1/maps/{name}/localize", summary="a photo's pose in the named map",
              openapi_extra={"requestBody": LOCALIZE_BODY}, responses=LOCALIZE_RESPONSES)
    async def localize(name: str, request: Request) -> Response:
        authorize(request)
        served = served_map(name)
        pool.check_room()  # a full server says so at once, before the upload is read
        body = await requests.read_body(request, options.max_bytes, options.body_timeout_s)
        query = await requests.parse(request, body, options.max_bytes)
        del body
        suffix = check_header(query.photo, options.max_megapixels)
        relocalizer = served.relocalizer
        t0 = time.perf_counter()
        deadline = time.monotonic() + options.timeout_s

        def work() -> dict[str, Any]:
            if processes is not None:
                return processes.localize(name, query.photo, suffix, query.intrinsics, query.name, deadline)
            return localize_photo(relocalizer, query.photo, suffix, query.intrinsics, query.name, workdir)

        try:
            record = await pool.run(work, options.timeout_s)
        except ApiError:
            raise
        except Exception:  # a bug, not the client's: logged here, one line there
            log.exception("localize %s on map %s failed", query.name, name)
            raise ApiError("internal", "the server failed on this photo (its log has the details)") from None
        metrics.latency(time.perf_counter() - t0)
        if not record.get("success"):
            raise ApiError("pose_refused", record.get("rejected") or "no pose", extra={"record": record})
        # json.dumps as `usvc localize` writes the line: the same bytes
        return Response(json.dumps(record), media_type="application/json")

    return app
