"""Gaussian splats as PLY in the layout of the reference 3DGS `save_ply`, which is what splat
viewers and other 3DGS tools read, so our scenes open elsewhere and theirs open here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from usvc.core.atomic import atomic_file
from usvc.core.errors import UsvcError
from usvc.splat.gaussians import Gaussians

# number of f_rest_* properties -> SH degree; (d+1)^2 - 1 coefficients per channel, 3 channels
_REST_COUNT_TO_DEGREE = {3 * ((d + 1) ** 2 - 1): d for d in range(4)}


def splat_property_names(sh_degree: int) -> list[str]:
    """Property names in the order the reference writes them."""
    m = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(m)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _columns(g: Gaussians) -> np.ndarray:
    """(N, P) float32 columns in `splat_property_names` order, after checking shapes agree."""
    t = {k: v.detach().to("cpu", torch.float32) for k, v in g.tensors().items()}
    n = t["means"].shape[0] if t["means"].ndim == 2 else -1
    k = t["sh_rest"].shape[1] if t["sh_rest"].ndim == 3 else -1
    expected = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,),
                "sh_dc": (n, 3), "sh_rest": (n, k, 3)}
    for name, shape in expected.items():
        if n < 0 or tuple(t[name].shape) != shape:
            raise UsvcError(f"cannot write Gaussians: {name} has shape {tuple(t[name].shape)}, "
                            f"expected {shape} (means {tuple(t['means'].shape)})")
    if 3 * k not in _REST_COUNT_TO_DEGREE:
        raise UsvcError(f"cannot write Gaussians: sh_rest has {k} coefficients per channel, "
                        "expected 0, 3, 8 or 15 (SH degree 0..3)")
    # The reference keeps features_rest as (N, K, 3) and writes it transposed to (N, 3, K) then
    # flattened: f_rest is channel-major (all of R's coefficients, then G's, then B's). Writing
    # it coefficient-major would load without error elsewhere but with scrambled view colours.
    rest = t["sh_rest"].transpose(1, 2).reshape(n, 3 * k)
    return torch.cat([t["means"], torch.zeros(n, 3), t["sh_dc"], rest, t["opacity_logits"][:, None],
                      t["log_scales"], t["quats"]], dim=1).numpy()


def write_splat_ply(path: Path, g: Gaussians) -> None:
    """Binary little-endian, raw (pre-activation) parameters as the reference stores them: the
    logit for opacity, log scales, unnormalised wxyz quaternions and zero normals."""
    path = Path(path)
    cols = _columns(g)
    names = splat_property_names(g.sh_degree)
    vertex = np.empty(cols.shape[0], dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertex[name] = cols[:, i]
    try:
        with atomic_file(path) as tmp:
            PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(str(tmp))
    except OSError as e:
        raise UsvcError(f"cannot write splat PLY {path}: {e}") from e


def read_splat_ply(path: Path) -> Gaussians:
    """Properties are looked up by name, so files from other tools with another property order
    (or extra properties) load as well; values come back as CPU float32."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"splat PLY not found: {path}")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises its own parse errors, plus ValueError/OSError
        raise UsvcError(f"cannot read splat PLY {path}: {e}") from e
    if "vertex" not in ply:
        raise UsvcError(f"splat PLY {path} has no 'vertex' element")
    vertex = ply["vertex"]
    present = {p.name for p in vertex.properties}
    n_rest = sum(1 for name in present if name.startswith("f_rest_"))
    if n_rest not in _REST_COUNT_TO_DEGREE:
        raise UsvcError(f"splat PLY {path} has {n_rest} f_rest_* properties, "
                        f"expected one of {sorted(_REST_COUNT_TO_DEGREE)} (SH degree 0..3)")

    def col(*names: str) -> torch.Tensor:
        for name in names:
            if name not in present:
                raise UsvcError(f"splat PLY {path} lacks required property '{name}'")
        arrays = [np.asarray(vertex[name], dtype=np.float32) for name in names]
        if not arrays:
            return torch.zeros(vertex.count, 0)
        return torch.from_numpy(np.stack(arrays, axis=1))

    k = n_rest // 3
    rest = col(*(f"f_rest_{i}" for i in range(n_rest)))
    return Gaussians(
        means=col("x", "y", "z"),
        log_scales=col("scale_0", "scale_1", "scale_2"),
        quats=col("rot_0", "rot_1", "rot_2", "rot_3"),
        opacity_logits=col("opacity")[:, 0].contiguous(),
        sh_dc=col("f_dc_0", "f_dc_1", "f_dc_2"),
        sh_rest=rest.reshape(vertex.count, 3, k).transpose(1, 2).contiguous(),  # channel-major, see _columns
    )
