"""`usvc localize` as a user runs it: JSON on stdout, or exactly one error line and exit 1.

The map is real but untrained, so its poses are garbage; these tests check the interface, and
tests/test_relocalizer.py checks that the poses are right.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from usvc.model.encoder import Encoder
from usvc.model.head import Head, Regressor, save_map

REPO = Path(__file__).resolve().parents[1]
KEYS = {"name", "success", "inliers", "cells", "confidence", "seconds"}


def usvc(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "usvc.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def make_map(folder: Path, seed: int) -> tuple[Path, Path]:
    torch.manual_seed(seed)
    encoder = Encoder(width=0.25)
    weights = folder / f"encoder{seed}.pt"
    torch.save(encoder.state_dict(), weights)
    map_path = folder / f"scene{seed}.map.pt"
    # A map as the train stage writes it, with 3D keypoints for query-time refinement (a map
    # without them still works, with one warning on stderr).
    keypoints = np.random.default_rng(seed).uniform(-1.0, 1.0, (50, 3)) + [0.0, 0.0, 3.0]
    save_map(map_path, Regressor(encoder, Head(in_channels=encoder.out_channels, width=64)),
             {"short_side": 120}, keypoints_xyz=keypoints)
    return map_path, weights


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("cli")
    map_path, weights = make_map(folder, 0)
    _, other_weights = make_map(folder, 1)
    photo = folder / "photo.png"
    cv2.imwrite(str(photo), np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8))
    garbage = folder / "garbage.jpg"
    garbage.write_bytes(b"not a jpeg at all")
    truncated = folder / "truncated.map.pt"
    truncated.write_bytes(map_path.read_bytes()[:2000])
    return {"map": map_path, "weights": weights, "other_weights": other_weights, "photo": photo,
            "garbage": garbage, "truncated": truncated, "missing_photo": folder / "nope.jpg",
            "missing_map": folder / "missing.map.pt"}


def test_localize_prints_json(files: dict[str, Path]) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"],
                "--focal", "130", files["photo"], files["photo"])
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 2
    for line in lines:
        record = json.loads(line)
        assert KEYS <= set(record)
        assert record["name"] == str(files["photo"]) and record["cells"] == 300
        assert 0.0 <= record["confidence"] <= 1.0
    assert proc.stderr == ""


def test_localize_json_list(files: dict[str, Path]) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], "--json-list",
                "--intrinsics", "130", "125", "81", "59", "--backend", "pycolmap", "--max-error-px", "5",
                files["photo"])
    assert proc.returncode == 0, proc.stderr
    records = json.loads(proc.stdout)
    assert isinstance(records, list) and len(records) == 1 and KEYS <= set(records[0])


def test_localize_without_refinement(files: dict[str, Path]) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], "--no-refine",
                "--focal", "130", files["photo"])
    assert proc.returncode == 0, proc.stderr
    record = json.loads(proc.stdout)
    assert record.get("refinement", {"iterations": 0})["iterations"] == 0


@pytest.mark.parametrize("extra, photo, cause", [
    ([], "photo", "intrinsics are missing"),
    (["--intrinsics", "260", "250", "162", "118"], "photo", "outside the 160x120 image"),
    (["--focal", "130"], "missing_photo", "image not found"),
    (["--focal", "130"], "garbage", "cannot decode image"),
    (["--focal", "130", "--encoder-weights", "{other_weights}"], "photo", "another encoder"),
    (["--focal", "130", "--map", "{truncated}"], "photo", "corrupt or truncated"),
    (["--focal", "130", "--map", "{missing_map}"], "photo", "map file does not exist"),
], ids=["no-intrinsics", "wrong-size", "missing-photo", "undecodable", "other-encoder", "truncated-map",
        "missing-map"])
def test_localize_errors(files: dict[str, Path], extra: list[str], photo: str, cause: str) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"],
                *(arg.format(**files) for arg in extra), files[photo])
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("usvc localize: error: ") and cause in lines[0]
    assert proc.stdout == ""
