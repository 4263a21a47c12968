"""`usvc serve`: its flags, and the server they start (uvicorn, one process; localize work on
--workers threads, or with --processes in --workers worker processes)."""

from __future__ import annotations

import argparse
import logging
import stat
from pathlib import Path

from usvc.core.errors import UsvcError
from usvc.core.precision import PRECISIONS

log = logging.getLogger("usvc.serve")

LOOPBACK = ("127.0.0.1", "::1", "localhost")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    srv = sub.add_parser("serve", help="a localization service over HTTP/JSON (docs/serve.md)")
    srv.add_argument("--map", action="append", metavar="NAME=PATH", default=[],
                     help="a map to serve under NAME (repeatable), e.g. office=data/office/map/map.pt")
    srv.add_argument("--maps-dir", help="serve each NAME/map.pt, NAME/map/map.pt or NAME.pt of this folder as NAME")
    srv.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    srv.add_argument("--port", type=int, default=8000)
    srv.add_argument("--token-file", help="a file holding the bearer token that /v1/* and /metrics then require")
    srv.add_argument("--max-mb", type=float, default=20.0, help="largest request body, MiB (default 20)")
    srv.add_argument("--max-megapixels", type=float, default=50.0,
                     help="largest photo, from its header before decoding (default 50)")
    srv.add_argument("--workers", type=int, default=1,
                     help="photos localized side by side, on threads (each gets --threads divided among them)")
    srv.add_argument("--processes", action="store_true",
                     help="localize side by side in --workers processes (each holding the maps) rather than threads")
    srv.add_argument("--batch", type=int, default=1,
                     help="up to this many photos running side by side go through the network as one batch "
                          "(for a GPU with several --workers; answers may differ in the last bits; default 1: off)")
    srv.add_argument("--queue", type=int, default=8,
                     help="requests that may wait beyond those running; more are answered 503 (default 8)")
    srv.add_argument("--timeout", type=float, default=30.0, help="seconds a request may wait and run (504 after)")
    srv.add_argument("--body-timeout", type=float, default=30.0,
                     help="seconds the request body may take to arrive (408 after)")
    srv.add_argument("--device", default="auto", help="torch device: auto | cpu | cuda | cuda:N")
    srv.add_argument("--precision", choices=PRECISIONS, default="auto")
    srv.add_argument("--log-level", dest="server_log_level", default="info",
                     choices=("critical", "error", "warning", "info", "debug"), help="uvicorn's log level")
    srv.set_defaults(run=run)
    return srv


def read_token(path: str | Path) -> str:
    path = Path(path)
    try:
        mode = path.stat().st_mode
        token = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as e:
        raise UsvcError(f"--token-file {path}: cannot read it ({e})") from None
    if not token or any(c.isspace() for c in token):
        raise UsvcError(f"--token-file {path}: must hold one token (no spaces), and holds "
                        f"{'nothing' if not token else 'several words'}")
    if mode & (stat.S_IRGRP | stat.S_IROTH):
        log.warning("--token-file %s is readable by other users (chmod 600 it)", path)
    return token


def run(args: argparse.Namespace) -> int:
    from usvc.pipeline import threads
    from usvc.relocalize.relocalizer import RelocalizeOptions
    from usvc.serve.maps import MapRegistry, maps_in_folder, parse_map_arg
    from usvc.serve.options import ServeOptions

    maps = [parse_map_arg(m) for m in args.map]
    if args.maps_dir:
        maps += maps_in_folder(args.maps_dir)
    if not maps:
        raise UsvcError("give at least one map: --map NAME=PATH (repeatable) or --maps-dir FOLDER")
    if not 0 < args.port < 65536:
        raise UsvcError(f"--port {args.port}: must be 1-65535")
    if not 0 < args.max_mb <= 1024:
        raise UsvcError(f"--max-mb {args.max_mb:g}: must be in (0, 1024]")
    token = read_token(args.token_file) if args.token_file else None
    options = ServeOptions(max_bytes=int(args.max_mb * 1024 * 1024), max_megapixels=args.max_megapixels,
                           threads=args.workers, processes=args.processes, batch=args.batch,
                           process_threads=max(1, args.threads // args.workers), queue=args.queue, timeout_s=args.timeout,
                           body_timeout_s=args.body_timeout, token=token).check()
    if args.host not in LOOPBACK and token is None:
        log.warning("serving on %s without --token-file: anyone who reaches it may use it", args.host)
    threads.apply(max(1, args.threads // args.workers))  # the cores shared among the photos running side by side
    registry = MapRegistry()
    relocalize = RelocalizeOptions(precision=args.precision)
    for name, path in maps:
        registry.load(name, path, relocalize, device=args.device)

    import uvicorn

    from usvc.serve.app import create_app

    app = create_app(registry, options)
    log.info("serving %s on http://%s:%d (docs at /docs)", ", ".join(registry.names()), args.host, args.port)
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.server_log_level, access_log=args.server_log_level == "debug",
                timeout_keep_alive=5, server_header=False, proxy_headers=False)
    return 0


