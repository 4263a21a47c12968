from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_scene(name: str) -> Path:
    path = SHARED / "scenes" / name
    if not path.is_dir():
        pytest.skip(f"{path} is not present (CI has ../shared)")
    return path
