"""Several photos localized at a time (`usvc.relocalize.photo_batch`, `Relocalizer.localize_many`,
`usvc localize --workers`, with `--processes` too): the answers in the photos' order, bit for bit
those of the photos one after the other with the same threads per query; each query's side work in place."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_cli import make_map
from test_feature_refinement import synthetic_relocalizer
from test_refinement import CAM, photo, synthetic_query  # noqa: F401

from usvc.core.errors import UsvcError
from usvc.relocalize.photo_batch import check_workers, in_order, query_threads, threads_per_query
from usvc.relocalize.query_cores import Job, inline_jobs

REPO = Path(__file__).resolve().parents[1]


def test_in_order_hands_out_answers_in_order_while_several_run_at_once():
    started, running, most = [], [0], [0]
    lock = threading.Lock()

    def work(i: int) -> tuple[int, str]:
        with lock:
            started.append(i)
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.02 * (5 - i % 5))  # later items finish first
        with lock:
            running[0] -= 1
        return i, threading.current_thread().name

    out = list(in_order(work, range(12), 3))
    assert [i for i, _ in out] == list(range(12))
    assert most[0] == 3  # three at a time, never more
    assert all(name.startswith("usvc-query") for _, name in out)
    here = threading.current_thread().name
    assert [name for _, name in in_order(work, range(3), 1)] == [here] * 3  # one worker: in place


def test_in_order_raises_at_the_failed_items_turn_and_starts_little_ahead():
    seen = []

    def work(i: int) -> int:
        seen.append(i)
        if i == 2:
            raise ValueError("two")
        return i

    got = in_order(work, range(100), 2)
    assert [next(got), next(got)] == [0, 1]
    with pytest.raises(ValueError, match="two"):
        next(got)
    got.close()
    assert max(seen) < 2 + 2 * 2 + 2  # at most 2 x workers ahead of the one handed out


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_a_wrong_worker_count_is_one_clear_error(bad):
    with pytest.raises(UsvcError, match="workers must be a whole number"):
        check_workers(bad)


def test_threads_are_divided_and_restored():
    assert [threads_per_query(16, w) for w in (1, 2, 3, 16, 32)] == [16, 8, 5, 1, 1]
    before = torch.get_num_threads(), cv2.getNumThreads()
    with query_threads(1):
        assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
    assert (torch.get_num_threads(), cv2.getNumThreads()) == before


def test_a_query_among_several_does_its_side_work_in_place():
    torch.set_num_threads(2)
    try:
        assert Job(int, 1).background  # one query: beside it, on the worker thread
        with inline_jobs():
            job = Job(threading.current_thread)
            assert not job.background and job.result() is threading.current_thread()
        assert Job(int, 1).background
    finally:
        torch.set_num_threads(1)


def test_localize_many_gives_the_answers_of_one_photo_after_another(tmp_path: Path, synthetic_query,
                                                                      monkeypatch):
    """Right, doubled (refused) and missing intrinsics, several times over, through two workers."""
    reloc, _ = synthetic_relocalizer(tmp_path, monkeypatch)
    (fx, fy), (cx, cy) = CAM.focal, CAM.principal_point
    queries = [(photo(), (fx, fy, cx, cy)), (photo(), (2 * fx, 2 * fy, cx, cy)), (photo(), None)] * 3
    torch.set_num_threads(1)
    one_by_one = [reloc.localize(image, intrinsics) for image, intrinsics in queries]
    torch.set_num_threads(2)
    try:
        together = list(reloc.localize_many(queries, workers=2))
        assert torch.get_num_threads() == 2  # each query had one thread; the count is back
    finally:
        torch.set_num_threads(1)
    assert [e.success for e in one_by_one] == [True, False, True] * 3
    for a, b in zip(one_by_one, together, strict=True):
        assert a.rejected == b.rejected and a.refine_path == b.refine_path
        assert np.array_equal(a.R, b.R, equal_nan=True) and np.array_equal(a.t, b.t, equal_nan=True)
    assert [e.rejected for e in reloc.localize_many(queries[:3])] == [e.rejected for e in one_by_one[:3]]


def _records(stdout: str) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if k != "seconds"} for line in stdout.splitlines()]


@pytest.mark.slow
def test_cli_workers_give_the_same_records_in_the_same_order(tmp_path: Path):
    map_path, weights = make_map(tmp_path, 0)
    folder = tmp_path / "photos"
    folder.mkdir()
    for k in range(5):
        cv2.imwrite(str(folder / f"p{k}.png"),
                    np.random.default_rng(k).integers(0, 256, (120, 160, 3), dtype=np.uint8))
    (folder / "p2b.jpg").write_bytes(b"not a jpeg")  # an unreadable photo keeps its place
    base = ["localize", "--map", str(map_path), "--encoder-weights", str(weights), "--focal", "130", str(folder)]
    runs = {}
    for threads, workers, more in ((1, 1, []), (3, 3, []), (3, 3, ["--processes"])):
        proc = subprocess.run([sys.executable, "-m", "usvc.cli", "--threads", str(threads), *base,
                               "--workers", str(workers), *more], cwd=REPO, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 1, proc.stderr  # the unreadable photo
        runs[workers, bool(more)] = _records(proc.stdout)
    assert [Path(r["name"]).name for r in runs[1, False]] == ["p0.png", "p1.png", "p2.png", "p2b.jpg", "p3.png",
                                                              "p4.png"]
    assert runs[3, False] == runs[1, False]
    assert runs[3, True] == runs[1, False]  # worker processes: the same records, the unreadable one in its place
    proc = subprocess.run([sys.executable, "-m", "usvc.cli", *base, "--workers", "0"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.strip().splitlines()[-1].endswith("--workers 0: must be a whole number >= 1")


@pytest.mark.parametrize("value", ["0", "-2", "many"])
def test_query_workers_below_one_fail_at_once(value):
    from usvc.pipeline.config import ConfigError, compose_for_script

    with pytest.raises(ConfigError, match=f"query_workers='{value}' must be 'auto' or a positive number"):
        compose_for_script("mini", [f"query_workers={value}"])
    assert compose_for_script("mini", ["query_workers=3"]).query_workers == "3"


def test_query_workers_auto_is_one_photo_per_thread():
    from usvc.pipeline.config import compose_for_script
    from usvc.pipeline.threads import query_workers

    assert compose_for_script("mini", []).query_workers == "auto"
    assert [query_workers("auto", n) for n in (1, 2, 16)] == [1, 2, 16]
    assert query_workers("3", 16) == query_workers(3, 1) == 3


def test_the_relocalize_stage_localizes_its_frames_in_order_with_workers(tmp_path: Path, synthetic_query,
                                                                         monkeypatch):
    from usvc.core.scene import Frame
    from usvc.relocalize.run import relocalize_frames

    reloc, _ = synthetic_relocalizer(tmp_path, monkeypatch)
    image = tmp_path / "query.png"
    cv2.imwrite(str(image), photo())
    fx, fy, cx, cy = CAM.params
    wrong = type(CAM)(CAM.model, CAM.width, CAM.height, (2 * fx, 2 * fy, cx, cy))  # twice the focal length
    frames = [Frame(f"q{k}", image, camera, "test") for k, camera in enumerate([CAM, wrong, CAM, wrong, CAM])]
    torch.set_num_threads(1)
    alone = relocalize_frames(reloc, frames)
    torch.set_num_threads(2)
    try:
        together = relocalize_frames(reloc, frames, workers=2)
    finally:
        torch.set_num_threads(1)
    assert [e.success for e in alone] == [True, False, True, False, True]
    for a, b in zip(alone, together, strict=True):
        assert a.rejected == b.rejected
        assert np.array_equal(a.R, b.R, equal_nan=True) and np.array_equal(a.t, b.t, equal_nan=True)
