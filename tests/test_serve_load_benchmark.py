"""`python -m benchmarks.query serve-load`'s parts: the load against a real server counts every
answer and the memory samples after the first answers; the memory of a process tree is summed
over its processes; photos resized for --size carry their intrinsics scaled; percentiles."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_localize_bad_input import tiny_map  # noqa: F401 (fixture)
from test_relocalizer import photo
from test_serve_page import server  # noqa: F401 (fixture: a real uvicorn server with the map "room")

from benchmarks.query.serve_load import memory_kb, percentile, resized, run_load

pytestmark = [pytest.mark.precision, pytest.mark.filterwarnings("ignore::DeprecationWarning")]


@pytest.fixture
def photos(tmp_path: Path) -> list:
    path = tmp_path / "a photo.png"
    cv2.imwrite(str(path), cv2.cvtColor(photo(160, 120), cv2.COLOR_RGB2BGR))
    return [(path, (130.0, 130.0, 80.0, 60.0))]


def test_the_load_counts_every_answer(server: str, photos: list) -> None:  # noqa: F811
    import os

    row = run_load(server.rstrip("/"), "room", photos, clients=3, seconds=0, requests=12, timeout=60,
                   server_pid=os.getpid(), memory_after=0)
    assert row["requests"] == 12 and row["answered"] + row["errors"] == 12
    assert row["statuses"] == {"200": 12}, row
    assert row["throughput_per_s"] > 0 and row["latency_s"]["p50"] <= row["latency_s"]["p99"]
    rss = row["rss_kb"]
    if rss["after_first_0"] is not None:  # sampled every 0.5 s: a fast run may end first
        assert rss["peak_sampled"] >= rss["after_first_0"] > 0
    missing = run_load(server.rstrip("/"), "no-such-map", photos, 1, 0, 2, 60)
    assert missing["statuses"] == {"404": 2} and missing["errors"] == 2 and "rss_kb" not in missing


def test_memory_is_summed_over_the_process_tree() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; x = bytearray(60_000_000); print('ready', "
                              "flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        import os

        assert child.stdout is not None and child.stdout.readline().strip() == "ready"  # its memory is taken
        alone, tree = memory_kb(child.pid), memory_kb(os.getpid())
        assert alone["processes"] == 1 and alone["VmRSS"] > 50_000
        assert tree["processes"] >= 2 and tree["VmRSS"] > alone["VmRSS"]
    finally:
        child.kill()
        child.wait()
    assert memory_kb(child.pid) == {"VmRSS": 0, "VmHWM": 0, "processes": 0}


def test_resized_photos_carry_scaled_intrinsics(photos: list) -> None:
    (payload, none), = resized(photos, "320x240")
    name, data, intrinsics = payload
    assert none is None and name == "a photo.jpg"
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (240, 320, 3)
    assert [float(v) for v in intrinsics.split()] == [260.0, 260.0, 160.0, 120.0]


def test_percentile() -> None:
    assert percentile([], 50) is None
    assert percentile([3.0, 1.0, 2.0], 50) == 2.0
    assert percentile([float(i) for i in range(101)], 99) == 99.0
