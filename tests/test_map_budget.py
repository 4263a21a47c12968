"""The map budget grows with the scene: buffer cells per mapping photo (within a floor and a
memory bound) and training steps as passes over the buffer, as ACE sizes its buffer and epochs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_buffer import SEED, SHORT_SIDE, encoder, scene  # noqa: F401 (fixtures)
from test_train_head import synthetic_buffer

from usvc.buffer.build import fill_buffer
from usvc.buffer.options import BufferOptions
from usvc.core.errors import UsvcError
from usvc.core.options import check
from usvc.core.scene_file import read_scene_h5
from usvc.train.options import TrainOptions
from usvc.train.trainer import train_head


def test_default_budget_keeps_small_scenes_and_grows_with_photos():
    b, t = BufferOptions(), TrainOptions()
    # Up to 64 photos: the budget the defaults were tuned on (mini's 60 photos), 500 steps.
    for photos in (1, 20, 60, 64):
        assert b.cells_for(photos) == 262144 and t.steps_for(b.cells_for(photos)) == 500
    # A 128-photo room gets twice the cells and twice the steps, linearly in between ...
    assert b.cells_for(128) == 2 * 262144 and t.steps_for(b.cells_for(128)) == 1000
    assert b.cells_for(100) == 409600 and t.steps_for(409600) == 781
    # ... up to the memory bound.
    assert b.cells_for(256) == b.cells_for(5000) == 1048576 and t.steps_for(1048576) == 2000


@pytest.mark.parametrize("name, steps", [("long", 2000), ("full", 6000)])
def test_longer_trainings_are_the_default_with_more_passes(name: str, steps: int):
    """train=long (a map that judges focal lengths) and train=full (the full-length recipe), one
    override away: 4x and 12x the default's 500 steps on the smallest buffer, nothing else changed."""
    from usvc.pipeline.config import compose_for_script, group_options

    longer = group_options(compose_for_script("mini", [f"train={name}"]), "train")
    default = group_options(compose_for_script("mini", []), "train")
    assert longer.steps_for(262144) == steps and default.steps_for(262144) == 500
    assert {k: v for k, v in vars(longer).items() if k != "passes"} == {k: v for k, v in vars(default).items()
                                                                        if k != "passes"}


def test_explicit_size_and_iterations_win():
    assert BufferOptions(size=1000).cells_for(500) == 1000
    assert TrainOptions(iterations=77).steps_for(10**7) == 77
    assert TrainOptions(passes=2.0, batch_size=100).steps_for(1000) == 20


@pytest.mark.parametrize("opts, message", [
    (BufferOptions(min_size=2000, max_size=1000), "buffer option min_size=2000 exceeds max_size=1000"),
    (BufferOptions(size=-1), "buffer option size=-1 must be >= 0"),
    (BufferOptions(cells_per_image=0), "buffer option cells_per_image=0 must be > 0"),
    (TrainOptions(passes=0.0), "train option passes=0.0 must be > 0"),
    (TrainOptions(passes=float("inf")), "train option passes=inf must be finite"),
    (TrainOptions(iterations=-5), "train option iterations=-5 must be >= 0"),
])
def test_bad_budget_options_are_named(opts, message):
    with pytest.raises(UsvcError, match=message):
        check(opts, "buffer" if isinstance(opts, BufferOptions) else "train")


def test_buffer_cells_follow_the_photo_count(scene, encoder):  # noqa: F811
    frames = read_scene_h5(scene / "scene.h5").split("train")  # 3 mapping images
    opts = BufferOptions(size=0, cells_per_image=200, min_size=300, max_size=500, samples_per_image=150)
    assert len(fill_buffer(frames[:1], encoder, opts, SHORT_SIDE, seed=SEED).features) == 300  # the floor
    assert len(fill_buffer(frames[:2], encoder, opts, SHORT_SIDE, seed=SEED).features) == 400
    assert len(fill_buffer(frames, encoder, opts, SHORT_SIDE, seed=SEED).features) == 500  # the bound
    # Rendered views add views, not budget: the count of mapping photos is what sizes it.
    assert len(fill_buffer(frames, encoder, opts, SHORT_SIDE, seed=SEED, mapping_images=2).features) == 400


def test_training_steps_follow_the_buffer():
    buf, _, _ = synthetic_buffer(n_points=50, n_views=4)  # 200 cells
    opts = TrainOptions(iterations=0, passes=1.6, batch_size=64, bundle_weight=0.0)
    head, summary = train_head(buf, 3.0, opts, head_width=32, head_blocks=1)
    assert summary["iterations"] == 5 and summary["epochs"] == pytest.approx(1.6)
    same, _ = train_head(buf, 3.0, TrainOptions(iterations=5, batch_size=64, bundle_weight=0.0), head_width=32,
                         head_blocks=1)
    for a, b in zip(head.state_dict().values(), same.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert np.isfinite(summary["final_loss"])
