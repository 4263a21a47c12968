"""Many photos in worker processes (`usvc.relocalize.photo_processes`, `localize_many(processes=True)`,
`usvc localize --workers N --processes`): the answers in the photos' order, bit for bit those of the
photos one after the other with the same threads per query; a photo's failure at its turn; a worker
that cannot start is one clear error."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_cli import make_map

from usvc.core.errors import UsvcError
from usvc.relocalize.photo_processes import in_processes
from usvc.relocalize.relocalizer import Relocalizer


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> tuple[Relocalizer, list[Path]]:
    folder = tmp_path_factory.mktemp("processes")
    map_path, weights = make_map(folder, 0)
    photos = []
    for k in range(5):
        path = folder / f"p{k}.png"
        cv2.imwrite(str(path), np.random.default_rng(k).integers(0, 256, (120, 160, 3), dtype=np.uint8))
        photos.append(path)
    return Relocalizer(map_path, weights, device="cpu"), photos


def _same(a, b) -> bool:
    return (a.rejected == b.rejected and a.success == b.success and np.array_equal(a.R, b.R, equal_nan=True)
            and np.array_equal(a.t, b.t, equal_nan=True))


def test_processes_give_the_answers_of_one_photo_after_another(mapped):
    reloc, photos = mapped
    queries = [(p, (130.0, 130.0, 80.0, 60.0)) for p in photos] + [(photos[0], None)]
    torch.set_num_threads(1)
    one_by_one = [reloc.localize(image, intrinsics) for image, intrinsics in queries]
    torch.set_num_threads(2)
    try:
        together = list(reloc.localize_many(queries, workers=2, processes=True))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
    assert len(together) == len(queries)
    assert all(_same(a, b) for a, b in zip(one_by_one, together, strict=True))


def test_a_photos_failure_is_raised_at_its_turn_or_handed_out(mapped, tmp_path: Path):
    reloc, photos = mapped
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not a jpeg")
    queries = [(photos[0], None), (bad, None), (photos[1], None)]
    got = reloc.localize_many(queries, workers=2, processes=True)
    assert hasattr(next(got), "R")  # the first photo's answer comes first
    with pytest.raises(UsvcError, match="cannot decode image"):
        next(got)
    got.close()
    known = UsvcError("already known to be unreadable")
    items = [(photos[0], None, {}), known, (bad, None, {}), (photos[1], None, {})]
    out = list(in_processes(Relocalizer, reloc.args, items, 2, 1, errors="return"))
    assert out[1] is known and isinstance(out[2], UsvcError) and "cannot decode image" in str(out[2])
    assert not isinstance(out[0], UsvcError) and not isinstance(out[3], UsvcError)
    with pytest.raises(ValueError, match="errors must be"):
        next(in_processes(Relocalizer, reloc.args, items, 2, 1, errors="ignore"))


def test_a_worker_that_cannot_start_is_one_clear_error(mapped, tmp_path: Path):
    reloc, photos = mapped
    gone = replace(reloc.args, map_path=tmp_path / "missing.map.pt")
    with pytest.raises(UsvcError, match="a worker process stopped"):
        list(in_processes(Relocalizer, gone, [(photos[0], None, {})], 2, 1))
