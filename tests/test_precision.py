"""The precision setting (`auto | bf16 | fp32`): how `auto` decides, what runs in bf16 and what
stays fp32, and that a bf16 training step agrees with fp32's within bf16's rounding."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from test_train_head import synthetic_buffer
from usvc.core import precision as prec
from usvc.model.head import Head
from usvc.pipeline.config import ConfigError, compose_for_script, validate
from usvc.train.reprojection_loss import reprojection_loss
from usvc.train.trainer import TrainOptions, heldout_fit, train_head

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both

REPO = Path(__file__).resolve().parents[1]
PROBE = prec.cpu_bf16_speedup  # the cached function itself, whatever a test patches in its place


@pytest.fixture
def fresh_probe():
    PROBE.cache_clear()
    yield
    PROBE.cache_clear()


@pytest.mark.parametrize("group", ["train", "buffer", "relocalize"])
def test_a_bad_precision_fails_at_config_time_naming_the_key(group):
    with pytest.raises(ConfigError, match=rf"{group}.precision='half' is not one of \['auto', 'bf16', 'fp32'\]"):
        validate(compose_for_script("mini", [f"{group}.precision=half"]))
    validate(compose_for_script("mini", [f"{group}.precision=bf16"]))


@pytest.mark.slow
def test_a_bad_precision_stops_the_stage_in_one_line():
    proc = subprocess.run([sys.executable, "-m", "stages.train", "train.precision=fp16"], cwd=REPO,
                          capture_output=True, text=True)
    assert proc.returncode == 1
    assert "train.precision='fp16'" in proc.stderr + proc.stdout
    assert "Traceback" not in proc.stderr + proc.stdout


def test_auto_is_fp32_without_native_bf16_and_never_runs_the_probe(monkeypatch, fresh_probe):
    monkeypatch.setattr(prec, "cpu_has_native_bf16", lambda: False)
    monkeypatch.setattr(prec, "product_seconds", lambda *a, **k: pytest.fail("the probe ran"))
    assert prec.resolve_precision("auto", "cpu") == "fp32"


@pytest.mark.parametrize("speedup, expected", [(2.6, "bf16"), (1.0, "fp32"), (0.05, "fp32")])
def test_auto_with_native_bf16_follows_the_measured_probe(monkeypatch, fresh_probe, speedup, expected):
    monkeypatch.setattr(prec, "cpu_has_native_bf16", lambda: True)
    monkeypatch.setattr(prec, "cpu_bf16_speedup", lambda: speedup)
    assert prec.resolve_precision("auto", "cpu") == expected


def test_explicit_settings_are_kept_and_unknown_ones_refused():
    assert prec.resolve_precision("bf16", "cpu") == "bf16"
    assert prec.resolve_precision("fp32", "cpu") == "fp32"
    with pytest.raises(ValueError, match="not one of"):
        prec.resolve_precision("fp16", "cpu")
    with pytest.raises(ValueError, match="resolve"):
        with prec.autocast("auto"):
            pass


@pytest.mark.probe
def test_the_probe_is_measured_once_per_process(monkeypatch, fresh_probe):
    calls = []
    monkeypatch.setattr(prec, "product_seconds", lambda dtype, reps=8: calls.append(dtype) or 1.0)
    assert prec.cpu_bf16_speedup() == 1.0 and prec.cpu_bf16_speedup() == 1.0
    assert calls == [torch.float32, torch.bfloat16]


@pytest.mark.probe
def test_native_bf16_check_matches_the_kernels_flags():
    flags = prec._cpuinfo_flags()
    if not flags:
        pytest.skip("no /proc/cpuinfo")
    assert prec.cpu_has_native_bf16() == bool(flags & {"avx512_bf16", "amx_bf16"})


def test_bf16_runs_the_head_layers_in_bf16_and_returns_fp32_coordinates():
    torch.manual_seed(0)
    head = Head(in_channels=32, width=64, num_blocks=1)
    head.set_scene_center([100.0, -50.0, 3.0])  # far from the origin: the centre is added in fp32
    x = torch.randn(256, 32)
    with prec.autocast("bf16"):
        lo = head.forward_flat(x)
    hi = head.forward_flat(x)
    assert lo.dtype == torch.float32 and head.fc1.weight.dtype == torch.float32
    assert not torch.equal(lo, hi)  # it did run in bf16
    # bf16 keeps 8 bits of mantissa: the head's raw output differs by about 2^-8 of its scale
    raw = (hi - head.scene_center).abs().max()
    assert (lo - hi).abs().max() < 0.05 * raw


def test_a_bf16_training_step_agrees_with_fp32_within_bf16_rounding():
    """Same head, same batch: the loss of one step and the gradient's direction. The loss is
    computed in fp32 in both cases (autocast is off inside the loss); only the head's products
    differ, by bf16's relative rounding (2^-8 = 0.4 %) accumulated over a few layers."""
    buf, _, _ = synthetic_buffer(n_points=200, n_views=6)
    feats = torch.from_numpy(buf.features).float()
    v = torch.from_numpy(buf.view_index.astype(np.int64))
    R, t = torch.from_numpy(buf.view_R_world_to_cam)[v], torch.from_numpy(buf.view_t_world_to_cam)[v]
    K = torch.from_numpy(buf.view_K)[v]
    uv = torch.from_numpy(buf.pixels)
    results = {}
    for p in ("fp32", "bf16"):
        torch.manual_seed(0)
        head = Head(in_channels=feats.shape[1], width=64, num_blocks=1)
        head.set_scene_center([0.0, 0.0, 0.5])
        with prec.autocast(p):
            pred = head.forward_flat(feats)
        loss, _ = reprojection_loss(pred, uv, R, t, K, torch.linalg.inv(K), 20.0, depth_min=0.15,
                                    depth_max=1500.0, max_reproj=1000.0, invalid_depth=15.0)
        assert loss.dtype == torch.float32
        loss.backward()
        grad = torch.cat([q.grad.flatten() for q in head.parameters()])
        results[p] = (float(loss.detach()), grad)
    (l32, g32), (l16, g16) = results["fp32"], results["bf16"]
    assert abs(l16 - l32) <= 0.005 * abs(l32), (l16, l32)  # measured: 0.002 %
    cosine = float(torch.nn.functional.cosine_similarity(g16, g32, dim=0))
    assert cosine > 0.995, cosine  # measured: 0.99993


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_training_at_a_fixed_precision_repeats_bit_for_bit(precision):
    buf, _, _ = synthetic_buffer(n_points=50, n_views=4)
    opts = TrainOptions(iterations=4, batch_size=64, bundle_weight=0.0, precision=precision)
    a, sa = train_head(buf, 3.0, opts, head_width=32, head_blocks=1)
    b, _ = train_head(buf, 3.0, opts, head_width=32, head_blocks=1)
    assert sa["precision"] == precision
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(va, vb, rtol=0, atol=0, msg=k)


def test_training_records_the_resolved_precision(monkeypatch, fresh_probe):
    monkeypatch.setattr(prec, "cpu_has_native_bf16", lambda: False)
    buf, _, _ = synthetic_buffer(n_points=50, n_views=4)
    _, summary = train_head(buf, 3.0, TrainOptions(iterations=2, batch_size=64, bundle_weight=0.0), head_width=32,
                            head_blocks=1)
    assert summary["precision"] == "fp32"


def test_the_heldout_curve_reads_the_head_without_changing_it():
    buf, pts, feats = synthetic_buffer(n_points=120, n_views=8)
    held, _, _ = synthetic_buffer(n_points=120, n_views=8, seed=0)  # the same points, seen again
    # fp32 pinned: the curve is compared bit for bit with an fp32 heldout_fit below (`auto` is bf16
    # on CPUs with native bf16)
    opts = TrainOptions(iterations=60, batch_size=256, lr=3e-3, threshold_start=20.0, bundle_weight=0.0,
                        validate_every=20, precision="fp32")
    a, plain = train_head(buf, 3.0, opts, head_width=64, head_blocks=1)
    b, summary = train_head(buf, 3.0, opts, head_width=64, head_blocks=1, heldout=held)
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(va, vb, rtol=0, atol=0, msg=k)
    assert "heldout_curve" not in plain
    curve = summary["heldout_curve"]
    assert [c["iteration"] for c in curve] == [20, 40, 60]
    assert curve[-1]["median_reprojection_px"] < curve[0]["median_reprojection_px"]
    final = heldout_fit(b, held, "fp32", depth_min=0.15)
    assert final == {k: curve[-1][k] for k in final}


def test_importing_usvc_sets_a_passive_wait_policy_unless_the_user_chose_one():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = "import usvc, os; print(os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OMP_WAIT_POLICY": "ACTIVE"},
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ACTIVE"


def test_stages_start_with_the_passive_wait_policy_before_torch_loads():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = ("import sys; import stages; import os; "
            "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["PASSIVE", "False"]
