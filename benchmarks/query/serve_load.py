"""Load on `usvc serve` over loopback: N concurrent clients send real query photos (a 503 waits its Retry-After) (multipart, each
with its intrinsics from the scene, as an app that knows its camera would) for --seconds or
--requests; reports throughput, p50/p95/p99 latency (and p50/p99 of the 503s), answers by status, and the server's peak
memory (the server's and its worker processes' resident memory summed: after the warm-up, after
the first --memory-after requests of a run, its largest sample during the run (every 0.5 s), and at
the end: flat memory over a long run). The server is started here (`usvc serve` on a free port,
--workers/--queue/--threads/--processes as given) unless --url names a running one. Writes
results/benchmarks/query_serve_load_<scene>_c<clients>_w<workers>[p].json (p: worker processes).
Run (nothing else heavy running):
python -m benchmarks.query serve-load --scene-dir data/office --clients 1 8 --workers 1 --requests 80
python -m benchmarks.query serve-load --scene-dir data/office --clients 1 8 --workers 2 --processes --requests 80
python -m benchmarks.query serve-load --scene-dir data/office --clients 8 --workers 2 --processes --requests 10000
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


def resized(photos: list[tuple[Path, tuple[float, float, float, float]]], size: str) -> list:
    """Each photo as a JPEG (quality 95) of WxH pixels, its intrinsics scaled with it: (payload, None)."""
    import cv2

    w, h = (int(v) for v in size.lower().split("x"))
    out = []
    for path, (fx, fy, cx, cy) in photos:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        sx, sy = w / img.shape[1], h / img.shape[0]
        ok, buf = cv2.imencode(".jpg", cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA),
                               [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert ok
        intrinsics = " ".join(repr(float(v)) for v in (fx * sx, fy * sy, cx * sx, cy * sy))
        out.append(((path.stem + ".jpg", buf.tobytes(), intrinsics), None))
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _process_tree(pid: int) -> list[int]:
    """pid and its descendants (Linux: /proc/<pid>/task/<tid>/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def memory_kb(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM (each process's own peak) of a process and its children, summed, kB (Linux)."""
    out = {"VmRSS": 0, "VmHWM": 0, "processes": 0}
    for p in _process_tree(pid):
        try:
            lines = Path(f"/proc/{p}/status").read_text().splitlines()
        except OSError:
            continue
        out["processes"] += 1
        for line in lines:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] += int(value.split()[0])
    return out


def start_server(args: argparse.Namespace, scene: str, map_file: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    cmd = [sys.executable, "-m", "usvc.cli", "--threads", str(args.threads), "serve", "--map", f"{scene}={map_file}",
           "--port", str(port), "--workers", str(args.workers), "--queue", str(args.queue), "--device", args.device,
           "--log-level", "warning", "--batch", str(args.batch)] + (["--processes"] if args.processes else [])
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
             timeout: float, server_pid: int | None = None, memory_after: int = 100) -> dict:
    import httpx

    payloads = [(p.name, p.read_bytes(), " ".join(repr(float(v)) for v in k)) if isinstance(p, Path) else p
                for p, k in photos]
    latencies: list[float] = []
    busy: list[float] = []  # how long a 503 took to come back
    statuses: Counter[str] = Counter()
    lock = threading.Lock()
    sent = [0]
    stop = time.perf_counter() + seconds
    memory: dict[str, int | None] = {"after_first": None, "peak_sampled": None}
    done = threading.Event()

    def sample() -> None:  # the resident memory summed over the server's processes, after the first requests
        while not done.wait(0.5):
            with lock:
                answered = sum(statuses.values())
            if answered < memory_after:
                continue
            rss = memory_kb(server_pid)["VmRSS"]  # type: ignore[arg-type]
            if memory["after_first"] is None:
                memory["after_first"] = rss
            memory["peak_sampled"] = max(memory["peak_sampled"] or 0, rss)

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
    sampler = threading.Thread(target=sample) if server_pid else None
    for t in threads + ([sampler] if sampler else []):
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    done.set()
    if sampler:
        sampler.join()
    ok = statuses.get("200", 0)
    return {"clients": clients, "requests": sum(statuses.values()), "answered": ok, "wall_s": round(wall, 3),
            "throughput_per_s": round(ok / wall, 3) if wall else None,
            "latency_s": {f"p{q}": None if percentile(latencies, q) is None else round(percentile(latencies, q), 4)
                          for q in (50, 95, 99)},
            "busy_latency_s": {f"p{q}": None if percentile(busy, q) is None else round(percentile(busy, q), 4)
                               for q in (50, 99)},
            "statuses": dict(sorted(statuses.items())),
            "errors": sum(n for s, n in statuses.items() if s != "200"),
            **({"rss_kb": {f"after_first_{memory_after}": memory["after_first"], "peak_sampled": memory["peak_sampled"]},
                "rss_peak_over_after_first": None if not memory["after_first"] else
                round(memory["peak_sampled"] / memory["after_first"], 4)} if server_pid else {})}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene-dir", type=Path, required=True, help="a scene's data folder (map/map.pt, prepared/)")
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4], help="concurrent clients, one run each")
    ap.add_argument("--seconds", type=float, default=30.0, help="each run's length")
    ap.add_argument("--requests", type=int, help="each run's requests instead of --seconds")
    ap.add_argument("--workers", type=int, default=1, help="the server's --workers")
    ap.add_argument("--processes", action="store_true", help="the server's --processes (worker processes)")
    ap.add_argument("--batch", type=int, default=1, help="the server's --batch (the network batched across photos)")
    ap.add_argument("--memory-after", type=int, default=100,
                    help="the run's memory is sampled from this many answered requests on (default 100)")
    ap.add_argument("--queue", type=int, default=8, help="the server's --queue")
    ap.add_argument("--threads", type=int, default=max(1, len(os.sched_getaffinity(0))),
                    help="the server's --threads (divided among its workers)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--url", help="a running server instead (its map named as the scene folder; no memory figures)")
    ap.add_argument("--timeout", type=float, default=120.0, help="a client's time limit per request")
    ap.add_argument("--start-timeout", type=float, default=120.0)
    ap.add_argument("--photos", type=int, help="only the first N query photos")
    ap.add_argument("--size", help="send each photo resized to WxH (JPEG, intrinsics scaled), e.g. 640x480")


def run(args: argparse.Namespace) -> None:
    scene = scene_of(args.scene_dir)
    photos = query_files(args.scene_dir)[:args.photos]
    if args.size:
        photos = resized(photos, args.size)
    proc, url = (None, args.url) if args.url else start_server(args, scene, ScenePaths.of_scene_dir(args.scene_dir).map_file)
    runs = []
    try:
        run_load(url, scene, photos[:1], 1, 0, 1, args.timeout)  # warm-up: one request
        start = memory_kb(proc.pid) if proc else {}
        for clients in args.clients:
            row = run_load(url, scene, photos, clients, args.seconds, args.requests, args.timeout,
                           proc.pid if proc else None, args.memory_after)
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
    result = {"scene": scene, "photos": len(photos), "size": args.size, "workers": args.workers,
              "processes": args.processes, "batch": args.batch,
              "queue": args.queue,
              "threads": args.threads, "device": args.device, "runs": runs,
              "server_rss_kb": {"after_warmup": start.get("VmRSS"), "end": end.get("VmRSS"),
                                "peak": end.get("VmHWM"), "processes": end.get("processes")}}
    clients = "-".join(str(c) for c in args.clients)
    path = write_report(report_name(args, scene, f"c{clients}", f"w{args.workers}{'p' if args.processes else ''}",
                                     args.size, f"b{args.batch}" if args.batch > 1 else None), result)
    print(f"wrote {path}")
