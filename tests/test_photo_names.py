"""Photo names as cameras and file managers write them, carried through SfM unchanged.

COLMAP reads a list of image pairs as text, cutting a line at its first space and skipping one
that starts with `#`: pairs of `IMG (1).jpg` or `#0012.jpg` were lost (silently on one thread).
Matching now names images by an alias of their id (usvc.sfm.pair_matching.aliased_names).
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_scene

from usvc.core.errors import SfmError
from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
from usvc.prepare.importers import load_scene
from usvc.prepare.working_images import prepare_scene
from usvc.sfm.pair_matching import _check_count, aliased_names
from usvc.sfm.reconstruction import SfmOptions, reconstruct
from usvc.sfm.tracks_file import from_reconstruction, sfm_stats

OPTS = SfmOptions(max_num_features=2048, matching="auto", exhaustive_max_images=150, sequential_overlap=10,
                  pose_pairs_per_image=20, reconstruction="auto", min_points=100, num_threads=-1, seed=0)

# Twelve names a phone, a file manager or a user gives photos.
ODD_NAMES = ["IMG_0001 (1).JPG", "IMG_0001 (2).JPG", "#0012.jpg", "100% done.jpeg", "café ☕ table.jpg",
             "-leading dash.jpg", "photo with spaces.JPG", "日本 写真.jpg", "a#b%c.JPEG", "x (copy).jpg",
             "-- two dashes.JPG", "#hash (3).jpeg"]


def _images_db(path: Path, names: list[str]) -> None:
    con = sqlite3.connect(path)
    with con:
        con.execute("CREATE TABLE images (image_id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE)")
        con.executemany("INSERT INTO images VALUES (?, ?)", list(enumerate(names, start=1)))
    con.close()


def _names(path: Path) -> list[str]:
    con = sqlite3.connect(path)
    try:
        return [n for (n,) in con.execute("SELECT name FROM images ORDER BY image_id")]
    finally:
        con.close()


def test_aliases_hold_no_space_or_hash_and_the_names_come_back(tmp_path):
    db = tmp_path / "database.db"
    _images_db(db, ODD_NAMES)
    with aliased_names(db) as aliases:
        assert list(aliases) == ODD_NAMES
        assert _names(db) == [aliases[n] for n in ODD_NAMES]
        assert len(set(aliases.values())) == len(ODD_NAMES)
        assert all(a.isascii() and not any(c.isspace() for c in a) and not a.startswith("#") for a in aliases.values())
    assert _names(db) == ODD_NAMES
    with pytest.raises(KeyError):  # an error inside the block: the names still come back
        with aliased_names(db):
            raise KeyError("boom")
    assert _names(db) == ODD_NAMES


def test_a_photo_named_like_an_alias_is_refused_by_name(tmp_path):
    db = tmp_path / "database.db"
    _images_db(db, ["a.jpg", "usvc-image-1"])
    with pytest.raises(SfmError, match="'usvc-image-1' is reserved"):
        with aliased_names(db):
            pass
    assert _names(db) == ["a.jpg", "usvc-image-1"]


def test_a_chunk_missing_pairs_is_an_error():
    _check_count(Path("x.db"), 5, 5)
    with pytest.raises(RuntimeError, match="matched 3 of 5 image pairs"):
        _check_count(Path("x.db"), 3, 5)


def _capture(src: Path, dst: Path, rename: dict[str, str]) -> None:
    """Twelve office photos (and their LLFF rows) under the names `rename` gives them."""
    rows = np.load(src / "poses_bounds.npy")
    all_names = sorted(p.name for p in (src / "images").iterdir())
    (dst / "images").mkdir(parents=True)
    for name in rename:
        shutil.copyfile(src / "images" / name, dst / "images" / rename[name])
    # LLFF rows follow the lexicographic order of the file names
    kept = sorted(rename, key=lambda n: rename[n])
    np.save(dst / "poses_bounds.npy", rows[[all_names.index(n) for n in kept]])


def _model(raw: Path, tmp: Path, reconstruction: str, threads: int):
    scene = load_scene("llff", raw, "names", "every_nth", 8)
    prepared = tmp / "prepared"
    if not prepared.exists():
        prepared.mkdir(parents=True)
        prepare_scene(scene, prepared, working_width=480)
    loaded = read_scene_h5(prepared / "scene.h5")
    work = tmp / f"work-{reconstruction}-{threads}"
    work.mkdir()
    opts = SfmOptions(**{**OPTS.__dict__, "reconstruction": reconstruction})
    rec, info = reconstruct(loaded.split("train"), prepared / IMAGE_DIR, work, opts, has_poses=True, threads=threads)
    tracks = from_reconstruction(rec, work / "database.db")
    return tracks, {**info, **sfm_stats(tracks)}, [f.name for f in loaded.split("train")]


@pytest.mark.slow
@pytest.mark.shared
@pytest.mark.parametrize("reconstruction", ["triangulate", "incremental"])
def test_odd_photo_names_give_the_model_plain_names_give(tmp_path, reconstruction):
    """Twelve office photos under plain names and under names with spaces, parentheses, '#', '%',
    unicode, a leading '-' and upper-case extensions: the same model, point for point, on one
    matching thread and on two (the names map in the same order, so image ids are the same)."""
    src = shared_scene("office")
    plain = sorted(p.name for p in (src / "images").iterdir())[:12]
    odd = dict(zip(plain, sorted(ODD_NAMES)))
    _capture(src, tmp_path / "plain", {n: n for n in plain})
    _capture(src, tmp_path / "odd", odd)
    models = {}
    for label in ("plain", "odd"):
        for threads in (1, 2):
            models[label, threads] = _model(tmp_path / label, tmp_path / f"{label}-out", reconstruction, threads)
    base, base_info, base_names = models["plain", 1]
    assert base_info["images"] == len(base_names) == 10 and len(base.xyz) > 100, len(base.xyz)
    for key, (tracks, info, names) in models.items():
        assert info["images"] == base_info["images"], key
        files = [Path(n).name for n in names]  # the frames' names are relative to the capture
        assert files == ([odd[Path(n).name] for n in base_names] if key[0] == "odd" else [Path(n).name for n in base_names])
        assert len(tracks.xyz) == len(base.xyz), key
        np.testing.assert_array_equal(tracks.xyz, base.xyz, err_msg=str(key))
        np.testing.assert_array_equal(tracks.obs_uv, base.obs_uv, err_msg=str(key))


def test_a_photo_colmap_cannot_decode_is_prepared_with_png_bytes_under_its_name(tmp_path):
    """A .webp photo keeps its name in the prepared scene, with lossless PNG content that COLMAP's
    reader, OpenCV and Pillow decode (they tell the format by the bytes)."""
    import cv2

    from usvc.prepare.working_images import write_image

    image = (np.arange(48 * 64 * 3) % 251).astype(np.uint8).reshape(48, 64, 3)
    write_image(tmp_path / "Photo (1).WEBP", image)
    data = (tmp_path / "Photo (1).WEBP").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), image)
    write_image(tmp_path / "a.JPG", image)  # a format COLMAP reads keeps it
    assert (tmp_path / "a.JPG").read_bytes()[:2] == b"\xff\xd8"


@pytest.mark.slow
@pytest.mark.shared
def test_a_webp_capture_is_posed_and_triangulated(tmp_path):
    """Twelve office photos as .webp (odd names too): imported, prepared and triangulated."""
    import cv2

    src = shared_scene("office")
    plain = sorted(p.name for p in (src / "images").iterdir())[:12]
    _capture(src, tmp_path / "jpg", dict(zip(plain, sorted(ODD_NAMES))))
    raw = tmp_path / "webp"
    (raw / "images").mkdir(parents=True)
    for path in sorted((tmp_path / "jpg" / "images").iterdir()):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        ok, data = cv2.imencode(".webp", cv2.resize(image, (640, 360), interpolation=cv2.INTER_AREA),
                                [cv2.IMWRITE_WEBP_QUALITY, 95])
        assert ok
        (raw / "images" / (path.stem + ".webp")).write_bytes(data.tobytes())
    shutil.copyfile(tmp_path / "jpg" / "poses_bounds.npy", raw / "poses_bounds.npy")
    tracks, info, names = _model(raw, tmp_path / "out", "triangulate", 2)
    assert all(n.endswith(".webp") for n in names) and info["images"] == 10 and len(tracks.xyz) > 100
