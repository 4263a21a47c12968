"""The training loop at the card's speed: data on the device once, batches drawn a block at a time,
nothing read back from the device between the blocks' statistics. Checked on the CPU through the
same code by counting reads; the CUDA tests run where torch sees a GPU."""

from __future__ import annotations

import math
import sys

import pytest
import torch

import usvc.train.trainer as trainer
from usvc.core.errors import UsvcError
from usvc.train.trainer import TrainOptions, train_head

from test_train_head import synthetic_buffer, with_keypoint_tuples

# Every way a tensor's value reaches Python; on a GPU each one waits for the queued work.
READS = ("item", "tolist", "numpy", "cpu", "__float__", "__int__", "__bool__", "__index__", "__format__")


def _bundle_buffer():
    buf, pts, feats = synthetic_buffer(n_points=60, n_views=6)
    return with_keypoint_tuples(buf, pts, feats, one_view_pixels=False)


def _opts(**kw) -> TrainOptions:
    base = dict(iterations=30, batch_size=64, lr=3e-3, threshold_start=20.0, bundle_weight=0.5,
                bundle_groups_per_batch=8, bundle_obs_per_group=4, precision="fp32", report_every=7)
    return TrainOptions(**{**base, **kw})


def _same(a: torch.nn.Module, b: torch.nn.Module) -> None:
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(va.cpu(), vb.cpu(), rtol=0, atol=0, msg=k)


def test_the_loop_reads_the_device_only_once_a_block(monkeypatch):
    """Every read of a tensor's value made by usvc's code during training is counted; the only
    ones allowed are `read_back`'s, one per block of `report_every` steps."""
    strays: list[str] = []
    blocks: list[int] = []

    def counted(name, original):
        def method(self, *args, **kwargs):
            caller = sys._getframe(1).f_code
            if "/usvc/" in caller.co_filename.replace("\\", "/") and caller.co_name != "read_back":
                strays.append(f"{name} in {caller.co_name} ({caller.co_filename})")
            return original(self, *args, **kwargs)
        return method

    real_read_back = trainer.read_back

    def read_back(values):
        blocks.append(len(values))
        return real_read_back(values)

    monkeypatch.setattr(trainer, "read_back", read_back)
    for name in READS:
        monkeypatch.setattr(torch.Tensor, name, counted(name, getattr(torch.Tensor, name)))
    _, summary = train_head(_bundle_buffer(), 3.0, _opts(), head_width=32, head_blocks=1)
    assert strays == []
    assert blocks == [7, 7, 7, 7, 2]  # ceil(30 / 7) reads, each the block's steps
    assert math.isfinite(summary["final_loss"]) and math.isfinite(summary["final_bundle_loss"])


def test_the_block_length_does_not_change_the_map():
    """Batches are drawn on the host in the order the seed gives, however many at a time."""
    buf = _bundle_buffer()
    heads = [train_head(buf, 3.0, _opts(report_every=every), head_width=32, head_blocks=1)[0]
             for every in (1, 7, 1000)]
    _same(heads[0], heads[1])
    _same(heads[0], heads[2])


def test_divergence_is_named_at_the_step_it_happened(monkeypatch):
    """The finite check reads the block's losses: it names the first step whose loss was not finite."""
    real_loss = trainer.reprojection_loss
    calls = []

    def failing(*args, **kwargs):
        loss, stats = real_loss(*args, **kwargs)
        calls.append(1)
        return (loss * float("nan") if len(calls) == 12 else loss), stats

    monkeypatch.setattr(trainer, "reprojection_loss", failing)
    with pytest.raises(UsvcError, match=r"training diverged at iteration 11 \(loss nan\); lower train.lr"):
        train_head(_bundle_buffer(), 3.0, _opts(), head_width=32, head_blocks=1)
    assert len(calls) == 14  # caught at the end of the block (steps 7-13), not later


def test_report_every_must_be_positive():
    with pytest.raises(UsvcError, match="report_every"):
        train_head(_bundle_buffer(), 3.0, _opts(report_every=0), head_width=32, head_blocks=1)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_cuda_training_is_the_same_map_every_time_and_never_waits_inside_a_block(precision):
    buf = _bundle_buffer()
    opts = _opts(precision=precision, iterations=40, report_every=20)
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with _no_sync_warnings_outside_reads() as warned:
            a, summary = train_head(buf, 3.0, opts, head_width=64, head_blocks=1, device="cuda")
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert warned == [], warned
    b, _ = train_head(buf, 3.0, opts, head_width=64, head_blocks=1, device="cuda")
    _same(a, b)
    assert summary["precision"] == precision
    if precision == "fp32":  # the same draws and arithmetic as the CPU's, up to the kernels' rounding
        cpu, _ = train_head(buf, 3.0, opts, head_width=64, head_blocks=1)
        x = torch.from_numpy(buf.features[:200]).float()
        with torch.no_grad():
            torch.testing.assert_close(a.forward_flat(x.cuda()).cpu(), cpu.forward_flat(x), rtol=0.01, atol=0.01)


class _no_sync_warnings_outside_reads:
    """Collects CUDA's synchronisation warnings, except those `read_back` (the block's one read) makes."""

    def __enter__(self):
        import warnings

        self._catch = warnings.catch_warnings(record=True)
        self._records = self._catch.__enter__()
        warnings.simplefilter("always")
        self._real = trainer.read_back
        records = self._records

        def read_back(values):
            before = len(records)
            out = self._real(values)
            del records[before:]
            return out

        trainer.read_back = read_back
        self.found: list[str] = []
        return self.found

    def __exit__(self, *exc):
        trainer.read_back = self._real
        self.found.extend(str(r.message) for r in self._records if "synchroniz" in str(r.message))
        self._catch.__exit__(*exc)
        return False
