"""One spelling per pose quantity: world-to-camera is `R_world_to_cam`/`t_world_to_cam` (as the
file formats spell it), camera-to-world is `cam_to_world` (a 4x4) or `R_cam_to_world` (its
rotation). The retired spellings (`R_w2c`, `view_R`, `c2w`, ...) must not come back: a silent
direction slip is the costliest bug geometry code has."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("usvc", "stages", "benchmarks", "scripts", "tests", "tools")
RETIRED = ("R_w2c", "t_w2c", "view_R", "view_t", "c2w", "w2c", "R_c2w", "t_c2w")
# Whole words; `c2w`/`w2c` also as a part of a snake_case name (`c2w_matrix`, `nerf_w2c`), so a
# function or variable built on the retired abbreviation is caught too.
RETIRED_RE = re.compile(
    r"\b(?:R_w2c|t_w2c|view_R|view_t|R_c2w|t_c2w)\b|(?<![A-Za-z0-9])(?:c2w|w2c)(?![A-Za-z0-9])"
)


def retired_spellings(text: str) -> list[tuple[int, str]]:
    """(line number, spelling) of every retired pose spelling in `text`."""
    return [(i, m.group(0)) for i, line in enumerate(text.splitlines(), 1) for m in RETIRED_RE.finditer(line)]


def test_the_scanner_finds_each_retired_spelling():
    for name in RETIRED:
        assert retired_spellings(f"x = {name}\n") == [(1, name)], name
    sample = "ok = R_world_to_cam\nT = c2w_matrix(gt)  # cam_to_world\nbuf.view_R[v], buf.view_t\n"
    assert retired_spellings(sample) == [(2, "c2w"), (3, "view_R"), (3, "view_t")]


def test_the_scanner_leaves_the_kept_spellings_alone():
    kept = ("R_world_to_cam t_world_to_cam cam_to_world R_cam_to_world view_R_world_to_cam view_t_world_to_cam "
            "view_K views/R_world_to_cam initial_R R t")
    assert retired_spellings(kept) == []


def test_no_retired_pose_spelling_comes_back():
    this = Path(__file__).resolve()
    found = [
        f"{path.relative_to(ROOT)}:{line}: {name}"
        for folder in SCANNED
        for path in sorted((ROOT / folder).rglob("*.py"))
        if path.resolve() != this
        for line, name in retired_spellings(path.read_text(encoding="utf-8"))
    ]
    assert not found, ("retired pose spellings (world-to-camera is R_world_to_cam/t_world_to_cam, "
                       "camera-to-world cam_to_world/R_cam_to_world):\n" + "\n".join(found))
