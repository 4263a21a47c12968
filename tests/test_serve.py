"""`usvc serve` (usvc/serve/): the answer is `usvc localize`'s record bit for bit; the maps,
health and metrics endpoints; every bad request is one JSON error with its status and the next
good request is answered; the token; backpressure (503 + Retry-After) and the time limit (504).

The map is tiny and untrained; where a pose matters the network is replaced by the exact scene
coordinates of a known camera (as in tests/test_relocalizer.py and test_localize_bad_input.py).
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import struct
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from PIL import Image
from test_localize_bad_input import CENTRED, exactly, photo_file, tiny_map  # noqa: F401 (fixtures)
from test_relocalizer import photo

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from usvc.cli import main  # noqa: E402
from usvc.core.errors import UsvcError  # noqa: E402
from usvc.relocalize.relocalizer import Relocalizer  # noqa: E402
from usvc.serve import MapRegistry, ServeOptions  # noqa: E402
from usvc.serve.app import create_app  # noqa: E402

pytestmark = [pytest.mark.precision, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

URL = "/v1/maps/tiny/localize"
TOKEN = "s3cret-token"


def app_with(tiny_map: tuple[Path, Path], **options: Any) -> tuple[Any, Relocalizer]:
    registry = MapRegistry()
    reloc = Relocalizer(*tiny_map)
    registry.add("tiny", reloc)
    return create_app(registry, ServeOptions(**options)), reloc


@pytest.fixture(scope="module")
def served(tiny_map: tuple[Path, Path]) -> Any:
    app, reloc = app_with(tiny_map, max_bytes=200_000, max_megapixels=1.0)
    with TestClient(app, raise_server_exceptions=False) as client:
        yield client, reloc


@pytest.fixture
def client(served: Any, monkeypatch: pytest.MonkeyPatch) -> TestClient:
    exactly(monkeypatch, CENTRED)  # poses are found: the network sees CENTRED's exact coordinates
    return served[0]


def png_bytes(width: int = 160, height: int = 120) -> bytes:
    ok, buf = cv2.imencode(".png", photo(width, height))
    assert ok
    return buf.tobytes()


def jpeg_bytes() -> bytes:
    ok, buf = cv2.imencode(".jpg", photo(160, 120))
    assert ok
    return buf.tobytes()


def png_header(width: int, height: int) -> bytes:
    """A PNG whose header claims width x height (its pixels are never there)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def post_photo(client: TestClient, data: bytes, filename: str = "photo.png", **fields: Any) -> Any:
    return client.post(URL, files={"photo": (filename, data, "image/png")},
                       data={k: str(v) for k, v in fields.items()})


def without_timing(record: dict) -> dict:
    return {k: v for k, v in record.items() if k != "seconds"}


def good(client: TestClient) -> dict:
    """The next good request is answered with a pose."""
    r = post_photo(client, png_bytes(), focal=130)
    assert r.status_code == 200, r.text
    record = r.json()
    assert record["success"] and record["intrinsics_source"] == "focal"
    return record


def cli_record(tiny_map: tuple[Path, Path], capsys: pytest.CaptureFixture[str], *args: str) -> dict:
    rc = main(["localize", "--map", str(tiny_map[0]), "--encoder-weights", str(tiny_map[1]), *args])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out.strip())


# ------------------------------------------------------------------ the answer

def test_the_answer_is_the_commands_record(client: TestClient, served: Any, tiny_map: tuple[Path, Path],
                                           photo_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Multipart, JSON with base64 and a bare image body: each the record `usvc localize` writes for
    the same file (but its name and timings), and `Relocalizer.localize`'s answer on it."""
    data = photo_file.read_bytes()
    expected = cli_record(tiny_map, capsys, "--focal", "130", str(photo_file))
    assert expected["success"]
    answers = [
        post_photo(client, data, "photo.png", focal=130),
        client.post(URL, json={"photo": base64.b64encode(data).decode(), "focal": 130, "name": "photo.png"}),
        client.post(URL + "?focal=130&name=photo.png", content=data, headers={"content-type": "image/png"}),
    ]
    reloc: Relocalizer = served[1]
    direct = reloc.localize(photo_file, CENTRED.__class__("SIMPLE_PINHOLE", 160, 120, (130.0, 80.0, 60.0)))
    for r in answers:
        assert r.status_code == 200, r.text
        assert r.headers["content-type"].startswith("application/json")
        record = r.json()
        assert record["name"] == "photo.png"
        assert list(record) == list(expected)  # the same fields in the same order
        assert without_timing(record) == {**without_timing(expected), "name": "photo.png"}
        assert without_timing({k: v for k, v in record.items() if k not in ("name", "intrinsics_source")}) == \
            without_timing(direct.to_json())
        assert set(record["seconds"]) == set(expected["seconds"])
    # every intrinsics form the command takes, and none (estimated with the pose)
    for fields, source, flags in [({"intrinsics": "130 130 80 60"}, "intrinsics", ["--intrinsics", "130", "130", "80", "60"]),
                                  ({"camera": "PINHOLE 130 130 80 60"}, "camera", ["--camera", "PINHOLE", "130", "130", "80", "60"]),
                                  ({}, "estimated", [])]:
        record = post_photo(client, data, **fields).json()
        assert record["intrinsics_source"] == source and record["success"]
        assert without_timing(record) == {**without_timing(cli_record(tiny_map, capsys, *flags, str(photo_file))),
                                          "name": "photo.png"}
    # a refused pose: 422, its reason, and the record the command writes for it
    r = post_photo(client, data, focal=1e9)
    assert r.status_code == 422
    refused = cli_record(tiny_map, capsys, "--focal", "1e9", str(photo_file))
    assert not refused["success"] and r.json()["error"] == refused["rejected"]
    assert without_timing(r.json()["record"]) == {**without_timing(refused), "name": "photo.png"}
    record = client.post(URL, json={"photo": base64.b64encode(data).decode(),
                                    "camera": {"model": "PINHOLE", "params": [130, 130, 80, 60]}}).json()
    assert record["success"] and record["name"] == "photo" and record["intrinsics_source"] == "camera"


def test_a_jpeg_with_exif_orientation_is_read_as_the_command_reads_it(client: TestClient, tmp_path: Path,
                                                                      tiny_map: tuple[Path, Path],
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Stored 120x160 with orientation 6: shown (and localized) 160x120, as the command does."""
    img = Image.fromarray(np.ascontiguousarray(np.rot90(photo(160, 120)[..., ::-1], 1)))
    exif = Image.Exif()
    exif[0x0112] = 6
    path = tmp_path / "turned.jpg"
    img.save(path, exif=exif, quality=95)
    r = post_photo(client, path.read_bytes(), "turned.jpg", focal=130)
    assert r.status_code == 200, r.text
    assert r.json()["camera"]["width"] == 160
    assert without_timing(r.json()) == {**without_timing(cli_record(tiny_map, capsys, "--focal", "130", str(path))),
                                        "name": "turned.jpg"}


def test_maps_health_metrics_and_page(client: TestClient) -> None:
    maps = client.get("/v1/maps").json()["maps"]
    assert [m["name"] for m in maps] == ["tiny"]
    info = maps[0]
    assert info["size_bytes"] > 0 and info["made"] and info["short_side"] == 120 and info["device"] == "cpu"
    assert set(info) >= {"name", "photos", "size_bytes", "encoder", "made"}
    health = client.get("/healthz").json()
    assert health["status"] == "ok" and health["maps"] == ["tiny"]
    good(client)
    client.post("/v1/maps/nowhere/localize", content=b"x")
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain; version=0.0.4")
    text = r.text
    assert 'usvc_serve_requests_total{endpoint="/v1/maps/{name}/localize",status="200"}' in text
    assert 'usvc_serve_failures_total{reason="unknown_map"}' in text
    assert 'usvc_serve_localize_seconds_bucket{le="+Inf"}' in text and "usvc_serve_localize_seconds_count" in text
    assert "usvc_serve_queue_depth 0" in text and "usvc_serve_maps 1" in text
    page = client.get("/")
    assert page.status_code == 200 and "drop a photo" in page.text.lower()
    assert client.get("/docs").status_code == 200
    spec = client.get("/openapi.json").json()
    body = spec["paths"]["/v1/maps/{name}/localize"]["post"]["requestBody"]["content"]
    assert set(body) == {"multipart/form-data", "application/json", "image/*"}


# ------------------------------------------------------------------ bad requests

def multipart(data: bytes, **fields: Any) -> dict[str, Any]:
    return {"files": {"photo": ("p.png", data, "image/png")}, "data": {k: str(v) for k, v in fields.items()}}


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def bad_requests() -> list[tuple[str, str, dict[str, Any], int, str]]:
    """(kind, method, request, status, reason)"""
    png, jpg = png_bytes(), jpeg_bytes()
    ico = io.BytesIO()
    Image.fromarray(photo(32, 32)).save(ico, format="ICO")
    return [
        ("empty multipart photo", "post", multipart(b""), 400, "bad_photo"),
        ("empty JSON body", "post", {"content": b"", "headers": {"content-type": "application/json"}}, 400, "bad_json"),
        ("empty image body", "post", {"content": b"", "headers": {"content-type": "image/jpeg"}}, 400, "bad_photo"),
        ("not an image", "post", multipart(b"hello, this is text, not a photo"), 400, "bad_photo"),
        ("truncated JPEG", "post", multipart(jpg[: len(jpg) // 2], focal=130), 400, "bad_photo"),
        ("400 MP PNG header", "post", multipart(png_header(20000, 20000)), 413, "too_many_pixels"),
        ("over the megapixel limit", "post", multipart(png_header(1500, 1000)), 413, "too_many_pixels"),
        ("an ICO file", "post", multipart(ico.getvalue()), 400, "bad_photo"),
        ("too small to localize", "post", multipart(png_bytes(16, 16)), 400, "bad_photo"),
        ("a strip, not a view", "post", multipart(png_bytes(400, 40)), 400, "bad_photo"),
        ("wrong content type", "post", {"content": b"abc", "headers": {"content-type": "text/plain"}}, 415,
         "unsupported_media_type"),
        ("no content type", "post", {"content": b"abc"}, 415, "unsupported_media_type"),
        ("negative focal", "post", multipart(png, focal=-130), 400, "bad_intrinsics"),
        ("zero focal", "post", {"json": {"photo": b64(png), "focal": 0}}, 400, "bad_intrinsics"),
        ("NaN focal", "post", {"content": b'{"photo": "%s", "focal": NaN}' % b64(png).encode(),
                               "headers": {"content-type": "application/json"}}, 400, "bad_intrinsics"),
        ("focal as a word", "post", multipart(png, focal="wide"), 400, "bad_intrinsics"),
        ("focal as a bool", "post", {"json": {"photo": b64(png), "focal": True}}, 400, "bad_intrinsics"),
        ("three intrinsics", "post", {"json": {"photo": b64(png), "intrinsics": [130, 130, 80]}}, 400,
         "bad_intrinsics"),
        ("principal point outside", "post", multipart(png, intrinsics="130 130 800 60"), 400, "bad_intrinsics"),
        ("negative intrinsics", "post", {"json": {"photo": b64(png), "intrinsics": [-130, 130, 80, 60]}}, 400,
         "bad_intrinsics"),
        ("unknown camera model", "post", multipart(png, camera="FISHEYE_9000 1 2 3"), 400, "bad_intrinsics"),
        ("camera with wrong count", "post", {"json": {"photo": b64(png), "camera": {"model": "OPENCV",
                                                                                    "params": [1, 2]}}}, 400,
         "bad_intrinsics"),
        ("focal and intrinsics", "post", multipart(png, focal=130, intrinsics="130 130 80 60"), 400, "bad_intrinsics"),
        ("absurd focal", "post", multipart(png, focal=1e9), 422, "pose_refused"),
        ("unknown map", "post-other", {"url": "/v1/maps/bird/localize", **multipart(png)}, 404, "unknown_map"),
        ("a path for a map", "post-other", {"url": "/v1/maps/..%2F..%2Fetc%2Fpasswd/localize", **multipart(png)},
         404, "not_found"),
        ("a file name for a map", "post-other", {"url": "/v1/maps/map.pt/localize", **multipart(png)}, 404,
         "unknown_map"),
        ("JSON list", "post", {"json": [1, 2, 3]}, 400, "bad_json"),
        ("JSON syntax", "post", {"content": b'{"photo": ', "headers": {"content-type": "application/json"}}, 400,
         "bad_json"),
        ("JSON photo not base64", "post", {"json": {"photo": "%%% not base64 %%%"}}, 400, "bad_request"),
        ("JSON photo a number", "post", {"json": {"photo": 12345}}, 400, "bad_request"),
        ("JSON without photo", "post", {"json": {"focal": 130}}, 400, "bad_request"),
        ("unknown field", "post", {"json": {"photo": b64(png), "path": "/etc/passwd"}}, 400, "bad_request"),
        ("name with control characters", "post", {"json": {"photo": b64(png), "name": "a\nb"}}, 400, "bad_request"),
        ("multipart without photo", "post", {"data": {"focal": "130"}, "files": {"other": ("x", b"y")}}, 400,
         "bad_request"),
        ("over the byte limit", "post", multipart(b"\0" * 300_000), 413, "too_large"),
        ("no such endpoint", "get-other", {"url": "/v1/nothing"}, 404, "not_found"),
        ("GET on localize", "get-other", {"url": URL}, 405, "method_not_allowed"),
    ]


BAD = bad_requests()


@pytest.mark.parametrize("kind,method,request_,status,reason", BAD, ids=[b[0] for b in BAD])
def test_a_bad_request_is_one_json_error_and_the_next_is_answered(client: TestClient, kind: str, method: str,
                                                                  request_: dict[str, Any], status: int,
                                                                  reason: str) -> None:
    request_ = dict(request_)
    url = request_.pop("url", URL)
    r = client.get(url) if method.startswith("get") else client.post(url, **request_)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json")
    body = r.json()
    assert body["reason"] == reason and body["status"] == status
    assert isinstance(body["error"], str) and body["error"] and "\n" not in body["error"]
    assert "Traceback" not in r.text and "usvc-serve-" not in r.text  # no trace, no server-side path
    if status == 422:  # a refused pose: its reason, and the record the command writes
        assert body["record"]["success"] is False and body["record"]["rejected"] == body["error"]
    good(client)


def test_at_least_twenty_kinds_of_bad_request() -> None:
    assert len(BAD) >= 20


def test_a_stalled_upload_gets_408_and_holds_no_worker(tiny_map: tuple[Path, Path],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A client that sends part of its body and then nothing: 408 after body_timeout_s."""
    app, _ = app_with(tiny_map, body_timeout_s=0.3)
    sent: list[dict] = []

    async def call() -> None:
        chunks = [{"type": "http.request", "body": b"\x89PNG\r\n", "more_body": True}]

        async def receive() -> dict:
            if chunks:
                return chunks.pop()
            await asyncio.sleep(3600)  # never finishes its upload
            return {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            sent.append(message)

        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
                 "scheme": "http", "path": URL, "raw_path": URL.encode(), "query_string": b"", "root_path": "",
                 "headers": [(b"content-type", b"image/png"), (b"content-length", b"100000"), (b"host", b"test")],
                 "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80)}
        await asyncio.wait_for(app(scope, receive, send), 10)

    t0 = time.perf_counter()
    asyncio.run(call())
    assert time.perf_counter() - t0 < 5
    assert sent[0]["status"] == 408
    body = json.loads(b"".join(m.get("body", b"") for m in sent[1:]))
    assert body["reason"] == "body_timeout"
    exactly(monkeypatch, CENTRED)
    with TestClient(app) as client:
        good(client)
        assert client.get("/healthz").json()["waiting"] == 0


# ------------------------------------------------------------------ token

def test_the_token_is_required_when_configured(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    exactly(monkeypatch, CENTRED)
    app, _ = app_with(tiny_map, token=TOKEN)
    with TestClient(app) as client:
        for headers in ({}, {"authorization": "Bearer wrong"}, {"authorization": f"Basic {TOKEN}"}):
            for r in (client.get("/v1/maps", headers=headers), client.get("/metrics", headers=headers),
                      client.post(URL, headers=headers, **multipart(png_bytes(), focal=130))):
                assert r.status_code == 401 and r.json()["reason"] == "unauthorized"
                assert r.headers["www-authenticate"].startswith("Bearer")
        auth = {"authorization": f"Bearer {TOKEN}"}
        assert client.get("/v1/maps", headers=auth).status_code == 200
        assert client.get("/metrics", headers=auth).status_code == 200
        r = client.post(URL, headers=auth, **multipart(png_bytes(), focal=130))
        assert r.status_code == 200 and r.json()["success"]
        assert client.get("/healthz").status_code == 200  # liveness needs no token
    with pytest.raises(UsvcError, match="token"):
        create_app(MapRegistry(), ServeOptions(token="two words"))


# ------------------------------------------------------------------ backpressure and time limit

def slow_localize(reloc: Relocalizer, release: threading.Event, started: threading.Event,
                  monkeypatch: pytest.MonkeyPatch) -> None:
    real = reloc.localize

    def slow(*args: Any, **kwargs: Any) -> Any:
        started.set()
        release.wait(10)
        return real(*args, **kwargs)

    monkeypatch.setattr(reloc, "localize", slow)


def test_a_full_queue_is_503_with_retry_after(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    exactly(monkeypatch, CENTRED)
    app, reloc = app_with(tiny_map, threads=1, queue=0, retry_after_s=2)
    release, started = threading.Event(), threading.Event()
    slow_localize(reloc, release, started, monkeypatch)
    with TestClient(app) as client:
        first: list[Any] = []
        held = threading.Thread(target=lambda: first.append(post_photo(client, png_bytes(), focal=130)))
        held.start()
        assert started.wait(10)
        r = post_photo(client, png_bytes(), focal=130)
        assert r.status_code == 503 and r.headers["retry-after"] == "2" and r.json()["reason"] == "busy"
        assert "usvc_serve_running 1" in client.get("/metrics").text
        release.set()
        held.join(10)
        assert first[0].status_code == 200 and first[0].json()["success"]
        good(client)


def test_a_request_over_its_time_limit_is_504(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    exactly(monkeypatch, CENTRED)
    app, reloc = app_with(tiny_map, threads=1, queue=1, timeout_s=0.3)
    release, started = threading.Event(), threading.Event()
    slow_localize(reloc, release, started, monkeypatch)
    with TestClient(app) as client:
        r = post_photo(client, png_bytes(), focal=130)
        assert r.status_code == 504 and r.json()["reason"] == "timeout"
        assert "usvc_serve_abandoned 1" in client.get("/metrics").text  # still running, unseen
        release.set()
        for _ in range(100):
            if client.get("/healthz").json()["running"] == 0:
                break
            time.sleep(0.05)
        assert client.get("/healthz").json() == {"status": "ok", "maps": ["tiny"], "waiting": 0, "running": 0,
                                                      "abandoned": 0, "capacity": 2}
        good(client)


# ------------------------------------------------------------------ usvc.client

def test_the_client(client: TestClient, photo_file: Path, tiny_map: tuple[Path, Path],
                    capsys: pytest.CaptureFixture[str]) -> None:
    from usvc.client import Client, ServeError

    c = Client(http=client)
    assert c.health()["status"] == "ok" and [m["name"] for m in c.maps()] == ["tiny"]
    record = c.localize("tiny", photo_file, focal=130)
    assert without_timing(record) == {**without_timing(cli_record(tiny_map, capsys, "--focal", "130",
                                                                  str(photo_file))), "name": "photo.png"}
    assert c.localize("tiny", photo_file.read_bytes(), intrinsics=(130, 130, 80, 60))["intrinsics_source"] == \
        "intrinsics"
    with pytest.raises(ServeError) as err:
        c.localize("tiny", photo_file, focal=1e9)
    assert err.value.status == 422 and err.value.reason == "pose_refused" and err.value.record["success"] is False
    with pytest.raises(ServeError) as err:
        c.localize("bird", photo_file)
    assert err.value.status == 404 and err.value.reason == "unknown_map"
    with pytest.raises(ServeError) as err:
        c.localize("../tiny", photo_file)  # quoted: no route, no file
    assert err.value.status == 404
