"""Bad input to `usvc localize`, the Relocalizer API and map files: one clear line naming what is
wrong and where (exit 1 from the CLI, never a traceback); in a batch, a bad photo is its own
failure and the others go on; every failed answer says why.

The map is tiny and untrained; where a pose matters, the network is replaced by the exact scene
coordinates of a known camera (as in tests/test_relocalizer.py).
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image
from test_relocalizer import SHORT_SIDE, exact_coordinates, make_map, photo

from usvc.cli import main
from usvc.cli.exports import FORMATS
from usvc.core.errors import UsvcError
from usvc.core.scene import Camera
from usvc.model.encoder import Encoder
from usvc.model.head import Head, Regressor
from usvc.model.map_file import save_map
from usvc.relocalize.camera_checks import implausible_focal, intrinsics_warnings, stretch_verdict
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.query_input import camera_from_intrinsics
from usvc.relocalize.relocalizer import Relocalizer

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both

CENTRED = Camera("SIMPLE_PINHOLE", 160, 120, (130.0, 80.0, 60.0))


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return make_map(tmp_path_factory.mktemp("badmap"))


@pytest.fixture(scope="module")
def photo_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("photos") / "photo.png"
    cv2.imwrite(str(path), photo(160, 120))
    return path


def exactly(monkeypatch: pytest.MonkeyPatch, camera: Camera = CENTRED) -> None:
    """The network replaced by the exact coordinates `camera` (at 160x120) sees."""
    monkeypatch.setattr(Relocalizer, "scene_coordinates",
                        lambda self, g: exact_coordinates(-(-g.shape[0] // 8), -(-g.shape[1] // 8), camera))


def run(capsys: pytest.CaptureFixture[str], tiny_map: tuple[Path, Path], *args: str | Path) -> tuple[int, str, str]:
    """`usvc localize --map M --encoder-weights W ARGS` in this process: (status, stdout, stderr)."""
    rc = main(["localize", "--map", str(tiny_map[0]), "--encoder-weights", str(tiny_map[1]), *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err


def one_error_line(rc: int, out: str, err: str) -> str:
    assert rc == 1, (out, err)
    assert out == "" and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("usvc localize: error: ")
    return lines[0]


def records_of(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines()]


def test_a_huge_inlier_threshold_is_refused(tiny_map: tuple[Path, Path], photo_file: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    problems = RelocalizeOptions(max_error_px=1e9).problems()
    assert problems == ["max_error_px=1000000000.0 must be <= 100 (px at a 480 px short side; larger thresholds "
                        "accept any pose)"]
    assert RelocalizeOptions(max_error_px=100.0).problems() == []
    assert RelocalizeOptions(features_max_error_px=float("inf")).problems()
    with pytest.raises(UsvcError, match=r"max_error_px=1000000000.0 must be <= 100"):
        Relocalizer(*tiny_map, options=RelocalizeOptions(max_error_px=1e9))
    line = one_error_line(*run(capsys, tiny_map, "--max-error-px", "1e9", "--focal", "130", photo_file))
    assert r"--max-error-px 1e+09: must be in (0, 100]" in line


# ------------------------------------------------------------------ 4. stretched photos

def test_a_stretched_photo_without_intrinsics_is_refused(tiny_map: tuple[Path, Path],
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A 4:3 photo squeezed to 3:4 and back: its content is a camera with fx/fy = 1.6."""
    stretched = Camera("PINHOLE", 160, 120, (160.0, 100.0, 80.0, 60.0))
    exactly(monkeypatch, stretched)
    est = Relocalizer(*tiny_map).localize(photo(160, 120), None)
    assert not est.success and "looks stretched" in est.rejected and "fx/fy = 1.6" in est.rejected
    assert est.to_json()["rejected"] == est.rejected
    exactly(monkeypatch, CENTRED)  # the same scene seen with square pixels: no false alarm
    assert Relocalizer(*tiny_map).localize(photo(160, 120), None).success


def test_stretch_verdict_needs_clearly_more_support() -> None:
    """The check itself: nothing to say where a square-pixel camera explains the cells."""
    points = exact_coordinates(15, 20, CENTRED).reshape(-1, 3)
    from usvc.model.encoder import cell_centers
    from usvc.core.absolute_pose import estimate_focal_pose

    pixels = cell_centers(15, 20, "colmap").permute(1, 2, 0).reshape(-1, 2).double().numpy()
    found = estimate_focal_pose(pixels, points, 160, 120, 2.5)
    assert found is not None
    assert stretch_verdict(pixels, points, found.camera, found.R, found.t, 2.5) == ""


def test_anisotropic_intrinsics_are_a_warning(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    given = Camera("PINHOLE", 160, 120, (170.0, 100.0, 80.0, 60.0))
    assert any("fx/fy = 1.70" in w for w in intrinsics_warnings(given))
    assert intrinsics_warnings(Camera("PINHOLE", 160, 120, (130.0, 125.0, 81.0, 59.0))) == []
    exactly(monkeypatch, given)
    est = Relocalizer(*tiny_map).localize(photo(160, 120), given)
    assert any("fx/fy = 1.70" in w for w in est.to_json()["warnings"])


def test_an_estimated_focal_far_from_the_map_cameras_is_refused(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The map records its cameras' focal lengths over the long side (focal_range); an estimate
    more than 3x outside it is no reading of this photo."""
    torch.manual_seed(0)
    encoder = Encoder(width=0.25)
    torch.save(encoder.state_dict(), tmp_path / "encoder.pt")
    map_path = tmp_path / "ranged.map.pt"
    save_map(map_path, Regressor(encoder, Head(in_channels=encoder.out_channels, width=64)),
             {"short_side": SHORT_SIDE, "focal_range": [0.8, 0.8]})
    reloc = Relocalizer(map_path, tmp_path / "encoder.pt")
    exactly(monkeypatch, CENTRED)  # f = 130 px: 0.81x the long side
    assert reloc.localize(photo(160, 120), None).success
    exactly(monkeypatch, Camera("SIMPLE_PINHOLE", 160, 120, (600.0, 80.0, 60.0)))  # 3.75x: over 0.8 x 3
    est = reloc.localize(photo(160, 120), None)
    assert not est.success and "is over 3x off the map's cameras' (0.80-0.80x)" in est.rejected
    assert est.confidence == 0.0


def test_the_train_stage_records_the_focal_range() -> None:
    from usvc.train.run import focal_range

    K = np.array([[[900.0, 0, 272.0], [0, 900.0, 480.0], [0, 0, 1]], [[450.0, 0, 320.0], [0, 450.0, 240.0], [0, 0, 1]]])
    assert focal_range(K) == [pytest.approx(450 / 640, abs=1e-4), pytest.approx(900 / 960, abs=1e-4)]
    with pytest.raises(UsvcError, match="no valid intrinsics"):
        focal_range(np.full((1, 3, 3), np.nan))


def test_implausible_focal_lengths() -> None:
    assert implausible_focal(130.0, 160, 120, "f") == ""
    assert "field of view" in implausible_focal(1e9, 160, 120, "the given focal length")
    assert "is implausible for a 160x120 photo" in implausible_focal(1e-9, 160, 120, "the given focal length")
    assert implausible_focal(float("nan"), 160, 120, "f")


# ------------------------------------------------------------------ 5. principal point far off the centre

def test_swapped_principal_point_is_a_warning(tiny_map: tuple[Path, Path], photo_file: Path,
                                              capsys: pytest.CaptureFixture[str],
                                              caplog: pytest.LogCaptureFixture) -> None:
    rc, out, err = run(capsys, tiny_map, "--camera", "PINHOLE", "130", "130", "60", "80", photo_file)
    assert rc == 0, err
    (record,) = records_of(out)
    assert any("principal point (60, 80)" in w and "cx and cy look swapped" in w for w in record["warnings"])
    assert "cx and cy look swapped" in caplog.text  # logged too
    rc, out, err = run(capsys, tiny_map, "--camera", "PINHOLE", "130", "130", "80", "60", photo_file)
    assert rc == 0 and "warnings" not in records_of(out)[0]


# ------------------------------------------------------------------ 6. --format ''

@pytest.mark.parametrize("fmt", ["", ",", " , "])
def test_an_empty_format_is_refused(tiny_map: tuple[Path, Path], photo_file: Path, tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str], fmt: str) -> None:
    out_dir = tmp_path / "out"
    line = one_error_line(*run(capsys, tiny_map, "--focal", "130", "--out-dir", out_dir, "--format", fmt,
                               photo_file))
    assert "names no format; valid: " + ", ".join(FORMATS) in line
    assert not out_dir.exists()


# ------------------------------------------------------------------ 7. decompression bomb in a batch

def header_only_png(path: Path, width: int, height: int) -> Path:
    """A PNG whose header claims width x height: a few dozen bytes that say 400 megapixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)  # 8-bit grey
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def test_a_decompression_bomb_is_its_photo_failure(tiny_map: tuple[Path, Path], photo_file: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str],
                                                   caplog: pytest.LogCaptureFixture) -> None:
    bomb = header_only_png(tmp_path / "bomb.png", 20000, 20000)
    assert bomb.stat().st_size < 200
    with pytest.raises(Image.DecompressionBombError):  # what Pillow alone makes of it
        Image.open(bomb)
    rc, out, err = run(capsys, tiny_map, "--focal", "130", photo_file, bomb, photo_file)
    assert rc == 1 and "Traceback" not in err
    records = records_of(out)
    assert [r["name"] for r in records] == [str(photo_file), str(bomb), str(photo_file)]
    assert records[1]["success"] is False and "20000x20000" in records[1]["error"]
    assert "error" not in records[0] and "error" not in records[2] and records[2]["cells"] == 300
    assert len([r for r in caplog.records if "bomb.png" in r.getMessage()]) == 1  # its one failure line
    # alone, it is the run's one error line
    line = one_error_line(*run(capsys, tiny_map, "--focal", "130", bomb))
    assert "bomb.png" in line and "megapixel" in line


def test_an_undecodable_photo_in_a_batch_is_its_own_failure(tiny_map: tuple[Path, Path], photo_file: Path,
                                                             tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                             ) -> None:
    """A file whose header is not an image's: its record says so, the batch and its exports go on."""
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"not a jpeg at all")
    out_dir = tmp_path / "out"
    rc, out, err = run(capsys, tiny_map, "--focal", "130", "--out-dir", out_dir, "--format", "jsonl", garbage,
                       photo_file)
    assert rc == 1 and "Traceback" not in err
    records = records_of(out)
    assert records[0]["success"] is False and "cannot decode image" in records[0]["error"]
    assert "error" not in records[1] and records[1]["cells"] == 300
    assert records_of((out_dir / "queries.jsonl").read_text()) == records


# ------------------------------------------------------------------ 8. every failure says why

@pytest.mark.parametrize("focal", ["1e9", "1e-9"])
def test_an_absurd_focal_is_a_failure_with_a_reason(tiny_map: tuple[Path, Path], photo_file: Path, focal: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run(capsys, tiny_map, "--focal", focal, photo_file)
    assert rc == 0, err
    (record,) = records_of(out)
    assert record["success"] is False and record["confidence"] == 0.0
    assert record["rejected"].startswith("the given focal length (") and "is implausible for a 160x120" in \
        record["rejected"]


def test_bool_intrinsics_are_refused(tiny_map: tuple[Path, Path]) -> None:
    for value in (True, False, np.bool_(True), [True, 1.0, 2.0, 3.0], np.ones(4, bool)):
        with pytest.raises(UsvcError, match="intrinsics must be"):
            camera_from_intrinsics(value, 160, 120)  # type: ignore[arg-type]
    with pytest.raises(UsvcError, match="a bool"):
        Relocalizer(*tiny_map).localize(photo(160, 120), True)  # type: ignore[arg-type]


def test_a_blank_photo_is_a_failure_with_a_reason(tiny_map: tuple[Path, Path]) -> None:
    for intrinsics in (None, 130.0):
        est = Relocalizer(*tiny_map).localize(np.zeros((120, 160, 3), np.uint8), intrinsics)
        assert not est.success and est.rejected.startswith("the photo is blank")
        assert est.to_json()["rejected"] == est.rejected and est.confidence == 0.0


@pytest.mark.parametrize("intrinsics", [None, 130.0])
def test_no_pose_is_a_failure_with_a_reason(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch,
                                            intrinsics: float | None) -> None:
    """Coordinates no camera explains (noise): the answer says there was no pose, and why."""
    noise = np.random.default_rng(1).uniform(-5.0, 5.0, (15, 20, 3))
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: noise)
    est = Relocalizer(*tiny_map).localize(photo(160, 120), intrinsics)
    assert not est.success and est.confidence == 0.0
    assert est.rejected, est.to_json()
    assert any(k in est.rejected for k in ("no pose", "no camera explains", "implausible", "confidence"))


# ------------------------------------------------------------------ 9. --out-dir that cannot be written

def test_an_out_dir_under_a_file_fails_before_localizing(tiny_map: tuple[Path, Path], photo_file: Path,
                                                         tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file")
    line = one_error_line(*run(capsys, tiny_map, "--focal", "130", "--out-dir", blocker / "out", photo_file))
    assert f"--out-dir {blocker / 'out'}: {blocker} is a file, not a folder" in line


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes in read-only folders")
def test_a_read_only_out_dir_fails_before_localizing(tiny_map: tuple[Path, Path], photo_file: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        for out_dir in (locked, locked / "sub"):
            line = one_error_line(*run(capsys, tiny_map, "--focal", "130", "--out-dir", out_dir, photo_file))
            assert f"--out-dir {out_dir}: cannot write in the folder" in line
    finally:
        locked.chmod(0o755)


# ------------------------------------------------------------------ 10. EXIF focal lengths

def exif_photo(path: Path, focal_35mm: int) -> Path:
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = focal_35mm  # FocalLengthIn35mmFilm: f = f35 / 36 * 160 px
    Image.fromarray(photo(160, 120)).save(path, exif=exif)
    return path


def test_a_1mm_exif_focal_is_named_as_exif(tiny_map: tuple[Path, Path], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    one_mm = exif_photo(tmp_path / "one_mm.jpg", 1)
    rc, out, err = run(capsys, tiny_map, one_mm)
    assert rc == 0, err
    (record,) = records_of(out)
    assert record["intrinsics_source"] == "exif" and record["success"] is False
    assert record["rejected"].startswith("the EXIF focal length (FocalLengthIn35mmFilm 1 mm: 4.444 px) is "
                                         "implausible")
    assert "check the intrinsics" not in record["rejected"] and record["rejected"].endswith(
        "--no-exif ignores EXIF focal lengths")
    rc, out, err = run(capsys, tiny_map, "--no-exif", one_mm)
    assert rc == 0, err
    assert records_of(out)[0]["intrinsics_source"] == "estimated"


def test_an_exif_focal_the_content_contradicts_says_exif(tiny_map: tuple[Path, Path], tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    exactly(monkeypatch, CENTRED)  # the content: f = 130 px; the EXIF says 18 / 36 * 160 = 80 px
    wrong = exif_photo(tmp_path / "wrong.jpg", 18)
    rc, out, err = run(capsys, tiny_map, "--no-refine", wrong)
    assert rc == 0, err
    (record,) = records_of(out)
    assert record["success"] is False
    assert record["rejected"].startswith("the EXIF focal length (FocalLengthIn35mmFilm 18 mm: 80 px) disagrees with "
                                         "the photo's content: the image implies a focal length 1.6")
    rc, out, err = run(capsys, tiny_map, "--no-refine", "--no-exif", wrong)
    (record,) = records_of(out)
    assert record["success"] is True and record["intrinsics_source"] == "estimated"
    assert record["camera"]["params"][0] == pytest.approx(130.0, rel=1e-3)


# ------------------------------------------------------------------ a photo over the decode limit

def test_a_photo_over_the_decode_limit_is_localized_from_its_reduced_pixels(
        tiny_map: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A JPEG over MAX_DECODE_PIXELS (a 108 MP phone photo) is decoded reduced; its intrinsics, given
    for its own pixels, are scaled with it, and the answer's camera is the photo's."""
    from test_relocalizer import assert_true_pose

    from usvc.core import images

    big = tmp_path / "big.jpg"
    cv2.imwrite(str(big), cv2.resize(photo(160, 120), (320, 240)), [cv2.IMWRITE_JPEG_QUALITY, 95])
    monkeypatch.setattr(images, "MAX_DECODE_PIXELS", 320 * 240 - 1)
    exactly(monkeypatch)  # the network sees CENTRED (f = 130 px at 160x120): f = 260 px at the photo's 320x240
    for intrinsics in (260.0, None):
        est = Relocalizer(*tiny_map).localize(big, intrinsics)
        assert_true_pose(est)
        assert (est.camera.width, est.camera.height) == (320, 240)
        assert est.camera.focal[0] == pytest.approx(260.0, rel=1e-3)
        assert any("320x240" in w and "decoded at 1/2 (160x120)" in w for w in est.warnings)
    rc, out, err = run(capsys, tiny_map, "--focal", "260", big)
    record = records_of(out)[0]
    assert rc == 0 and record["success"] and record["camera"]["width"] == 320, (out, err)
