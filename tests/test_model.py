from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from usvc.core.errors import UsvcError
from usvc.model.encoder import (
    LAYERS,
    Encoder,
    cell_centers,
    encoder_fingerprint,
    encoder_flops,
    load_encoder_weights,
)
from usvc.model.errors import ModelError
from usvc.model.head import Head, Regressor, homogeneous_scale
from usvc.model.map_file import load_map, save_map
from usvc.model.preprocess import luma01, normalise, resize_to_short_side

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both

MODEL_DIR = Path(__file__).resolve().parents[1] / "usvc" / "model"


@pytest.fixture(scope="module")
def encoder() -> Encoder:
    torch.manual_seed(0)
    return Encoder().eval()


@pytest.fixture(scope="module")
def small_encoder() -> Encoder:
    """Map tests use the narrow encoder: same code paths, a quarter of the hashing work."""
    torch.manual_seed(1)
    return Encoder(width=0.5).eval()


def fabricated_state(width: float = 1.0) -> dict[str, torch.Tensor]:
    """A state dict built only from the published table, as a weight file would hold it."""
    gen = torch.Generator().manual_seed(1)
    state = {}
    for name, cin, cout, k, _ in LAYERS:
        cin_s = 1 if cin == 1 else int(round(cin * width / 8)) * 8
        cout_s = int(round(cout * width / 8)) * 8
        state[f"{name}.weight"] = torch.randn(cout_s, cin_s, k, k, generator=gen) * 0.01
        state[f"{name}.bias"] = torch.randn(cout_s, generator=gen) * 0.01
    return state


def test_encoder_state_dict_matches_table(encoder: Encoder) -> None:
    state = encoder.state_dict()
    assert len(state) == 22
    expected = {}
    for name, cin, cout, k, _ in LAYERS:
        expected[f"{name}.weight"] = (cout, cin, k, k)
        expected[f"{name}.bias"] = (cout,)
    assert {k: tuple(v.shape) for k, v in state.items()} == expected
    n_params = sum(p.numel() for p in encoder.parameters())
    assert abs(n_params - 5.57e6) / 5.57e6 < 0.01
    assert encoder.out_channels == 512 and Encoder.OUTPUT_STRIDE == 8


def test_fabricated_weights_load_strictly(tmp_path: Path) -> None:
    state = fabricated_state()
    path = tmp_path / "encoder.pt"
    torch.save(state, path)
    enc = load_encoder_weights(path)
    for key, value in enc.state_dict().items():
        assert torch.equal(value, state[key])
    assert not enc.training and not any(p.requires_grad for p in enc.parameters())


def test_half_width_weights_load(tmp_path: Path) -> None:
    path = tmp_path / "small.pt"
    torch.save(fabricated_state(0.5), path)
    assert load_encoder_weights(path, width=0.5).out_channels == 256
    with pytest.raises(ModelError, match="shape"):
        load_encoder_weights(path)  # default width does not fit


def test_wrong_key_named(tmp_path: Path) -> None:
    state = fabricated_state()
    state["extra.weight"] = state.pop("res2_skip.bias")
    path = tmp_path / "bad_keys.pt"
    torch.save(state, path)
    with pytest.raises(ModelError) as info:
        load_encoder_weights(path)
    msg = str(info.value)
    assert str(path) in msg and "missing res2_skip.bias" in msg and "unexpected extra.weight" in msg
    assert "\n" not in msg


def test_wrong_shape_named(tmp_path: Path) -> None:
    state = fabricated_state()
    state["conv3.weight"] = torch.zeros(128, 64, 1, 1)
    path = tmp_path / "bad_shape.pt"
    torch.save(state, path)
    with pytest.raises(ModelError) as info:
        load_encoder_weights(path)
    msg = str(info.value)
    assert "conv3.weight" in msg and "[128, 64, 1, 1]" in msg and "[128, 64, 3, 3]" in msg


def test_corrupt_and_missing_files(tmp_path: Path) -> None:
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a torch file at all")
    with pytest.raises(ModelError, match="corrupt.pt: cannot read"):
        load_encoder_weights(corrupt)
    with pytest.raises(ModelError, match="does not exist"):
        load_encoder_weights(tmp_path / "nope.pt")
    not_dict = tmp_path / "list.pt"
    torch.save([torch.zeros(1)], not_dict)
    with pytest.raises(ModelError, match="not a state dict"):
        load_encoder_weights(not_dict)
    assert issubclass(ModelError, UsvcError)


def test_safetensors_without_package_is_clear(tmp_path: Path) -> None:
    path = tmp_path / "enc.safetensors"
    path.write_bytes(b"\0" * 16)
    try:
        import safetensors  # noqa: F401
    except ImportError:
        with pytest.raises(ModelError, match="safetensors"):
            load_encoder_weights(path)
    else:
        with pytest.raises(ModelError, match="cannot read"):
            load_encoder_weights(path)


def test_pickled_code_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "evil.pt"
    torch.save({"conv1.weight": Path("/")}, path)  # arbitrary object, not a tensor
    with pytest.raises(ModelError, match="refused as encoder weights: it holds Python objects") as info:
        load_encoder_weights(path)
    assert "weights_only" not in str(info.value) and "False" not in str(info.value)


@pytest.mark.parametrize("content", [b"not a torch file at all", bytes(range(256)) * 20, b"PK\x03\x04broken zip"])
def test_unreadable_files_never_relay_torchs_unsafe_advice(tmp_path: Path, content: bytes) -> None:
    """Torch's own text suggests `weights_only=False`; our one line says what is wrong instead."""
    from usvc.model.map_file import read_map_header

    path = tmp_path / "random.pt"
    path.write_bytes(content)
    for load, what in ((load_encoder_weights, "encoder weights"), (read_map_header, "map")):
        with pytest.raises(ModelError, match=f"random.pt: cannot read {what}") as info:
            load(path)
        assert "weights_only" not in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(("h", "w"), [(480, 640), (241, 321)])
def test_output_shape(encoder: Encoder, h: int, w: int) -> None:
    with torch.no_grad():
        out = encoder(torch.zeros(1, 1, h, w))
    assert tuple(out.shape) == (1, 512, math.ceil(h / 8), math.ceil(w / 8))


def test_small_variant() -> None:
    enc = Encoder(width=0.5)
    assert enc.out_channels == 256
    assert enc.conv1.in_channels == 1 and enc.conv1.out_channels == 16
    assert all(m.out_channels % 8 == 0 for m in enc.modules() if isinstance(m, torch.nn.Conv2d))
    with torch.no_grad():
        assert tuple(enc(torch.zeros(1, 1, 64, 96)).shape) == (1, 256, 8, 12)


def test_flops() -> None:
    assert encoder_flops(480, 640) == pytest.approx(58e9, rel=0.03)
    assert encoder_flops(240, 320) == pytest.approx(14.6e9, rel=0.03)
    assert encoder_flops(480, 640, 0.5) == pytest.approx(encoder_flops(480, 640) / 4, rel=0.05)


def test_cell_centers() -> None:
    c = cell_centers(3, 4)
    assert c.shape == (2, 3, 4) and c.dtype == torch.float32
    assert c[:, 2, 1].tolist() == [8 * 1 + 4.5, 8 * 2 + 4.5]  # (x, y) of cell (i=2, j=1)
    assert torch.equal(cell_centers(3, 4, "opencv") + 0.5, c)


def test_preprocess() -> None:
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)
    rgb[0, 1] = (0, 255, 0)
    rgb[1, 2] = (255, 255, 255)
    x = normalise(luma01(rgb, rgb=True))
    assert x.shape == (1, 1, 2, 3) and x.dtype == torch.float32
    assert x[0, 0, 0, 0].item() == pytest.approx((0.299 - 0.4) / 0.25, abs=1e-6)
    assert x[0, 0, 0, 1].item() == pytest.approx((0.587 - 0.4) / 0.25, abs=1e-6)
    assert x[0, 0, 1, 2].item() == pytest.approx((1.0 - 0.4) / 0.25, abs=1e-5)
    assert x[0, 0, 1, 0].item() == pytest.approx(-1.6)
    assert torch.allclose(normalise(luma01(rgb[..., ::-1].copy(), rgb=False)), x)

    img = np.zeros((960, 1280, 3), np.uint8)
    small, scale = resize_to_short_side(img)
    assert small.shape == (480, 640, 3) and scale == 0.5
    tall, scale = resize_to_short_side(np.zeros((500, 333), np.uint8), 240)
    assert tall.shape == (360, 240) and scale == pytest.approx(240 / 333)


def test_homogeneous_scale() -> None:
    assert homogeneous_scale(torch.zeros(1)).item() == pytest.approx(1.0, abs=1e-6)
    assert homogeneous_scale(torch.tensor([-1e4])).item() == pytest.approx(0.25)
    assert homogeneous_scale(torch.tensor([1e4])).item() == pytest.approx(100.0)
    assert homogeneous_scale(torch.linspace(-50, 500, 101)).min() > 0.25 - 1e-6


def test_head_zero_output_is_scene_center() -> None:
    head = Head()
    head.set_scene_center([1.5, -2.0, 1000.25])
    torch.nn.init.zeros_(head.out.weight)
    torch.nn.init.zeros_(head.out.bias)
    with torch.no_grad():
        head.out.bias[:3] = torch.tensor([1.0, 2.0, 3.0])
        out = head(torch.randn(2, 512, 3, 4))
    assert out.shape == (2, 3, 3, 4) and out.dtype == torch.float32
    expected = torch.tensor([2.5, 0.0, 1003.25]).view(1, 3, 1, 1).expand_as(out)
    assert torch.allclose(out, expected)  # h = 1 at o3 = 0


def test_head_size_and_projection() -> None:
    n = sum(p.numel() for p in Head().parameters())
    assert abs(n - 2.1e6) / 2.1e6 < 0.02
    narrow = Head(in_channels=256)
    with torch.no_grad():
        assert narrow(torch.randn(1, 256, 2, 2)).shape == (1, 3, 2, 2)
    assert Head(homogeneous=False).out.out_channels == 3


def test_head_half_keeps_fp32_center() -> None:
    torch.manual_seed(0)
    head = Head()
    center = [123.456789, -98.7654321, 50.0001]
    head.set_scene_center(center)
    head.half()
    assert head.fc1.weight.dtype == torch.float16
    assert head.scene_center.dtype == torch.float32
    assert head.scene_center.flatten().tolist() == torch.tensor(center).tolist()
    head.float()
    assert head.scene_center.dtype == torch.float32
    head.half()
    with torch.no_grad():
        try:
            out = head(torch.randn(1, 512, 2, 2))
        except RuntimeError as exc:  # some CPU builds lack fp16 convolution
            pytest.skip(f"no fp16 conv on this CPU: {exc}")
    assert out.dtype == torch.float32


def small_regressor(encoder: Encoder) -> Regressor:
    torch.manual_seed(3)
    head = Head(in_channels=encoder.out_channels)
    head.set_scene_center([10.0, 20.0, -5.0])
    return Regressor(encoder, head).eval()


def test_map_round_trip(tmp_path: Path, small_encoder: Encoder) -> None:
    reg = small_regressor(small_encoder)
    path = tmp_path / "scene.map.pt"
    meta = {"scene": "chess", "frames": 1000, "mean_error": 1.5, "tags": ["a", "b"]}
    save_map(path, reg, meta)
    assert path.stat().st_size < 5e6
    loaded, got_meta = load_map(path, small_encoder)
    assert got_meta == meta
    assert loaded.head.scene_center.tolist() == reg.head.scene_center.tolist()
    image = torch.randn(1, 1, 32, 48)
    with torch.no_grad():
        features = small_encoder(image)
        want = reg.head(features)
        got = loaded(image)
        assert torch.allclose(got, want, rtol=1e-2, atol=1e-2)
        for p in reg.head.parameters():  # same weights rounded to fp16: identical outputs
            p.copy_(p.half().float())
        assert torch.equal(reg.head(features), loaded.head(features))


def test_map_rejects_other_encoder(tmp_path: Path, small_encoder: Encoder) -> None:
    path = tmp_path / "scene.map.pt"
    save_map(path, small_regressor(small_encoder), {})
    torch.manual_seed(99)
    with pytest.raises(ModelError, match="another encoder"):
        load_map(path, Encoder(width=0.5))


def test_map_fingerprint_survives_half(encoder: Encoder) -> None:
    copy = Encoder()
    copy.load_state_dict(encoder.state_dict())
    assert encoder_fingerprint(copy.half()) == encoder_fingerprint(encoder)


def test_map_bad_files(tmp_path: Path, small_encoder: Encoder) -> None:
    with pytest.raises(ModelError, match="does not exist"):
        load_map(tmp_path / "none.pt", small_encoder)
    path = tmp_path / "scene.map.pt"
    save_map(path, small_regressor(small_encoder), {})
    data = path.read_bytes()
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelError, match="truncated.pt: cannot read map"):
        load_map(truncated, small_encoder)
    other = tmp_path / "other.pt"
    torch.save({"format": "something"}, other)
    with pytest.raises(ModelError, match="not a usvc map"):
        load_map(other, small_encoder)
    with pytest.raises(ModelError, match="plain types"):
        save_map(tmp_path / "x.pt", small_regressor(small_encoder), {"path": Path("/")})


def test_torch_load_always_weights_only() -> None:
    calls = 0
    for source in MODEL_DIR.parent.rglob("*.py"):  # the whole usvc package
        text = source.read_text()
        for match in re.finditer(r"torch\.load\(", text):
            depth, end = 1, match.end()
            while depth:
                depth += {"(": 1, ")": -1}.get(text[end], 0)
                end += 1
            call = text[match.start() : end]
            assert "weights_only=True" in call, f"{source}: {call}"
            calls += 1
    assert calls >= 1  # usvc/model/safe_load.py: every reader goes through it
