"""`usvc localize FOLDER` reads every photo format the decoder (usvc.core.images) reads, whatever the
case of the extension or the characters of the name, and names each file it skips, with why."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, features

from usvc.cli import main
from usvc.cli.photo_args import expand_photos, folder_photos, folder_suffixes
from usvc.relocalize.photo_camera import UnreadablePhoto, photo_camera
from usvc.core.errors import SceneError, UsvcError
from usvc.core.images import NO_HEIF_DECODER, heif_decoder, read_photo

from test_cli import fake_estimates, make_map

PIXELS = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
# name -> how Pillow saves it; every one of these is a photo the folder yields
PHOTOS = {
    "a.jpg": "JPEG", "B.JPG": "JPEG", "c.jpeg": "JPEG", "d (1).png": "PNG", "e #2.webp": "WEBP",
    "f%20g.TIF": "TIFF", "h.tiff": "TIFF", "-i.bmp": "BMP", "j.gif": "GIF", "K.GIF": "GIF",
    "ü 写真 ñ.PNG": "PNG", "l.WebP": "WEBP",
}
if heif_decoder():  # pillow-heif installed (not a dependency): HEIC is one more photo
    PHOTOS["IMG_1.heic"] = "HEIF"
SKIPPED = {"notes.txt": "not listed", "no_extension": "files without an extension", "raw.CR2": ".CR2 files"}
if not heif_decoder():
    SKIPPED["IMG_1.heic"] = NO_HEIF_DECODER


def write_photo(path: Path, fmt: str) -> None:
    img = Image.fromarray(PIXELS)
    if fmt == "GIF":  # two frames: the first is the photo
        img.save(path, format=fmt, save_all=True, append_images=[Image.fromarray(255 - PIXELS)], duration=100)
    else:
        img.save(path, format=fmt)


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    photos = tmp_path / "photos"
    photos.mkdir()
    for name, fmt in PHOTOS.items():
        write_photo(photos / name, fmt)
    for name in SKIPPED:
        (photos / name).write_bytes(b"\x00\x00\x00\x18ftypheic" if name.endswith(".heic") else b"not a photo")
    (photos / "sub").mkdir()  # not looked into, not a skipped file either
    write_photo(photos / "sub" / "deep.png", "PNG")
    return photos


def test_the_folder_yields_every_format_the_decoder_reads(folder: Path, caplog) -> None:
    with caplog.at_level(logging.WARNING):
        photos = expand_photos([str(folder)])
    names = [p.name for _, p in photos]
    assert sorted(names) == sorted(PHOTOS) and names == sorted(names)
    for _, path in photos:  # what the folder yields is what the decoder reads (a GIF's first frame)
        photo = read_photo(path)
        assert photo.bgr.shape == (120, 160, 3) and photo.reduction == 1
        if PHOTOS[path.name] in ("PNG", "TIFF", "BMP", "WEBP"):
            lossless = PHOTOS[path.name] != "WEBP"
            error = np.abs(photo.bgr[..., ::-1].astype(int) - PIXELS).mean()
            assert error == 0 if lossless else error < 60
        if PHOTOS[path.name] == "GIF":  # palette quantised, but the first frame, not the inverted second
            assert np.abs(photo.bgr[..., ::-1].astype(int) - PIXELS).mean() < 30
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == len(SKIPPED)
    for name, why in SKIPPED.items():  # one line each, naming the file and why
        assert sum(line.startswith(f"skipped {folder / name}: ") and why in line for line in lines) == 1


def test_extensions_listed_follow_the_installed_decoders() -> None:
    suffixes = folder_suffixes()
    assert {".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff", ".bmp", ".gif"} <= set(suffixes)
    assert (".heic" in suffixes) is heif_decoder() and (".avif" in suffixes) is bool(features.check("avif"))


@pytest.mark.skipif(heif_decoder(), reason="pillow-heif installed: HEIC files are photos")
def test_heic_without_a_decoder_is_named_in_the_error_of_a_folder_of_heic(tmp_path: Path) -> None:
    (tmp_path / "IMG_1.HEIC").write_bytes(b"\x00\x00\x00\x18ftypheic")
    with pytest.raises(UsvcError, match=r"has no images .*IMG_1\.HEIC \(no HEIC decoder installed \(pip install "
                                        r"pillow-heif\)\)"):
        expand_photos([str(tmp_path)])
    assert folder_photos(tmp_path) == ([], [(tmp_path / "IMG_1.HEIC", NO_HEIF_DECODER)])


def test_localize_answers_each_photo_of_the_folder_and_names_each_skipped_file(
        folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        caplog: pytest.LogCaptureFixture) -> None:
    """Through `usvc localize` (the network's answer replaced): one record per photo, in name order,
    each read at its size; one warning line per skipped file."""
    map_path, weights = make_map(tmp_path, 0)
    given = fake_estimates(monkeypatch)
    with caplog.at_level(logging.WARNING):
        rc = main(["localize", "--map", str(map_path), "--encoder-weights", str(weights), "--focal", "130",
                   str(folder)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    records = [json.loads(line) for line in captured.out.splitlines()]
    assert [Path(r["name"]).name for r in records] == sorted(PHOTOS)
    assert [r["success"] for r in records] == [i != 1 for i in range(len(PHOTOS))]  # fake_estimates fails photo 1
    assert len(given) == len(PHOTOS) and all(cam.width == 160 and cam.height == 120 for cam in given)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("skipped ")]
    assert len(lines) == len(SKIPPED)
    for name, why in SKIPPED.items():
        assert sum(line.startswith(f"skipped {folder / name}: ") and why in line for line in lines) == 1
    assert not any("deep.png" in r.getMessage() for r in caplog.records)


@pytest.mark.skipif(heif_decoder(), reason="pillow-heif installed: HEIC files are photos")
def test_a_heic_named_directly_says_that_no_decoder_is_installed(tmp_path: Path) -> None:
    heic = tmp_path / "IMG_2.heic"
    heic.write_bytes(b"\x00\x00\x00\x18ftypheic")
    assert expand_photos([str(heic)]) == [(str(heic), heic)]  # named directly: tried, as any file is
    args = argparse.Namespace(focal=None, intrinsics=None, no_exif=False)
    with pytest.raises(UnreadablePhoto, match=r"IMG_2\.heic: no HEIC decoder installed \(pip install pillow-heif\)"):
        photo_camera(args, None, str(heic), heic)
    with pytest.raises(SceneError, match=r"no HEIC decoder installed"):
        read_photo(heic)
