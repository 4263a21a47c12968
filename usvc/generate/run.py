"""The generate step: render the miniature synthetic scene (ACE layout, metres) into a folder."""

from __future__ import annotations

from pathlib import Path

from usvc.generate.params import RoomParams
from usvc.generate.writer import generate_scene


def run(out: Path, options: RoomParams) -> dict:
    """Render the scene of `options` into `out` (replaced whole, never left half-written); returns
    the frames per split."""
    return generate_scene(out, options)
