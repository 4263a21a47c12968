"""`usvc localize` as a user runs it: JSON on stdout, or exactly one error line and exit 1.

The map is real but untrained, so its poses are garbage; these tests check the interface, and
tests/test_relocalizer.py checks that the poses are right.
"""

from __future__ import annotations

import json
import os
import re
import select
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from usvc.cli import main
from usvc.core.pose_errors import rotation_error_deg
from usvc.core.poses_file import read_poses_txt
from usvc.core.scene import Camera
from usvc.model.encoder import Encoder
from usvc.model.head import Head, Regressor
from usvc.model.map_file import save_map
from usvc.prepare.importers import load_scene

REPO = Path(__file__).resolve().parents[1]
KEYS = {"name", "success", "inliers", "cells", "confidence", "seconds", "intrinsics_source"}


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


NO_LANDMARKS = "refinement by features is off"  # the one note for a map without landmarks beside it


def quiet(stderr: str) -> bool:
    """Nothing on stderr but the note that these test maps have no landmarks."""
    return all(NO_LANDMARKS in line for line in stderr.splitlines()) and len(stderr.splitlines()) <= 1


@pytest.mark.slow
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
    # a map without landmarks localizes, with one line saying refinement by features is off
    assert len(proc.stderr.splitlines()) == 1 and "refinement by features is off" in proc.stderr


@pytest.mark.slow
def test_localize_json_list(files: dict[str, Path]) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], "--json-list",
                "--intrinsics", "130", "125", "81", "59", "--backend", "pycolmap", "--max-error-px", "5",
                files["photo"])
    assert proc.returncode == 0, proc.stderr
    records = json.loads(proc.stdout)
    assert isinstance(records, list) and len(records) == 1 and KEYS <= set(records[0])


@pytest.mark.slow
def test_localize_without_refinement(files: dict[str, Path]) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], "--no-refine",
                "--focal", "130", files["photo"])
    assert proc.returncode == 0, proc.stderr
    record = json.loads(proc.stdout)
    assert record.get("refinement", {"iterations": 0})["iterations"] == 0


@pytest.mark.parametrize("extra, photo, cause", [
    (["--intrinsics", "260", "250", "162", "118"], "photo", "outside the 160x120 image"),
    (["--focal", "130"], "missing_photo", "image not found"),
    (["--focal", "130"], "garbage", "cannot decode image"),
    (["--focal", "130", "--encoder-weights", "{other_weights}"], "photo", "another encoder"),
    (["--focal", "130", "--map", "{truncated}"], "photo", "corrupt or truncated"),
    (["--focal", "130", "--map", "{missing_map}"], "photo", "map file does not exist"),
    (["--focal", "130", "--min-confidence", "1.5"], "photo", "--min-confidence 1.5: must be in [0, 1]"),
    (["--focal", "130", "--focal-tolerance", "-1"], "photo", "--focal-tolerance -1: must be >= 0"),
], ids=["wrong-size", "missing-photo", "undecodable", "other-encoder", "truncated-map",
        "missing-map", "confidence-range", "focal-tolerance-range"])
@pytest.mark.slow
def test_localize_errors(files: dict[str, Path], extra: list[str], photo: str, cause: str) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"],
                *(arg.format(**files) for arg in extra), files[photo])
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("usvc localize: error: ") and cause in lines[0]
    assert proc.stdout == ""


@pytest.mark.slow
def test_a_photo_that_fails_to_decode_keeps_the_others(files: dict[str, Path], tmp_path: Path) -> None:
    """A truncated JPEG (its header reads, its pixels do not) is that photo's record, not the run's end."""
    good = tmp_path / "good.jpg"
    cv2.imwrite(str(good), cv2.imread(str(files["photo"])))
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    for mode in ([], ["--json-list"]):
        proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], *mode,
                    "--focal", "130", good, cut, good)
        assert proc.returncode == 1, proc.stderr
        records = json.loads(proc.stdout) if mode else [json.loads(line) for line in proc.stdout.splitlines()]
        assert [r["name"] for r in records] == [str(good), str(cut), str(good)]
        assert KEYS <= set(records[0]) and KEYS <= set(records[2])
        assert records[1]["success"] is False and "truncated or corrupt JPEG" in records[1]["error"]
        assert "Traceback" not in proc.stderr and "cut.jpg" in proc.stderr


# ------------------------------------------------------------ batches, intrinsics sources, exports

def test_version() -> None:
    proc = usvc("--version")
    assert proc.returncode == 0 and re.fullmatch(r"usvc \S+\n", proc.stdout), (proc.stdout, proc.stderr)


@pytest.fixture(scope="module")
def batch(files: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A folder of three photos (and a non-image), an empty folder, and a JPEG with a 36 mm equivalent lens."""
    folder = tmp_path_factory.mktemp("batch")
    photos = folder / "photos"
    photos.mkdir()
    for name in ("b.PNG", "a.jpg", "c.png"):
        (photos / name).write_bytes(files["photo"].read_bytes() if name.lower().endswith("png") else b"")
    cv2.imwrite(str(photos / "a.jpg"), cv2.imread(str(files["photo"])))
    (photos / "notes.txt").write_text("not a photo")
    (photos / "sub").mkdir()
    cv2.imwrite(str(photos / "sub" / "d.png"), cv2.imread(str(files["photo"])))
    (folder / "empty").mkdir()
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 36  # f = 36 / 36 * 160 px
    Image.open(files["photo"]).save(folder / "exif.jpg", exif=exif)
    return {"photos": photos, "empty": folder / "empty", "exif": folder / "exif.jpg", "root": folder}


@pytest.mark.slow
def test_folder_batch_with_all_exports(files: dict[str, Path], batch: dict[str, Path]) -> None:
    out = batch["root"] / "out"
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], "--focal", "130",
                "--out-dir", out, batch["photos"], files["photo"])
    assert proc.returncode == 0, proc.stderr
    photos = batch["photos"]
    # no progress bar when stderr is not a terminal; the one file of the folder that is not a photo is named
    skipped = [line for line in proc.stderr.splitlines() if "skipped " in line]
    assert len(skipped) == 1 and f"skipped {photos / 'notes.txt'}: .txt files are not listed" in skipped[0]
    assert quiet("\n".join(line for line in proc.stderr.splitlines() if "skipped " not in line))
    records = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [r["name"] for r in records] == [str(photos / "a.jpg"), str(photos / "b.PNG"), str(photos / "c.png"),
                                            str(files["photo"])]  # sorted by name, not recursive
    assert {r["intrinsics_source"] for r in records} == {"focal"}
    assert [json.loads(line) for line in (out / "queries.jsonl").read_text().splitlines()] == records
    ok = [r["name"] for r in records if r["success"]]
    assert list(read_poses_txt(out / "poses.txt")) == ok
    assert pycolmap.Reconstruction(str(out)).num_images() == len(ok)
    assert len(json.loads((out / "transforms.json").read_text())["frames"]) == len(ok)


@pytest.mark.slow
def test_intrinsics_from_exif_else_estimated(files: dict[str, Path], batch: dict[str, Path]) -> None:
    proc = usvc("localize", "--map", files["map"], "--encoder-weights", files["weights"], batch["exif"],
                files["photo"])
    assert proc.returncode == 0, proc.stderr  # focal estimation exists: a photo without EXIF is localized
    exif_record, plain_record = (json.loads(line) for line in proc.stdout.splitlines())
    assert exif_record["intrinsics_source"] == "exif" and plain_record["intrinsics_source"] == "estimated"
    if "camera" in exif_record:
        assert exif_record["camera"]["params"][0] == pytest.approx(160.0)


def fake_estimates(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """Replace Relocalizer.localize: photo i gets a known pose, except photo 1, which fails."""
    from usvc.relocalize.pose_estimate import PoseEstimate
    from usvc.relocalize.relocalizer import Relocalizer

    given: list[Any] = []

    def localize(self: Relocalizer, image: np.ndarray, intrinsics: Any) -> PoseEstimate:
        i = len(given)
        given.append(intrinsics)
        if i == 1:
            nan = np.full((3, 3), np.nan)
            return PoseEstimate(False, nan, nan[0], 0, 300, {"total": 0.0})
        R, t = Rotation.random(random_state=i).as_matrix(), np.array([0.1 * i, 0.2, 1.5])
        return PoseEstimate(True, R, t, 100, 300, {"total": 0.0}, initial_R=R, initial_t=t, camera=intrinsics)

    monkeypatch.setattr(Relocalizer, "localize", localize)
    return given


def test_failed_photos_only_in_jsonl(files: dict[str, Path], batch: dict[str, Path], tmp_path: Path,
                                     monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    given = fake_estimates(monkeypatch)
    out = tmp_path / "out"
    # The folder after --camera's parameters is a photo, however greedy --camera's nargs is.
    rc = main(["localize", "--map", str(files["map"]), "--encoder-weights", str(files["weights"]),
               "--camera", "OPENCV", "130", "131", "80", "60", "0.05", "-0.08", "0", "0", str(batch["photos"]),
               "--out-dir", str(out), "--format", "jsonl,poses", "--format", "colmap", "--format", "nerfstudio"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    records = [json.loads(line) for line in captured.out.splitlines()]
    assert [r["success"] for r in records] == [True, False, True]
    assert {r["intrinsics_source"] for r in records} == {"camera"}
    assert given[0] == Camera("OPENCV", 160, 120, (130, 131, 80, 60, 0.05, -0.08, 0, 0))
    names = [records[0]["name"], records[2]["name"]]
    poses = read_poses_txt(out / "poses.txt")
    assert list(poses) == names
    rec = pycolmap.Reconstruction(str(out))
    assert sorted(image.name for image in rec.images.values()) == ["a.jpg", "c.png"]
    assert [c.model.name for c in rec.cameras.values()] == ["OPENCV"]
    scene = load_scene("transforms", out, "q", split_rule="every_nth", split_n=2)
    for frame in scene.frames:
        R, t = poses[str(batch["photos"] / Path(frame.image_path).name)]
        np.testing.assert_allclose(frame.R, R, atol=1e-9)
        np.testing.assert_allclose(frame.t, t, atol=1e-9)
        assert frame.camera.model == "OPENCV"


def test_exact_scene_coordinates_export_the_true_pose(files: dict[str, Path], tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """The real localize path (network replaced by exact coordinates) through to the files."""
    from usvc.model.encoder import cell_centers
    from usvc.relocalize.relocalizer import Relocalizer

    R_true, t_true = Rotation.from_rotvec([0.1, -0.3, 0.05]).as_matrix(), np.array([0.2, -0.1, 1.5])
    fx, fy, cx, cy = 130.0, 125.0, 81.0, 59.0

    def exact(self: Relocalizer, gray01: np.ndarray) -> np.ndarray:
        uv = cell_centers(-(-gray01.shape[0] // 8), -(-gray01.shape[1] // 8), "colmap").permute(1, 2, 0).double()
        x, y = (uv[..., 0].numpy() - cx) / fx, (uv[..., 1].numpy() - cy) / fy
        depth = 2.0 + 0.4 * x + 0.3 * np.cos(3.0 * y)
        return (np.stack([x * depth, y * depth, depth], -1) - t_true) @ R_true

    monkeypatch.setattr(Relocalizer, "scene_coordinates", exact)
    out = tmp_path / "out"
    rc = main(["localize", "--map", str(files["map"]), "--encoder-weights", str(files["weights"]), "--no-refine",
               "--intrinsics", str(fx), str(fy), str(cx), str(cy), "--out-dir", str(out), str(files["photo"])])
    assert rc == 0, capsys.readouterr().err
    record = json.loads(capsys.readouterr().out)
    assert record["success"] and record["intrinsics_source"] == "intrinsics"
    R, t = read_poses_txt(out / "poses.txt")[str(files["photo"])]
    image = next(iter(pycolmap.Reconstruction(str(out)).images.values()))
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    # transforms.json (one frame cannot be split into train and test for the importer): invert the math.
    cam_to_world = np.array(json.loads((out / "transforms.json").read_text())["frames"][0]["transform_matrix"])
    R_gl = (cam_to_world[:3, :3] @ np.diag([1.0, -1.0, -1.0])).T
    for R_est, t_est in [(R, t), (pose.rotation.matrix(), pose.translation), (R_gl, -R_gl @ cam_to_world[:3, 3])]:
        assert rotation_error_deg(R_est, R_true) < 0.01
        np.testing.assert_allclose(t_est, t_true, atol=1e-3)


@pytest.mark.slow
def test_progress_bar_goes_to_a_terminal_stderr_only(files: dict[str, Path], batch: dict[str, Path]) -> None:
    pty = pytest.importorskip("pty")
    import fcntl
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a new pty is 0 columns wide
    try:
        proc = subprocess.run([sys.executable, "-m", "usvc.cli", "localize", "--map", str(files["map"]),
                               "--encoder-weights", str(files["weights"]), "--focal", "130", str(batch["photos"])],
                              cwd=REPO, stdout=subprocess.PIPE, stderr=slave, text=True, timeout=120)
        os.close(slave)
        terminal = b""
        while select.select([master], [], [], 0.1)[0]:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: the other end is closed
                break
            if not chunk:
                break
            terminal += chunk
    finally:
        os.close(master)
    assert proc.returncode == 0, terminal
    assert len([json.loads(line) for line in proc.stdout.splitlines()]) == 3
    assert b"localize" in terminal and b"3/3" in terminal


@pytest.mark.parametrize("args, cause", [
    (["--camera", "FOO", "1", "2", "3", "{photo}"], "--camera: unknown camera model 'FOO'"),
    (["--camera", "OPENCV", "130", "130", "80", "60", "{photo}"], "--camera OPENCV takes 8 parameters"),
    (["--camera", "PINHOLE", "130", "130", "80", "60", "0", "{photo}"], "--camera PINHOLE takes 4 parameters"),
    (["--camera", "PINHOLE", "-5", "130", "80", "60", "{photo}"], "focal length must be positive"),
    (["--camera", "SIMPLE_PINHOLE", "130", "200", "60", "{photo}"], "outside the 160x120 image"),
    (["--focal", "0", "{photo}"], "--focal for"),
    (["--focal", "130", "{empty}"], "has no images"),
    (["--focal", "130", "{photo}", "{missing_photo}"], "image not found"),
    (["--focal", "130", "{garbage}", "{garbage}"], "none of the 2 photos can be read"),
    (["--focal", "130", "--format", "poses", "{photo}"], "--format needs --out-dir"),
    (["--focal", "130", "--out-dir", "{out}", "--format", "jsonl,ply", "{photo}"], "unknown format 'ply'"),
    (["--focal", "130", "--out-dir", "{photo}", "{photo}"], "is not a folder"),
    (["--focal", "130", "--out-dir", "{out}", "--format", "poses", "{photo}", "{photo}"], "given twice"),
    ([], "no photos given"),
], ids=["camera-model", "camera-too-few", "camera-too-many", "camera-focal", "camera-pp", "focal-zero",
        "empty-folder", "missing-in-batch", "all-garbage", "format-no-dir", "format-unknown", "out-is-file",
        "twice", "no-photos"])
@pytest.mark.slow
def test_batch_errors_before_the_map_loads(files: dict[str, Path], batch: dict[str, Path], tmp_path: Path,
                                           args: list[str], cause: str) -> None:
    paths = {**files, **batch, "out": tmp_path / "out"}
    # A missing map proves the input was rejected before the map was loaded.
    proc = usvc("localize", "--map", files["missing_map"], *(arg.format(**paths) for arg in args))
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("usvc localize: error: ") and cause in lines[0], lines[0]
    assert proc.stdout == "" and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_localize_landmarks_flags(files: dict[str, Path], tmp_path: Path) -> None:
    base = ("localize", "--map", files["map"], "--encoder-weights", files["weights"], "--focal", "130")
    missing = usvc(*base, "--landmarks", tmp_path / "nowhere.h5", files["photo"])
    assert missing.returncode == 1 and "landmarks not found" in missing.stderr
    assert len(missing.stderr.strip().splitlines()) == 1 and "Traceback" not in missing.stderr
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    junk = usvc(*base, "--landmarks", tmp_path / "junk.h5", files["photo"])
    assert junk.returncode == 1 and "junk.h5" in junk.stderr and "Traceback" not in junk.stderr
    plain = usvc(*base, "--refine", "none", files["photo"])  # no landmarks wanted: no note either
    assert plain.returncode == 0 and plain.stderr == ""
    assert json.loads(plain.stdout)["success"] in (True, False)
    bad = usvc(*base, "--refine", "sometimes", files["photo"])
    assert bad.returncode == 2 and "--refine" in bad.stderr
    # --prior none without landmarks: one line saying what it needs, no traceback
    blind = usvc(*base, "--prior", "none", files["photo"])
    assert blind.returncode == 1 and "prior=none needs the map's landmarks" in blind.stderr
    assert len(blind.stderr.strip().splitlines()) == 1 and "Traceback" not in blind.stderr
    assert usvc(*base, "--prior", "maybe", files["photo"]).returncode == 2
    assert usvc(*base, "--final", "maybe", files["photo"]).returncode == 2
    assert usvc(*base, "--refine", "none", "--final", "images", files["photo"]).returncode == 0


def test_photos_are_decoded_one_ahead_in_order(monkeypatch, tmp_path: Path) -> None:
    """`usvc localize` decodes the next photo while one is localized; order and failures are kept."""
    import threading

    import usvc.core.images as images
    from usvc.cli.photo_prefetch import decoded_ahead
    from usvc.core.errors import UsvcError

    started: list[str] = []
    gate = threading.Event()

    def read_photo(path):
        started.append(Path(path).name)
        if Path(path).name == "b.jpg":
            gate.wait(5)
            raise UsvcError("b.jpg: cannot be decoded")
        return f"pixels of {Path(path).name}"

    monkeypatch.setattr(images, "read_photo", read_photo)
    ahead = decoded_ahead([tmp_path / "a.jpg", tmp_path / "b.jpg", None, tmp_path / "d.jpg"])
    first = next(ahead)
    assert first.result() == "pixels of a.jpg"
    for _ in range(500):  # b.jpg is being decoded while the caller still holds only a.jpg
        if "b.jpg" in started:
            break
        threading.Event().wait(0.01)
    assert started == ["a.jpg", "b.jpg"]
    gate.set()
    second = next(ahead)
    with pytest.raises(UsvcError, match="b.jpg: cannot be decoded"):
        second.result()
    assert next(ahead) is None  # already known unreadable: nothing decoded
    assert next(ahead).result() == "pixels of d.jpg"
    assert list(ahead) == [] and started == ["a.jpg", "b.jpg", "d.jpg"]
