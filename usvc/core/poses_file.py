"""poses.txt: one world-to-camera pose per localized query, `name qw qx qy qz tx ty tz` a line
(OpenCV axes, Hamilton unit quaternion), under a `#` header line.

A name is written as it is (spaces inside it included: the name is everything before the last
seven fields), unless a reader would take it for something else: a name that starts with `#` or
`"`, starts or ends with white space, or holds a line break is written as a JSON string
(`"#0012.jpg" 1.0 0.0 ...`)."""

from __future__ import annotations

import json

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
        if not name:
            raise UsvcError(f"{path}: a query has an empty name")
        if not (np.all(np.isfinite(Ri)) and np.all(np.isfinite(ti))):
            raise UsvcError(f"{path}: pose of {name!r} is not finite")
        values = np.concatenate([matrix_to_quat_wxyz(Ri), ti])
        lines.append(" ".join([_written_name(name), *(repr(float(v)) for v in values)]))
    with atomic_file(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _written_name(name: str) -> str:
    """The name as a line holds it: as it is, or as a JSON string where a reader would misread it."""
    plain = name == name.strip() and not name.startswith(("#", '"')) and len(name.splitlines()) == 1 \
        and name.splitlines()[0] == name
    return name if plain else json.dumps(name)  # ASCII: no character a line reader splits at


def _split_line(line: str) -> tuple[str, list[str]] | None:
    """(name, the seven value fields) of a pose line, or None when it does not have that shape."""
    if line.startswith('"'):
        try:
            name, end = json.JSONDecoder().raw_decode(line)
        except json.JSONDecodeError:
            return None
        fields = line[end:].split()
        return (name, fields) if isinstance(name, str) and len(fields) == 7 and line[end:end + 1].isspace() else None
    fields = line.rsplit(maxsplit=7)
    return (fields[0], fields[1:]) if len(fields) == 8 else None


def read_poses_txt(path: Path | str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a poses file into {name: (R, t)}; '#' lines and blank lines are skipped.

    The name is everything before the last seven fields, so names may contain spaces.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise UsvcError(f"{path}: cannot read poses file ({e.strerror or e})") from e
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        split = _split_line(line)
        if split is None:
            raise UsvcError(f"{where}: expected 'name qw qx qy qz tx ty tz', got {line!r}")
        name, fields = split
        try:
            values = np.array([float(v) for v in fields])
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
