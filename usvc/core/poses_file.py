"""poses.txt: one world-to-camera pose per localized query, `name qw qx qy qz tx ty tz` a line
(OpenCV axes, Hamilton unit quaternion), under a `#` header line."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from usvc.core.atomic import atomic_file
from usvc.core.errors import UsvcError
from usvc.core.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix

POSES_HEADER = "# name qw qx qy qz tx ty tz  (world-to-camera, OpenCV axes, Hamilton quaternion)"


def write_poses_txt(path: Path | str, names: Sequence[str], R: np.ndarray, t: np.ndarray) -> None:
    """Write world-to-camera poses, one `name qw qx qy qz tx ty tz` line per query."""
    path = Path(path)
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    if not (len(names) == len(R) == len(t)):
        raise UsvcError(f"{path}: {len(names)} names, {len(R)} rotations and {len(t)} translations")
    lines = [POSES_HEADER]
    for name, Ri, ti in zip(names, R, t):
        if not name or name != name.strip() or "\n" in name or "\r" in name or name.startswith("#"):
            raise UsvcError(f"{path}: query name {name!r} cannot be written on one line")
        if not (np.all(np.isfinite(Ri)) and np.all(np.isfinite(ti))):
            raise UsvcError(f"{path}: pose of {name!r} is not finite")
        values = np.concatenate([matrix_to_quat_wxyz(Ri), ti])
        lines.append(" ".join([name, *(repr(float(v)) for v in values)]))
    with atomic_file(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def read_poses_txt(path: Path | str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a poses file into {name: (R, t)}; '#' lines and blank lines are skipped.

    The name is everything before the last seven fields, so names may contain spaces.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise UsvcError(f"{path}: cannot read poses file ({e.strerror or e})") from e
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        fields = line.rsplit(maxsplit=7)
        if len(fields) != 8:
            raise UsvcError(f"{where}: expected 'name qw qx qy qz tx ty tz', got {line!r}")
        name = fields[0]
        try:
            values = np.array([float(v) for v in fields[1:]])
        except ValueError:
            raise UsvcError(f"{where}: non-numeric pose value in {line!r}") from None
        if not np.all(np.isfinite(values)):
            raise UsvcError(f"{where}: pose of {name!r} is not finite")
        if name in poses:
            raise UsvcError(f"{where}: duplicate query name {name!r}")
        try:
            R = quat_wxyz_to_matrix(values[:4])
        except ValueError:
            raise UsvcError(f"{where}: quaternion of {name!r} has zero norm") from None
        poses[name] = (R, values[4:].copy())
    return poses
