"""XFeat's backbone as a frozen encoder: same cell grid as the ACE-layout encoder, maps that name it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from usvc.model.encoder import feature_size
from usvc.model.errors import ModelError
from usvc.model.head import Head, Regressor
from usvc.model.map_file import load_map, read_map_header, save_map
from usvc.model.xfeat_encoder import (
    FEATURE_DIM,
    load_xfeat_encoder,
    shipped_xfeat_weights,
)
from usvc.weights import load_configured_encoder


@pytest.fixture(scope="module")
def xfeat():
    return load_xfeat_encoder()


@pytest.mark.parametrize("h,w", [(64, 96), (45, 83), (360, 640), (33, 31)])
def test_xfeat_gives_unit_features_on_the_ace_cell_grid(xfeat, h: int, w: int) -> None:
    with torch.no_grad():
        out = xfeat(torch.rand(1, 1, h, w))
    assert out.shape == (1, FEATURE_DIM, *feature_size(h, w))
    assert torch.allclose(out.norm(dim=1), torch.ones(()), atol=1e-4)


def test_xfeat_features_follow_the_image_content(xfeat) -> None:
    """A shifted image gives shifted features (8 px = one cell) away from the borders."""
    torch.manual_seed(0)
    image = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 136, 168), 3, 1, 1)
    with torch.no_grad():
        a = xfeat(image[..., :, :128 + 32])
        b = xfeat(image[..., :, 8:128 + 40])
    inner_a, inner_b = a[..., 4:-4, 5:-4], b[..., 4:-4, 4:-5]
    cos = (inner_a * inner_b).sum(dim=1)
    assert cos.median() > 0.9
    unrelated = (a[..., 4:-4, 5:-4] * a[..., 4:-4, 4:-5]).sum(dim=1)  # the neighbouring cell
    assert cos.median() > unrelated.median() + 0.1


def test_xfeat_map_round_trip_names_its_encoder(tmp_path: Path, xfeat) -> None:
    head = Head(in_channels=FEATURE_DIM, width=32, num_blocks=1)
    path = tmp_path / "map.pt"
    save_map(path, Regressor(xfeat, head), {"scene": "x"})
    assert read_map_header(path)["encoder"]["kind"] == "xfeat"
    encoder, weights = load_configured_encoder(1.0, None, "xfeat")
    assert weights == shipped_xfeat_weights()
    regressor, meta = load_map(path, encoder)
    assert meta == {"scene": "x"}
    with torch.no_grad():
        assert regressor(torch.rand(1, 1, 48, 64)).shape == (1, 3, 6, 8)
    ace, _ = load_configured_encoder(0.5, None, "ace")
    with pytest.raises(ModelError, match="another encoder"):
        load_map(path, ace)


def test_xfeat_weights_must_be_a_plain_state_dict(tmp_path: Path) -> None:
    bad = tmp_path / "bad.pt"
    torch.save({"conv.weight": torch.zeros(1)}, bad)
    with pytest.raises(ModelError, match="XFeat weights keys do not match"):
        load_xfeat_encoder(bad)
    with pytest.raises(ModelError, match="does not exist"):
        load_xfeat_encoder(tmp_path / "missing.pt")
