import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from usvc.core.errors import UsvcError
from usvc.splat import ply_file
from usvc.splat.gaussians import Gaussians
from usvc.splat.ply_file import read_splat_ply, splat_property_names, write_splat_ply

N = 7


def random_gaussians(degree: int, n: int = N, seed: int = 0) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return Gaussians(
        means=torch.randn(n, 3, generator=gen) * 5,
        log_scales=torch.randn(n, 3, generator=gen) - 3,
        quats=torch.randn(n, 4, generator=gen) * 2,  # deliberately unnormalised
        opacity_logits=torch.randn(n, generator=gen) * 3,
        sh_dc=torch.randn(n, 3, generator=gen),
        sh_rest=torch.randn(n, k, 3, generator=gen),
    )


def expected_names(degree: int) -> list[str]:
    m = 3 * ((degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(m)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_bit_exact(tmp_path, degree):
    g = random_gaussians(degree, seed=degree)
    path = tmp_path / "s.ply"
    write_splat_ply(path, g)
    back = read_splat_ply(path)
    assert back.sh_degree == degree
    for name, t in g.tensors().items():
        b = getattr(back, name)
        assert b.dtype == torch.float32 and b.device.type == "cpu", name
        assert b.shape == t.shape, name
        assert torch.equal(b, t), name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]  # no temp file left


def test_layout_matches_reference(tmp_path):
    degree, k = 3, 15
    g = random_gaussians(degree)
    # every f_rest entry encodes (point, coefficient, channel), so any permutation shows up
    idx = torch.arange(N)[:, None, None] * 1000 + torch.arange(k)[None, :, None] * 10 + torch.arange(3)
    g.sh_rest = idx.float() + 0.5
    path = tmp_path / "s.ply"
    write_splat_ply(path, g)

    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    assert v.count == N
    assert [p.name for p in v.properties] == expected_names(degree) == splat_property_names(degree)
    assert all(v.data.dtype[p.name] == np.dtype("<f4") for p in v.properties)
    col = {p.name: torch.from_numpy(np.asarray(v[p.name]).astype(np.float32)) for p in v.properties}

    assert torch.equal(torch.stack([col[c] for c in "xyz"], 1), g.means)
    for c in ("nx", "ny", "nz"):
        assert torch.all(col[c] == 0)
    assert torch.equal(col["opacity"], g.opacity_logits)
    assert torch.allclose(torch.sigmoid(col["opacity"]), g.opacities)
    scales = torch.stack([col[f"scale_{i}"] for i in range(3)], 1)
    assert torch.equal(scales, g.log_scales)
    assert torch.allclose(torch.exp(scales), g.scales)
    rot = torch.stack([col[f"rot_{i}"] for i in range(4)], 1)
    assert torch.equal(rot, g.quats)  # wxyz, stored raw
    assert torch.allclose(torch.nn.functional.normalize(rot, dim=-1), g.rotations)
    f_dc = torch.stack([col[f"f_dc_{i}"] for i in range(3)], 1)
    assert torch.equal(f_dc, g.sh_dc)
    for j in range(3 * k):  # channel-major: f_rest_j is channel j // k, coefficient j % k
        assert torch.equal(col[f"f_rest_{j}"], g.sh_rest[:, j % k, j // k]), j
    assert torch.equal(col["f_rest_1"], torch.arange(N) * 1000 + 10 + 0.5)  # R, coefficient 2
    assert torch.equal(col[f"f_rest_{k}"], torch.arange(N) * 1000 + 1 + 0.5)  # G, coefficient 1


def write_raw(path, columns: dict[str, np.ndarray], dtype: str = "<f4") -> None:
    n = len(next(iter(columns.values())))
    arr = np.empty(n, dtype=[(name, dtype) for name in columns])
    for name, values in columns.items():
        arr[name] = values
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(path))


def raw_columns(g: Gaussians) -> dict[str, np.ndarray]:
    cols = {}
    k = g.sh_rest.shape[1]
    for i, c in enumerate("xyz"):
        cols[c] = g.means[:, i].numpy()
    for i in range(3):
        cols[f"f_dc_{i}"] = g.sh_dc[:, i].numpy()
        cols[f"scale_{i}"] = g.log_scales[:, i].numpy()
    for j in range(3 * k):
        cols[f"f_rest_{j}"] = g.sh_rest[:, j % k, j // k].numpy()
    cols["opacity"] = g.opacity_logits.numpy()
    for i in range(4):
        cols[f"rot_{i}"] = g.quats[:, i].numpy()
    return cols


def test_reads_other_property_order_and_extras(tmp_path):
    g = random_gaussians(1)
    cols = raw_columns(g)
    names = list(cols)[::-1]  # reversed order, no normals, plus an extra property
    shuffled = {name: cols[name] for name in names} | {"red": np.zeros(N)}
    path = tmp_path / "other.ply"
    write_raw(path, shuffled)
    back = read_splat_ply(path)
    for name, t in g.tensors().items():
        assert torch.equal(getattr(back, name), t), name


def test_missing_property(tmp_path):
    cols = raw_columns(random_gaussians(0))
    del cols["scale_1"]
    path = tmp_path / "noscale.ply"
    write_raw(path, cols)
    with pytest.raises(UsvcError, match="scale_1") as e:
        read_splat_ply(path)
    assert "noscale.ply" in str(e.value)


def test_bad_f_rest_count(tmp_path):
    cols = raw_columns(random_gaussians(1))
    del cols["f_rest_8"]
    path = tmp_path / "rest.ply"
    write_raw(path, cols)
    with pytest.raises(UsvcError, match="8 f_rest") as e:
        read_splat_ply(path)
    assert "rest.ply" in str(e.value)


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.ply"
    with pytest.raises(UsvcError, match="nowhere.ply"):
        read_splat_ply(path)


def test_inconsistent_gaussians_leave_no_file(tmp_path):
    g = random_gaussians(2)
    g.opacity_logits = torch.zeros(N + 1)
    path = tmp_path / "bad.ply"
    with pytest.raises(UsvcError, match="opacity_logits"):
        write_splat_ply(path, g)
    assert list(tmp_path.iterdir()) == []


def test_failure_mid_write_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "s.ply"
    write_splat_ply(path, random_gaussians(0))
    before = path.read_bytes()

    def half_write(self, stream):
        with open(stream, "wb") as f:
            f.write(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError("disk full")

    monkeypatch.setattr(ply_file.PlyData, "write", half_write)
    with pytest.raises(UsvcError, match="disk full"):
        write_splat_ply(path, random_gaussians(3))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]
