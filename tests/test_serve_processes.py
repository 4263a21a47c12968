"""`usvc serve --processes`: photos localized in worker processes answer what the server's own
process answers (bit for bit, the same threads), refusals come back with their status and
reason, a photo over the time limit ends its process (504) and a new one takes the next request,
and the processes end with the server.

The relocalizer classes below are made again in each spawned process (sent by name): the exact
one sees the exact scene coordinates of a known camera (as `exactly` does in-process), the slow
one takes 30 s a photo.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_localize_bad_input import CENTRED, photo_file, tiny_map  # noqa: F401 (fixtures)
from test_relocalizer import exact_coordinates
from test_serve import URL, jpeg_bytes, png_bytes, post_photo, without_timing

pytest.importorskip("fastapi")

from fastapi.testclient import TestClient  # noqa: E402

from usvc.relocalize.photo_batch import query_threads  # noqa: E402
from usvc.relocalize.relocalizer import Relocalizer  # noqa: E402
from usvc.serve import MapRegistry, ServeOptions  # noqa: E402
from usvc.serve.app import create_app  # noqa: E402
from usvc.serve.intrinsics import PhotoIntrinsics  # noqa: E402
from usvc.serve.photo import localize_photo  # noqa: E402

pytestmark = [pytest.mark.precision, pytest.mark.filterwarnings("ignore::DeprecationWarning")]


class ExactRelocalizer(Relocalizer):
    """The network replaced by the exact coordinates CENTRED (at 160x120) sees."""

    def scene_coordinates(self, g: Any) -> np.ndarray:
        return exact_coordinates(-(-g.shape[0] // 8), -(-g.shape[1] // 8), CENTRED)


class SlowRelocalizer(Relocalizer):
    def localize(self, *args: Any, **kwargs: Any) -> Any:
        time.sleep(30)
        return super().localize(*args, **kwargs)


def served_in_processes(reloc: Relocalizer, **options: Any) -> Any:
    registry = MapRegistry()
    registry.add("tiny", reloc)
    return create_app(registry, ServeOptions(processes=True, **options))


def test_processes_answer_as_the_servers_own_process(tiny_map: tuple[Path, Path], tmp_path: Path) -> None:
    reloc = ExactRelocalizer(*tiny_map)
    data = png_bytes()
    with query_threads(1):  # a worker process's threads
        expected = localize_photo(reloc, data, ".png", PhotoIntrinsics(focal=130.0), "photo.png", tmp_path)
    assert expected["success"]
    app = served_in_processes(reloc, threads=2, process_threads=1, queue=2)
    with TestClient(app) as client:
        assert len(app.state.processes.maps) == 1
        for _ in range(3):  # both processes answer, and each the same
            r = post_photo(client, data, focal=130)
            assert r.status_code == 200, r.text
            assert without_timing(r.json()) == without_timing(expected)
        # a refused pose comes back as the server's own process refuses it: 422 with its record
        with query_threads(1):
            refused = localize_photo(reloc, data, ".png", PhotoIntrinsics(focal=1e9), "photo.png", tmp_path)
        r = post_photo(client, data, focal=1e9)
        assert r.status_code == 422 and r.json()["reason"] == "pose_refused" and not refused["success"]
        assert r.json()["error"] == refused["rejected"]
        assert without_timing(r.json()["record"]) == without_timing(refused)
        # a photo the worker cannot decode: 400, one line, and the next photo answered
        jpg = jpeg_bytes()
        r = client.post(URL, files={"photo": ("cut.jpg", jpg[: len(jpg) // 2], "image/jpeg")}, data={"focal": "130"})
        assert r.status_code == 400 and r.json()["reason"] == "bad_photo" and "\n" not in r.json()["error"]
        assert post_photo(client, data, focal=130).json()["success"]
        processes = list(app.state.processes._all)
    assert all(not w.process.is_alive() for w in processes)  # ended with the server


def test_a_photo_over_the_time_limit_ends_its_process(tiny_map: tuple[Path, Path]) -> None:
    app = served_in_processes(SlowRelocalizer(*tiny_map), threads=1, queue=1, timeout_s=1.0)
    with TestClient(app) as client:
        before = app.state.processes._all[0].process.pid
        t0 = time.perf_counter()
        r = post_photo(client, png_bytes(), focal=130)
        assert r.status_code == 504 and r.json()["reason"] == "timeout"
        for _ in range(200):  # the slot frees once a new process has loaded the map, not after 30 s
            if client.get("/healthz").json()["running"] == 0 and app.state.processes._free.qsize() == 1:
                break
            time.sleep(0.05)
        assert time.perf_counter() - t0 < 20
        assert app.state.processes.restarts == 1
        after = app.state.processes._all[0].process.pid
        assert after != before and app.state.processes._all[0].process.is_alive()


def test_a_map_a_process_cannot_load_fails_the_start(tiny_map: tuple[Path, Path], tmp_path: Path) -> None:
    reloc = Relocalizer(*tiny_map)
    gone = tmp_path / "map.pt"
    gone.write_bytes(tiny_map[0].read_bytes())
    moved = Relocalizer(gone, tiny_map[1])
    gone.unlink()  # loaded in the server, gone before the processes start
    registry = MapRegistry()
    registry.add("tiny", reloc)
    registry.add("moved", moved)
    with pytest.raises(RuntimeError, match="could not load the maps"):
        create_app(registry, ServeOptions(processes=True))


def test_the_option_is_checked() -> None:
    with pytest.raises(Exception, match="process_threads"):
        ServeOptions(processes=True, process_threads=0).check()
