"""Photos localized side by side go through the network as one batch (`usvc.relocalize.network_batch`,
`usvc serve --batch`): every photo gets its own row's coordinates, photos of another size batch on
their own, a full batch leaves the rest to the next one, an error reaches every photo of its batch,
and a relocalizer's batched coordinates match its unbatched ones (fp32) with batches formed."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from test_localize_bad_input import tiny_map  # noqa: F401 (fixture)
from test_relocalizer import photo

from usvc.relocalize.network_batch import NetworkBatcher
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.query_input import as_gray
from usvc.relocalize.relocalizer import Relocalizer


def side_by_side(fn, inputs: list) -> list:
    """fn(x) for every input on threads started together."""
    out: list = [None] * len(inputs)
    start = threading.Barrier(len(inputs))

    def run(i: int) -> None:
        start.wait()
        try:
            out[i] = fn(inputs[i])
        except Exception as e:  # noqa: BLE001 (the test looks at it)
            out[i] = e

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(inputs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    return out


class Doubler:
    def __init__(self) -> None:
        self.calls: list[list[tuple[int, ...]]] = []
        self.lock = threading.Lock()

    def __call__(self, grays: list[np.ndarray]) -> list[np.ndarray]:
        with self.lock:
            self.calls.append([g.shape for g in grays])
        return [2 * g for g in grays]


def test_each_photo_gets_its_own_rows_and_batches_form() -> None:
    forward = Doubler()
    batcher = NetworkBatcher(forward, max_batch=8, wait_s=0.5)
    inputs = [np.full((4, 6), float(i)) for i in range(8)]
    out = side_by_side(batcher, inputs)
    for i, o in enumerate(out):
        np.testing.assert_array_equal(o, 2 * inputs[i])
    assert sum(batcher.batches) == 8 and max(batcher.batches) > 1


def test_sizes_batch_apart_and_a_full_batch_leaves_the_rest_to_the_next() -> None:
    forward = Doubler()
    batcher = NetworkBatcher(forward, max_batch=3, wait_s=0.3)
    inputs = [np.full((4, 6) if i % 2 else (6, 4), float(i)) for i in range(10)]
    out = side_by_side(batcher, inputs)
    for i, o in enumerate(out):
        np.testing.assert_array_equal(o, 2 * inputs[i])
    assert sum(batcher.batches) == 10 and max(batcher.batches) <= 3
    assert all(len(set(shapes)) == 1 for shapes in forward.calls)  # one size a batch


def test_an_error_reaches_every_photo_of_its_batch_and_the_next_batch_runs() -> None:
    def broken(grays: list[np.ndarray]) -> list[np.ndarray]:
        raise RuntimeError("out of memory")

    batcher = NetworkBatcher(broken, max_batch=4, wait_s=0.3)
    out = side_by_side(batcher, [np.zeros((2, 2)) for _ in range(4)])
    assert all(isinstance(o, RuntimeError) for o in out)
    batcher.forward = Doubler()
    np.testing.assert_array_equal(batcher(np.ones((2, 2))), 2 * np.ones((2, 2)))


def test_the_options_are_checked() -> None:
    with pytest.raises(ValueError, match="max_batch"):
        NetworkBatcher(Doubler(), max_batch=0)
    with pytest.raises(ValueError, match="wait_s"):
        NetworkBatcher(Doubler(), wait_s=-1)


def test_a_relocalizers_batched_coordinates_match_its_own(tiny_map: tuple[Path, Path]) -> None:
    reloc = Relocalizer(*tiny_map, RelocalizeOptions(precision="fp32"))
    grays = [np.clip(as_gray(photo(160, 120), "rgb") * (1 - 0.1 * s) + 0.05 * s, 0, 1) for s in range(4)]
    alone = [reloc.scene_coordinates(g) for g in grays]
    reloc.batch_network(4, wait_s=0.5)
    together = side_by_side(reloc.scene_coordinates, grays)
    assert max(reloc.batcher.batches) > 1  # type: ignore[union-attr]
    for a, b in zip(alone, together):
        assert a.shape == b.shape and a.dtype == b.dtype == np.float64
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-4 * float(np.abs(a).max()))
    reloc.batch_network(1)
    assert reloc.batcher is None
