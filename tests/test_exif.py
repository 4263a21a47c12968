"""EXIF orientation and focal length, on small photos written with Pillow."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps
from PIL.TiffImagePlugin import IFDRational

from usvc.core.errors import SceneError
from usvc.core.exif import exif_focal_px, oriented_size
from usvc.core.images import read_image_bgr

W, H = 64, 48


def photo(path: Path, orientation: int | None = None, size: tuple[int, int] = (W, H),
          **exif_tags: float | int | IFDRational) -> Path:
    """A smooth image (JPEG keeps it; any flip or turn changes it) with the given orientation and
    Exif IFD tags (keyword names are hex tag ids)."""
    y, x = np.mgrid[0:size[1], 0:size[0]]
    pixels = np.stack([x * 255 // size[0], y * 255 // size[1], (x + 2 * y) * 255 // (size[0] + 2 * size[1])],
                      axis=-1).astype(np.uint8)
    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    ifd = exif.get_ifd(0x8769)
    for tag, value in exif_tags.items():
        ifd[int(tag, 16)] = value
    Image.fromarray(pixels).save(path, exif=exif, **({"quality": 95} if path.suffix == ".jpg" else {}))
    return path


@pytest.mark.parametrize("orientation", range(1, 9))
def test_read_image_applies_orientation_like_viewers(tmp_path: Path, orientation: int) -> None:
    png = photo(tmp_path / f"o{orientation}.png", orientation)
    expected = np.asarray(ImageOps.exif_transpose(Image.open(png)).convert("RGB"))[..., ::-1]
    for path in (png, photo(tmp_path / f"o{orientation}.jpg", orientation),
                 photo(tmp_path / f"o{orientation}.tif", orientation)):
        bgr = read_image_bgr(path)
        assert bgr.dtype == np.uint8 and bgr.flags.c_contiguous and bgr.shape == expected.shape, path
        assert oriented_size(path) == (bgr.shape[1], bgr.shape[0])
        diff = np.abs(bgr.astype(int) - expected.astype(int))
        if path.suffix == ".jpg":  # lossy: compare loosely
            assert diff.mean() < 3, path
        else:  # PNG, and TIFF (decoded by Pillow)
            assert diff.max() == 0, path


def test_orientation_6_is_portrait(tmp_path: Path) -> None:
    path = photo(tmp_path / "portrait.jpg", 6)
    assert oriented_size(path) == (H, W)
    assert read_image_bgr(path).shape == (W, H, 3)
    assert cv2.imread(str(path)).shape == (W, H, 3)  # plain cv2.imread turns JPEGs the same way
    assert oriented_size(photo(tmp_path / "plain.jpg")) == (W, H)


@pytest.mark.parametrize("make", [lambda p: p.write_bytes(b"not an image"), lambda p: None],
                         ids=["garbage", "missing"])
def test_unreadable_files_name_the_file(tmp_path: Path, make) -> None:
    path = tmp_path / "bad.jpg"
    make(path)
    for fn in (oriented_size, read_image_bgr, exif_focal_px):
        with pytest.raises(SceneError, match="bad.jpg"):
            fn(path)


def test_focal_from_35mm_equivalent(tmp_path: Path) -> None:
    # 36 mm on the long side: a 36 mm equivalent lens has f = the long side in pixels.
    assert exif_focal_px(photo(tmp_path / "a.jpg", A405=36)) == pytest.approx(W)
    assert exif_focal_px(photo(tmp_path / "b.jpg", A405=27)) == pytest.approx(27 / 36 * W)
    # Portrait (orientation 6): still the long side.
    assert exif_focal_px(photo(tmp_path / "c.jpg", 6, A405=27)) == pytest.approx(27 / 36 * W)
    # 35 mm equivalent wins over the sensor resolution.
    assert exif_focal_px(photo(tmp_path / "d.jpg", A405=27, **{"920A": IFDRational(4), "A20E": IFDRational(1000),
                                                             "A210": 4})) == pytest.approx(27 / 36 * W)


@pytest.mark.parametrize("unit, per_unit_mm", [(2, 25.4), (3, 10.0), (4, 1.0), (None, 25.4)],
                         ids=["inch", "cm", "mm", "default-inch"])
def test_focal_from_sensor_resolution(tmp_path: Path, unit: int | None, per_unit_mm: float) -> None:
    # A 4 mm lens on a sensor with 10 px/mm: 40 px.
    tags = {"920A": IFDRational(4, 1), "A20E": IFDRational(int(10 * per_unit_mm * 100), 100)}
    if unit is not None:
        tags["A210"] = unit
    assert exif_focal_px(photo(tmp_path / "s.jpg", **tags)) == pytest.approx(40.0)
    # The same EXIF on a copy downscaled from a 128x96 original: half the pixels, half the focal.
    tags.update({"A002": 128, "A003": 96})
    assert exif_focal_px(photo(tmp_path / "t.jpg", **tags)) == pytest.approx(20.0)


@pytest.mark.parametrize("tags", [
    {},
    {"A405": 0},
    {"920A": IFDRational(4)},  # no sensor resolution
    {"920A": IFDRational(0), "A20E": IFDRational(1000), "A210": 2},
    {"920A": IFDRational(4), "A20E": IFDRational(1, 0), "A210": 2},  # rational with a zero denominator
    {"920A": IFDRational(4), "A20E": IFDRational(1000), "A210": 1},  # unit "none"
    {"920A": IFDRational(-4), "A20E": IFDRational(1000), "A210": 2},
], ids=["none", "35mm-zero", "no-resolution", "zero-focal", "nan-resolution", "no-unit", "negative"])
def test_focal_absent_or_nonsensical_is_none(tmp_path: Path, tags: dict) -> None:
    assert exif_focal_px(photo(tmp_path / "n.jpg", **tags)) is None


def test_png_without_exif(tmp_path: Path) -> None:
    path = tmp_path / "plain.png"
    Image.new("RGB", (W, H)).save(path)
    assert exif_focal_px(path) is None and oriented_size(path) == (W, H)
    assert read_image_bgr(path).shape == (H, W, 3) and not math.isnan(read_image_bgr(path).mean())


def test_truncated_jpeg_is_one_clear_error_not_grey_pixels(tmp_path: Path) -> None:
    """Decoders fill a cut-off JPEG with grey and carry on; usvc refuses it by name."""
    from usvc.core.images import jpeg_is_complete

    whole = photo(tmp_path / "whole.jpg", orientation=6, size=(160, 120), **{"a405": 28})
    data = whole.read_bytes()
    assert jpeg_is_complete(data) and jpeg_is_complete(data + b"motion-photo video" * 100)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[: len(data) * 2 // 3])
    assert not jpeg_is_complete(cut.read_bytes())
    with pytest.raises(SceneError, match=r"cannot decode image .*cut\.jpg: truncated or corrupt JPEG"):
        read_image_bgr(cut)
    progressive = tmp_path / "progressive.jpg"
    Image.open(whole).save(progressive, progressive=True, quality=90)
    assert read_image_bgr(progressive).shape == (120, 160, 3)


def test_a_camera_for_the_unturned_size_names_the_exif_orientation(tmp_path: Path) -> None:
    """A photo stored 64x48 with orientation 6 is a 48x64 image; a 64x48 camera gets a reason."""
    from usvc.core.scene import Camera
    from usvc.core.undistort import check_image_size

    path = photo(tmp_path / "turned.jpg", 6)
    image = read_image_bgr(path)
    assert image.shape[:2] == (W, H)
    with pytest.raises(SceneError, match=r"image is 48x64 but its camera says 64x48 \(its EXIF orientation 6 turns"):
        check_image_size(image, Camera("PINHOLE", W, H, (50, 50, 32, 24)), str(path))
    plain = photo(tmp_path / "plain.jpg")
    with pytest.raises(SceneError, match=r"camera says 48x64$"):
        check_image_size(read_image_bgr(plain), Camera("PINHOLE", H, W, (50, 50, 24, 32)), str(plain))


def _chunks(data: bytes) -> list[bytes]:
    """A PNG's chunks, each with its length, type, data and CRC."""
    out, at = [], 8
    while at < len(data):
        length = int.from_bytes(data[at:at + 4], "big")
        out.append(data[at:at + 12 + length])
        at += 12 + length
    return out


@pytest.mark.parametrize("where", ["before", "after", "none", "xmp-after"])
def test_png_exif_is_read_without_decoding_unless_it_follows_the_pixels(tmp_path: Path, where: str,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A PNG's EXIF (orientation, focal length) is what Pillow finds by decoding the whole image; the
    pixels are decoded for it only when metadata follows them."""
    from PIL import PngImagePlugin

    from usvc.core.exif import open_checked, png_metadata_after_pixels, read_exif

    path = photo(tmp_path / "p.png", 6 if where != "none" else None, size=(96, 64), **{"a405": 28})
    chunks = _chunks(path.read_bytes())
    if where in ("after", "xmp-after"):  # move the eXIf chunk (or add an XMP one) behind the pixels
        exif = next(c for c in chunks if c[4:8] == b"eXIf")
        chunks.remove(exif)
        if where == "xmp-after":
            info = PngImagePlugin.PngInfo()
            info.add_itxt("XML:com.adobe.xmp", '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf='
                          '"http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description xmlns:tiff='
                          '"http://ns.adobe.com/tiff/1.0/" tiff:Orientation="8"/></rdf:RDF></x:xmpmeta>')
            Image.new("RGB", (4, 4)).save(tmp_path / "x.png", pnginfo=info)
            exif = next(c for c in _chunks((tmp_path / "x.png").read_bytes()) if c[4:8] == b"iTXt")
        chunks.insert(len(chunks) - 1, exif)
        path.write_bytes(PngImagePlugin._MAGIC + b"".join(chunks))
    assert png_metadata_after_pixels(path) == (where in ("after", "xmp-after"))
    with Image.open(path) as img:
        expected = dict(img.getexif())  # Pillow's own: decodes the image
    decodes = []
    load = PngImagePlugin.PngImageFile.load
    monkeypatch.setattr(PngImagePlugin.PngImageFile, "load", lambda img: decodes.append(1) or load(img))
    with open_checked(path) as img:
        found = read_exif(img)
    assert len(decodes) == (where in ("after", "xmp-after"))  # decoded only when it had to
    assert dict(found) == expected
    assert oriented_size(path) == {"before": (64, 96), "after": (64, 96), "none": (96, 64),
                                   "xmp-after": (64, 96)}[where]
    assert exif_focal_px(path) == (None if where in ("none", "xmp-after") else pytest.approx(28 / 36 * 96))
    cut = tmp_path / "cut.png"  # no IEND: Pillow's own way
    cut.write_bytes(path.read_bytes()[:-12])
    assert png_metadata_after_pixels(cut)
