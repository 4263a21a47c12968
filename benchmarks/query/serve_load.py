"""Load on `usvc serve` over loopback: N concurrent clients send real query photos (a 503 waits its Retry-After) (multipart, each
with its intrinsics from the scene, as an app that knows its camera would) for --seconds or
--requests; reports throughput, p50/p95/p99 latency (and p50/p99 of the 503s), answers by status, and the server's peak
memory (VmHWM, and its RSS at the start and the end: flat memory over a long run). The server is
started here (`usvc serve` on a free port, --workers/--queue/--threads as given) unless --url
names a running one. Writes results/benchmarks/query_serve_load_<scene>_c<clients>_w<workers>.json.
Run (nothing else heavy running):
python -m benchmarks.query serve-load --scene-dir data/office --clients 1 2 4 --workers 1 --seconds 60
python -m benchmarks.query serve-load --scene-dir data/office --clients 4 --workers 2 --threads 2 --seconds 300
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path


from benchmarks._report import report_name, scene_of, write_report
from usvc.pipeline.paths import ScenePaths


def query_files(scene_dir: Path) -> list[tuple[Path, tuple[float, float, float, float]]]:
    """The scene's query photos (its test split) as files, with (fx, fy, cx, cy) of each."""
    from usvc.core.scene_file import read_scene_h5
    from usvc.pipeline.paths import ScenePaths

    out = []
    for f in read_scene_h5(ScenePaths.of_scene_dir(scene_dir).scene_file).split("test"):
        (fx, fy), (cx, cy) = f.camera.focal, f.camera.principal_point
        out.append((Path(f.image_path), (fx, fy, cx, cy)))
    if not out:
        raise SystemExit(f"{scene_dir}: no query photos (test split)")
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def memory_kb(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM (peak) of a process, kB (Linux)."""
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0])
    except OSError:
        pass
    return out


def start_server(args: argparse.Namespace, scene: str, map_file: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    cmd = [sys.executable, "-m", "usvc.cli", "--threads", str(args.threads), "serve", "--map", f"{scene}={map_file}",
           "--port", str(port), "--workers", str(args.workers), "--queue", str(args.queue), "--device", args.device,
           "--log-level", "warning"]
    proc = subprocess.Popen(cmd, cwd=Path(__file__).resolve().parents[2], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    import httpx

    deadline = time.time() + args.start_timeout
    while time.time() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"the server stopped: {proc.stderr.read()[-2000:] if proc.stderr else ''}")
        try:
            if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                return proc, url
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    raise SystemExit(f"the server did not answer /healthz within {args.start_timeout} s")


def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


def run_load(url: str, map_name: str, photos: list, clients: int, seconds: float, requests: int | None,
             timeout: float) -> dict:
    import httpx

    payloads = [(p.name, p.read_bytes(), " ".join(repr(float(v)) for v in k)) for p, k in photos]
    latencies: list[float] = []
    busy: list[float] = []  # how long a 503 took to come back
    statuses: Counter[str] = Counter()
    lock = threading.Lock()
    sent = [0]
    stop = time.perf_counter() + seconds

    def client(index: int) -> None:
        with httpx.Client(base_url=url, timeout=timeout) as http:
            i = index
            while True:
                with lock:
                    if (requests is not None and sent[0] >= requests) or (requests is None and
                                                                           time.perf_counter() >= stop):
                        return
                    sent[0] += 1
                name, data, intrinsics = payloads[i % len(payloads)]
                i += clients
                t0 = time.perf_counter()
                try:
                    r = http.post(f"/v1/maps/{map_name}/localize", files={"photo": (name, data, "image/jpeg")},
                                  data={"intrinsics": intrinsics})
                    status = str(r.status_code)
                except httpx.HTTPError as e:
                    status = type(e).__name__
                dt = time.perf_counter() - t0
                if status == "503":  # the server asks to come back later: as a well-behaved client does
                    retry = r.headers.get("retry-after", "1")
                    time.sleep(min(float(retry) if retry.isdigit() else 1.0, 5.0))
                with lock:
                    statuses[status] += 1
                    if status == "200":
                        latencies.append(dt)
                    elif status == "503":
                        busy.append(dt)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    ok = statuses.get("200", 0)
    return {"clients": clients, "requests": sum(statuses.values()), "answered": ok, "wall_s": round(wall, 3),
            "throughput_per_s": round(ok / wall, 3) if wall else None,
            "latency_s": {f"p{q}": None if percentile(latencies, q) is None else round(percentile(latencies, q), 4)
                          for q in (50, 95, 99)},
            "busy_latency_s": {f"p{q}": None if percentile(busy, q) is None else round(percentile(busy, q), 4)
                               for q in (50, 99)},
            "statuses": dict(sorted(statuses.items())),
            "errors": sum(n for s, n in statuses.items() if s != "200")}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene-dir", type=Path, required=True, help="a scene's data folder (map/map.pt, prepared/)")
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4], help="concurrent clients, one run each")
    ap.add_argument("--seconds", type=float, default=30.0, help="each run's length")
    ap.add_argument("--requests", type=int, help="each run's requests instead of --seconds")
    ap.add_argument("--workers", type=int, default=1, help="the server's --workers")
    ap.add_argument("--queue", type=int, default=8, help="the server's --queue")
    ap.add_argument("--threads", type=int, default=max(1, len(os.sched_getaffinity(0))),
                    help="the server's --threads (divided among its workers)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--url", help="a running server instead (its map named as the scene folder; no memory figures)")
    ap.add_argument("--timeout", type=float, default=120.0, help="a client's time limit per request")
    ap.add_argument("--start-timeout", type=float, default=120.0)
    ap.add_argument("--photos", type=int, help="only the first N query photos")


def run(args: argparse.Namespace) -> None:
    scene = scene_of(args.scene_dir)
    photos = query_files(args.scene_dir)[:args.photos]
    proc, url = (None, args.url) if args.url else start_server(args, scene, ScenePaths.of_scene_dir(args.scene_dir).map_file)
    runs = []
    try:
        run_load(url, scene, photos[:1], 1, 0, 1, args.timeout)  # warm-up: one request
        start = memory_kb(proc.pid) if proc else {}
        for clients in args.clients:
            row = run_load(url, scene, photos, clients, args.seconds, args.requests, args.timeout)
            if proc:
                row["server_memory_kb"] = memory_kb(proc.pid)
            runs.append(row)
            print(json.dumps(row), flush=True)
        end = memory_kb(proc.pid) if proc else {}
    finally:
        if proc:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
    result = {"scene": scene, "photos": len(photos), "workers": args.workers, "queue": args.queue,
              "threads": args.threads, "device": args.device, "runs": runs,
              "server_rss_kb": {"after_warmup": start.get("VmRSS"), "end": end.get("VmRSS"),
                                "peak": end.get("VmHWM")}}
    clients = "-".join(str(c) for c in args.clients)
    path = write_report(report_name(args, scene, f"c{clients}", f"w{args.workers}"), result)
    print(f"wrote {path}")
