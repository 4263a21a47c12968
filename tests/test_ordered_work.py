"""Per-photo work on several threads: results in the photos' order, the same files for any thread count."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from usvc.core.errors import SceneError
from usvc.core.ordered_pool import ordered_map
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import DepthMaps, PackedDepth, write_scene_h5
from usvc.prepare.working_images import prepare_scene


def test_ordered_map_keeps_the_order_and_bounds_what_it_holds() -> None:
    started: list[int] = []
    lock = threading.Lock()

    def work(i: int) -> int:
        with lock:
            started.append(i)
        time.sleep(0.002 * (i % 3))  # later items often finish first
        return i * i

    handed = []
    for i, (item, result) in enumerate(ordered_map(work, range(40), workers=3, ahead=2)):
        assert item == i and result == i * i
        with lock:
            assert len(started) <= i + 1 + 2 * 3 + 1  # never more than ahead x workers beyond what was handed out
        handed.append(item)
    assert handed == list(range(40)) and sorted(started) == list(range(40))
    assert list(ordered_map(work, range(5), workers=1)) == [(i, i * i) for i in range(5)]


@pytest.mark.parametrize("workers", [1, 3])
def test_ordered_map_raises_an_items_error_at_its_turn(workers: int) -> None:
    def work(i: int) -> int:
        if i in (4, 6):
            raise ValueError(f"item {i}")
        return i

    got = []
    with pytest.raises(ValueError, match="item 4"):
        for item, _ in ordered_map(work, range(10), workers=workers):
            got.append(item)
    assert got == [0, 1, 2, 3]


def _scene(root: Path, n: int = 9, missing: int | None = None) -> Scene:
    """Distorted photos (OPENCV) with 16-bit depth maps, a third of them queries."""
    rng = np.random.default_rng(0)
    cam = Camera("OPENCV", 200, 150, (160.0, 158.0, 100.5, 74.5, -0.12, 0.03, 0.001, -0.002))
    root.mkdir(parents=True)
    frames = []
    for i in range(n):
        image = cv2.GaussianBlur(rng.integers(0, 255, (150, 200, 3), dtype=np.uint8), (5, 5), 0)
        depth = (1000 + 40 * i + rng.integers(0, 500, (150, 200))).astype(np.uint16)
        path, depth_path = root / f"photo ({i}).png", root / f"depth {i}.png"
        if i != missing:
            cv2.imwrite(str(path), image)
        cv2.imwrite(str(depth_path), depth)
        frames.append(Frame(path.name, path, cam, "test" if i % 3 == 0 else "train", np.eye(3),
                            np.array([0.1 * i, 0.0, 0.0]), depth_path=depth_path, depth_scale=0.001))
    return Scene("toy", frames, 1.0, root)


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_prepare_writes_the_same_files_on_any_number_of_threads(tmp_path: Path) -> None:
    scene = _scene(tmp_path / "src")
    outs = []
    for threads in (1, 3):
        out = tmp_path / f"prepared{threads}"
        out.mkdir()
        stats = prepare_scene(scene, out, working_width=120, threads=threads)
        assert stats["frames"] == 9 and stats["has_depth"] and stats["undistorted"] == 9
        outs.append(_files(out))
    assert outs[0].keys() == outs[1].keys() and len(outs[0]) == 10  # 9 images and scene.h5
    assert all(outs[0][k] == outs[1][k] for k in outs[0]), [k for k in outs[0] if outs[0][k] != outs[1][k]]
    size = cv2.imread(str(tmp_path / "prepared3" / "images" / "photo (1).png")).shape[:2]
    assert size[1] == 120
    with DepthMaps(tmp_path / "prepared3" / "scene.h5", list(range(9))) as depths:
        assert all(d.dtype == np.float32 and d.shape == size and 0.9 < np.median(d) < 2.0 for d in depths)


@pytest.mark.parametrize("threads", [1, 3])
def test_prepare_names_the_first_photo_it_cannot_read(tmp_path: Path, threads: int) -> None:
    scene = _scene(tmp_path / "src", missing=5)
    out = tmp_path / "prepared"
    out.mkdir()
    with pytest.raises(SceneError, match=r"photo \(5\)\.png"):
        prepare_scene(scene, out, working_width=0, threads=threads)


def test_packed_and_plain_depth_are_stored_alike(tmp_path: Path) -> None:
    cam = Camera("PINHOLE", 8, 6, (8.0, 8.0, 4.0, 3.0))
    frames = [Frame(f"{i}.png", Path(f"{i}.png"), cam, "train", np.eye(3), np.zeros(3)) for i in range(3)]
    depth = np.linspace(0.5, 3.0, 48, dtype=np.float32).reshape(6, 8)
    write_scene_h5(tmp_path / "a.h5", Scene("s", frames), [depth, None, np.zeros((0, 8), np.float32)])
    write_scene_h5(tmp_path / "b.h5", Scene("s", frames), [PackedDepth.of(depth), None,
                                                            PackedDepth.of(np.zeros((0, 8), np.float32))])
    for name in ("a.h5", "b.h5"):
        with h5py.File(tmp_path / name) as h5:
            assert sorted(h5["depth"]) == ["0", "2"] and h5["depth/0"].compression == "gzip"
            np.testing.assert_array_equal(h5["depth/0"][()], depth)
            assert h5["depth/2"].shape == (0, 8)
    with h5py.File(tmp_path / "a.h5") as a, h5py.File(tmp_path / "b.h5") as b:
        assert a["depth/0"].id.read_direct_chunk((0, 0)) == b["depth/0"].id.read_direct_chunk((0, 0))
