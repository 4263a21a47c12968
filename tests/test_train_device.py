"""The training loop at the card's speed: data on the device once, batches drawn a block at a time,
nothing read back from the device between the blocks' statistics. Checked on the CPU through the
same code by counting reads; the CUDA tests run where torch sees a GPU."""

from __future__ import annotations

import math
import sys
from dataclasses import replace

import pytest
import torch

import usvc.train.train_step as train_step
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


def test_the_next_block_is_drawn_before_the_queued_one_is_read(monkeypatch):
    """On a GPU the steps of a block are queued, not run, when the loop reaches the read: drawing the
    next block first keeps the host's draw (the keypoint groups are picked in Python) beside the
    device's work instead of between blocks. Each block is drawn once, in order, and none after
    the last."""
    events: list[str] = []
    real_block, real_read_back = trainer._BatchDraw.block, trainer.read_back

    def block(self, steps, device):
        events.append(f"draw {steps}")
        return real_block(self, steps, device)

    def read_back(values):
        events.append(f"read {len(values)}")
        return real_read_back(values)

    monkeypatch.setattr(trainer._BatchDraw, "block", block)
    monkeypatch.setattr(trainer, "read_back", read_back)
    train_head(_bundle_buffer(), 3.0, _opts(), head_width=32, head_blocks=1)
    assert events == ["draw 7", "draw 7", "read 7", "draw 7", "read 7", "draw 7", "read 7", "draw 2", "read 7",
                      "read 2"]


def test_the_block_length_does_not_change_the_map():
    """Batches are drawn on the host in the order the seed gives, however many at a time."""
    buf = _bundle_buffer()
    heads = [train_head(buf, 3.0, _opts(report_every=every), head_width=32, head_blocks=1)[0]
             for every in (1, 7, 1000)]
    _same(heads[0], heads[1])
    _same(heads[0], heads[2])


def test_divergence_is_named_at_the_step_it_happened(monkeypatch):
    """The finite check reads the block's losses: it names the first step whose loss was not finite."""
    real_loss = train_step.reprojection_loss
    calls = []

    def failing(*args, **kwargs):
        loss, stats = real_loss(*args, **kwargs)
        calls.append(1)
        return (loss * float("nan") if len(calls) == 12 else loss), stats

    monkeypatch.setattr(train_step, "reprojection_loss", failing)
    with pytest.raises(UsvcError, match=r"training diverged at iteration 11 \(loss nan\); lower train.lr"):
        train_head(_bundle_buffer(), 3.0, _opts(), head_width=32, head_blocks=1)
    assert len(calls) == 14  # caught at the end of the block (steps 7-13), not later


def test_report_every_must_be_positive():
    with pytest.raises(UsvcError, match="report_every"):
        train_head(_bundle_buffer(), 3.0, _opts(report_every=0), head_width=32, head_blocks=1)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("precision,graph", [("fp32", True), ("bf16", True), ("fp32", False)])
def test_cuda_training_is_the_same_map_every_time_and_never_waits_inside_a_block(precision, graph, monkeypatch):
    """CUDA warns of every synchronising call from the first block's draw on (the setup before the
    loop copies the buffer to the device, which may wait)."""
    buf = _bundle_buffer()
    opts = _opts(precision=precision, iterations=40, report_every=20, cuda_graph=graph)
    real_block = trainer._BatchDraw.block

    def block(self, steps, device):
        torch.cuda.set_sync_debug_mode("warn")
        return real_block(self, steps, device)

    monkeypatch.setattr(trainer._BatchDraw, "block", block)
    try:
        with _no_sync_warnings_outside_reads() as warned:
            a, summary = train_head(buf, 3.0, opts, head_width=64, head_blocks=1, device="cuda")
    finally:
        torch.cuda.set_sync_debug_mode(0)
        monkeypatch.undo()
    assert warned == [], warned
    assert summary["cuda_graph"] == ("captured" if graph else "off")
    b, _ = train_head(buf, 3.0, opts, head_width=64, head_blocks=1, device="cuda")
    _same(a, b)
    assert summary["precision"] == precision
    if precision == "fp32":
        # The same draws and arithmetic as the CPU's: the same losses over the first steps (the
        # warm-up, the capture and replays). Not the same weights after many steps: Adam's first
        # steps move every weight by +-lr whatever its gradient's size, so a gradient near zero
        # whose sign differs in the last bit between the two devices' kernels moves its weight the
        # other way, and such differences grow over training.
        short = replace(opts, iterations=6, report_every=6)
        _, on_gpu = train_head(buf, 3.0, short, head_width=64, head_blocks=1, device="cuda")
        _, on_cpu = train_head(buf, 3.0, short, head_width=64, head_blocks=1)
        for key in ("loss_curve", "bundle_loss_curve"):
            assert on_gpu[key] == pytest.approx(on_cpu[key], rel=1e-2), key
        assert on_gpu["final_loss"] == pytest.approx(on_cpu["final_loss"], rel=1e-2)


class _no_sync_warnings_outside_reads:
    """Collects CUDA's synchronisation warnings, except those `read_back` (the block's one read) and
    `capture` (the graph's capture, once) make."""

    def __enter__(self):
        import warnings

        self._catch = warnings.catch_warnings(record=True)
        self._records = self._catch.__enter__()
        warnings.simplefilter("always")
        self._real = trainer.read_back, train_step.capture
        records = self._records

        def allowed(real):
            def call(*args):
                before = len(records)
                out = real(*args)
                del records[before:]
                return out
            return call

        trainer.read_back, train_step.capture = (allowed(real) for real in self._real)
        self.found: list[str] = []
        return self.found

    def __exit__(self, *exc):
        trainer.read_back, train_step.capture = self._real
        # CUDA's words for a call that waits ("called a synchronizing CUDA operation"); not its
        # notice that the debug mode is a prototype, which says "synchronizing operations" too.
        self.found.extend(str(r.message) for r in self._records
                          if "synchroniz" in str(r.message) and "prototype" not in str(r.message))
        self._catch.__exit__(*exc)
        return False


@pytest.mark.parametrize("schedule,optimizer", [("one_cycle", "adamw"), ("constant", "adamw"),
                                                ("one_cycle", "adabelief")])
def test_each_step_gets_the_rate_and_beta1_torchs_scheduler_gives_it(schedule, optimizer):
    """The loop sets every step's learning rate and beta1 from lists worked out up front (so that a
    CUDA graph can read them on the device): what the scheduler sets on a real run."""
    opts = _opts(schedule=schedule, optimizer=optimizer, iterations=50, warmup_fraction=0.3)
    lrs, beta1s = trainer.schedule_values(opts)
    param = torch.nn.Parameter(torch.ones(3))
    optim = (torch.optim.AdamW([param], lr=opts.lr, weight_decay=opts.weight_decay) if optimizer == "adamw"
             else trainer._optimizer(opts, [param], "cpu"))
    sched = (torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=opts.lr, total_steps=50, pct_start=0.3)
             if schedule == "one_cycle" else torch.optim.lr_scheduler.LambdaLR(optim, lambda _: 1.0))
    for it in range(50):
        group = optim.param_groups[0]
        assert (group["lr"], group["betas"][0]) == (lrs[it], beta1s[it]), it
        param.grad = torch.full((3,), 0.1)
        optim.step()
        sched.step()
    if schedule == "one_cycle":  # the rate peaks at lr after 30 %; beta1 goes 0.95 -> 0.85 -> 0.95
        peak = max(range(50), key=lrs.__getitem__)
        assert lrs[peak] == pytest.approx(opts.lr) and 13 <= peak <= 16 and lrs[-1] < opts.lr / 100
        assert beta1s[peak] == pytest.approx(0.85) and beta1s[0] == beta1s[-1] == pytest.approx(0.95)
    else:
        assert set(lrs) == {opts.lr} and set(beta1s) == {0.9}


def test_training_with_the_graph_optimizer_is_training_with_torchs(monkeypatch):
    """On CUDA the step uses GraphAdamW (rate and beta1 on the device); the same training on the
    CPU with it ends where torch's AdamW ends (the same update, rounded in another order)."""
    buf = _bundle_buffer()
    opts = _opts(iterations=30, report_every=10)
    _, torch_adamw = train_head(buf, 3.0, opts, head_width=32, head_blocks=1)
    made = []

    def graph_optimizer(opts, params, device):
        made.append(trainer.GraphAdamW(params, lr=opts.lr, weight_decay=opts.weight_decay))
        return made[-1]

    monkeypatch.setattr(trainer, "_optimizer", graph_optimizer)
    _, graph_adamw = train_head(buf, 3.0, opts, head_width=32, head_blocks=1)
    assert made and float(made[-1].steps) == 30
    assert graph_adamw["loss_curve"] == pytest.approx(torch_adamw["loss_curve"], rel=1e-3)
    assert graph_adamw["final_loss"] == pytest.approx(torch_adamw["final_loss"], rel=1e-3)
