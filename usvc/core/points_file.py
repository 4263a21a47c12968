"""Point clouds as binary PLY (xyz + rgb + optional scalar fields) for any viewer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, **scalars: np.ndarray) -> None:
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    fields += [(name, "f4") for name in scalars]
    data = np.empty(len(xyz), dtype=fields)
    data["x"], data["y"], data["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    for name, values in scalars.items():
        data[name] = values
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
