"""Relocalizer: the pose path on exact synthetic scene coordinates, and its input errors.

An untrained head predicts nothing useful, so the pose tests replace `scene_coordinates` with
the exact coordinates of a known camera looking at a known depth map; everything else (image
decoding, resizing to the map's resolution, intrinsics scaling, cell centres, PnP) is real.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from usvc.core.errors import UsvcError
from usvc.core.pose_errors import rotation_error_deg
from usvc.core.scene import Camera
from usvc.core.undistort import undistorted_camera
from usvc.model.encoder import Encoder, cell_centers
from usvc.model.errors import ModelError
from usvc.model.head import Head, Regressor
from usvc.model.map_file import save_map
from usvc.relocalize.options import BACKENDS
from usvc.relocalize.pose_estimate import PoseEstimate
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both

SHORT_SIDE = 120  # the map's working resolution: 160x120 images, 20x15 cells
WORK_CAMERA = Camera("PINHOLE", 160, 120, (130.0, 125.0, 81.0, 59.0))
R_TRUE = Rotation.from_rotvec([0.1, -0.3, 0.05]).as_matrix()
T_TRUE = np.array([0.2, -0.1, 1.5])


def make_map(tmp_path: Path, seed: int = 0) -> tuple[Path, Path]:
    """A tiny map (random width-0.25 encoder, random head) and the encoder's weight file."""
    torch.manual_seed(seed)
    encoder = Encoder(width=0.25)
    weights = tmp_path / f"encoder{seed}.pt"
    torch.save(encoder.state_dict(), weights)
    head = Head(in_channels=encoder.out_channels, width=64)
    map_path = tmp_path / f"scene{seed}.map.pt"
    save_map(map_path, Regressor(encoder, head), {"short_side": SHORT_SIDE})
    return map_path, weights


def exact_coordinates(h_cells: int, w_cells: int, camera: Camera = WORK_CAMERA) -> np.ndarray:
    """World points seen at the cell centres by (R_TRUE, T_TRUE) on a smooth, non-planar depth map."""
    uv = cell_centers(h_cells, w_cells, "colmap").permute(1, 2, 0).double().numpy()
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    x, y = (uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy
    depth = 2.0 + 0.4 * x + 0.3 * np.cos(3.0 * y)
    x_cam = np.stack([x * depth, y * depth, depth], -1)
    return (x_cam - T_TRUE) @ R_TRUE  # R^T (x_cam - t), row-wise


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return make_map(tmp_path_factory.mktemp("map"))


@pytest.fixture
def exact(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """Patch in exact coordinates; records the (h, w) of every image the network would see."""
    seen: list[tuple[int, int]] = []

    def fake(self: Relocalizer, gray01: np.ndarray) -> np.ndarray:
        h, w = gray01.shape
        seen.append((h, w))
        return exact_coordinates(-(-h // 8), -(-w // 8))

    monkeypatch.setattr(Relocalizer, "scene_coordinates", fake)
    return seen


def photo(width: int, height: int) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)


def assert_true_pose(est: PoseEstimate) -> None:
    assert est.success
    assert rotation_error_deg(est.R, R_TRUE) < 0.1
    assert np.linalg.norm(est.t - T_TRUE) < 1e-3


@pytest.mark.parametrize("backend", BACKENDS)
def test_recovers_pose(tiny_map: tuple[Path, Path], exact: list, backend: str) -> None:
    reloc = Relocalizer(*tiny_map, options=RelocalizeOptions(backend=backend))
    est = reloc.localize(photo(160, 120), (130.0, 125.0, 81.0, 59.0))
    assert_true_pose(est)
    assert exact == [(120, 160)]
    assert est.cells == 15 * 20
    assert 0.0 < est.confidence <= 1.0
    assert est.inliers == est.cells  # exact data: every cell agrees


@pytest.mark.parametrize("intrinsics", [
    Camera("PINHOLE", 160, 120, WORK_CAMERA.params),
    np.array([[130.0, 0.0, 81.0], [0.0, 125.0, 59.0], [0.0, 0.0, 1.0]]),
])
def test_intrinsics_forms(tiny_map: tuple[Path, Path], exact: list, intrinsics: object) -> None:
    assert_true_pose(Relocalizer(*tiny_map).localize(photo(160, 120), intrinsics))


def test_focal_only_centres_principal_point(tiny_map: tuple[Path, Path],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    centred = Camera("PINHOLE", 160, 120, (128.0, 128.0, 80.0, 60.0))
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: exact_coordinates(15, 20, centred))
    assert_true_pose(Relocalizer(*tiny_map).localize(photo(160, 120), 128.0))


def test_resizes_to_map_resolution(tiny_map: tuple[Path, Path], exact: list, tmp_path: Path) -> None:
    """A 2x photo with 2x intrinsics is the same view: resized to the map's short side, same pose."""
    (fx, fy), (cx, cy) = WORK_CAMERA.focal, WORK_CAMERA.principal_point
    path = tmp_path / "big.png"
    cv2.imwrite(str(path), photo(320, 240))
    est = Relocalizer(*tiny_map).localize(path, (2 * fx, 2 * fy, 2 * cx, 2 * cy))
    assert exact == [(120, 160)]
    assert_true_pose(est)


def test_outliers_lower_confidence(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)

    def noisy(self: Relocalizer, gray01: np.ndarray) -> np.ndarray:
        coords = exact_coordinates(15, 20)
        bad = rng.random((15, 20)) < 0.3
        coords[bad] = rng.uniform(-3.0, 3.0, (int(bad.sum()), 3))
        return coords

    monkeypatch.setattr(Relocalizer, "scene_coordinates", noisy)
    est = Relocalizer(*tiny_map).localize(photo(160, 120), WORK_CAMERA)
    assert_true_pose(est)
    assert 0.5 < est.confidence < 0.9


def test_low_confidence_answers_are_failures_with_a_reason(tiny_map: tuple[Path, Path],
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """70 % of the cells are outliers: RANSAC still finds the pose from the other 30 %; the
    answer is kept below min_confidence and reported as a failure (no pose) above it."""
    def mostly_wrong(self: Relocalizer, gray01: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(1)
        coords = exact_coordinates(15, 20)
        bad = rng.random((15, 20)) < 0.7
        coords[bad] = rng.uniform(-3.0, 3.0, (int(bad.sum()), 3))
        return coords

    monkeypatch.setattr(Relocalizer, "scene_coordinates", mostly_wrong)
    kept = Relocalizer(*tiny_map, options=RelocalizeOptions(min_confidence=0.1)).localize(photo(160, 120), WORK_CAMERA)
    assert_true_pose(kept)
    assert 0.2 < kept.confidence < 0.4 and not kept.rejected
    refused = Relocalizer(*tiny_map, options=RelocalizeOptions(min_confidence=0.5)).localize(photo(160, 120),
                                                                                              WORK_CAMERA)
    assert not refused.success and np.isnan(refused.R).all() and np.isnan(refused.t).all()
    assert refused.confidence == pytest.approx(kept.confidence)
    assert refused.rejected == f"confidence {kept.confidence:.3f} < min_confidence 0.5"
    record = refused.to_json()
    assert record["success"] is False and "q_wxyz" not in record and record["rejected"] == refused.rejected


@pytest.mark.parametrize("factor, ok", [(1.0, True), (1.15, True), (2.0, False), (0.5, False)])
def test_a_focal_length_the_map_contradicts_is_a_failure(tiny_map: tuple[Path, Path], exact: list,
                                                         factor: float, ok: bool) -> None:
    """Exact scene coordinates imply the true focal length; a given one 2x off is refused by name,
    one within the tolerance is used."""
    (fx, fy), (cx, cy) = WORK_CAMERA.focal, WORK_CAMERA.principal_point
    reloc = Relocalizer(*tiny_map, options=RelocalizeOptions(focal_tolerance=0.25))
    est = reloc.localize(photo(160, 120), (fx * factor, fy * factor, cx, cy))
    assert est.success is ok
    if ok:
        assert not est.rejected
    else:
        implied = re.match(r"the image implies a focal length ([0-9.]+)x the given one \(tolerance 0.25\)", est.rejected)
        assert implied and float(implied.group(1)) == pytest.approx(1 / factor, rel=0.1), est.rejected
        assert np.isnan(est.R).all() and est.confidence > 0


@pytest.mark.parametrize("model,params", [
    ("OPENCV", (130.0, 125.0, 81.0, 59.0, 0.06, -0.08, 0.001, -0.002)),
    ("SIMPLE_RADIAL", (128.0, 80.0, 60.0, -0.1)),
    ("OPENCV_FISHEYE", (120.0, 120.0, 80.0, 60.0, 0.05, 0.01, 0.0, 0.0)),
])
def test_distorted_query_is_undistorted_first(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch,
                                              model: str, params: tuple) -> None:
    """The network must see the image resampled to the undistorted pinhole camera, and PnP must use
    that camera at the network's resolution: exact coordinates of that view give the true pose."""
    distorted = Camera(model, 160, 120, params)
    pinhole = undistorted_camera(distorted)
    assert (pinhole.width, pinhole.height) != (160, 120) or model == "OPENCV_FISHEYE"

    def fake(self: Relocalizer, gray01: np.ndarray) -> np.ndarray:
        h, w = gray01.shape
        return exact_coordinates(-(-h // 8), -(-w // 8), pinhole.scaled(w, h))

    monkeypatch.setattr(Relocalizer, "scene_coordinates", fake)
    est = Relocalizer(*tiny_map).localize(photo(160, 120), distorted)
    assert_true_pose(est)
    assert est.camera == distorted


@pytest.mark.parametrize("size", [(160, 120), (320, 240)])
def test_unknown_focal_is_estimated_with_the_pose(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch,
                                                  tmp_path: Path, size: tuple[int, int]) -> None:
    centred = Camera("PINHOLE", 160, 120, (128.0, 128.0, 80.0, 60.0))
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: exact_coordinates(15, 20, centred))
    path = tmp_path / "photo.png"
    cv2.imwrite(str(path), photo(*size))
    est = Relocalizer(*tiny_map).localize(path, None)
    assert_true_pose(est)
    scale = size[0] / 160
    assert est.camera is not None and est.camera.model == "SIMPLE_PINHOLE" and est.focal_estimated
    assert est.camera.params == pytest.approx((128.0 * scale, size[0] / 2, size[1] / 2), rel=1e-3)
    assert est.to_json()["camera"]["focal_estimated"] is True


def test_unknown_focal_garbage_fails_cleanly(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """No usable coordinates (the head predicted nothing finite): a failure, not an exception."""
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: np.full((15, 20, 3), np.nan))
    est = Relocalizer(*tiny_map).localize(photo(160, 120), None)
    assert not est.success and est.confidence == 0.0 and "q_wxyz" not in est.to_json()


def test_to_json(tiny_map: tuple[Path, Path], exact: list) -> None:
    out = Relocalizer(*tiny_map).localize(photo(160, 120), WORK_CAMERA).to_json()
    assert set(out) == {"success", "inliers", "cells", "confidence", "seconds",
                        "q_wxyz", "t", "camera_center", "refinement", "camera"}
    assert out["camera"] == {"model": "PINHOLE", "width": 160, "height": 120,
                             "params": list(WORK_CAMERA.params), "focal_estimated": False}
    assert set(out["seconds"]) == {"preprocess", "network", "pnp", "refine", "total"}
    # this map has no keypoints: no refinement, the initial pose is the returned one
    assert out["refinement"]["iterations"] == 0 and out["refinement"]["kept"] is False
    assert np.allclose(out["refinement"]["initial_t"], out["t"])
    assert out["refinement"]["initial_q_wxyz"] == out["q_wxyz"]
    assert np.allclose(out["t"], T_TRUE, atol=1e-3)
    assert np.allclose(out["camera_center"], -R_TRUE.T @ T_TRUE, atol=1e-3)
    failed = PoseEstimate(False, np.full((3, 3), np.nan), np.full(3, np.nan), 3, 300).to_json()
    assert failed["confidence"] == 0.0 and "q_wxyz" not in failed and "t" not in failed
    assert "refinement" not in failed


def test_real_network_runs(tiny_map: tuple[Path, Path]) -> None:
    """Unpatched: the untrained map gives some answer (likely a failure) of the right shape."""
    reloc = Relocalizer(*tiny_map)
    assert reloc.scene_coordinates(np.full((120, 160), 0.5, np.float32)).shape == (15, 20, 3)
    est = reloc.localize(photo(160, 120), 130.0)
    assert est.cells == 300 and 0.0 <= est.confidence <= 1.0


def test_any_map_runs_at_either_precision(tiny_map: tuple[Path, Path]) -> None:
    """The map's weights are fp16 whatever it was trained at: bf16 queries give fp32 coordinates
    close to the fp32 query's; `auto` resolves to one of the two."""
    gray = np.random.default_rng(1).random((120, 160)).astype(np.float32)
    out = {}
    for p in ("fp32", "bf16"):
        reloc = Relocalizer(*tiny_map, options=RelocalizeOptions(precision=p))
        assert reloc.precision == p
        out[p] = reloc.scene_coordinates(gray)
        assert reloc.localize(photo(160, 120), 130.0).cells == 300
    assert out["bf16"].dtype == np.float64 and np.isfinite(out["bf16"]).all()
    scale = np.abs(out["fp32"]).max()
    assert np.abs(out["bf16"] - out["fp32"]).max() < 0.05 * scale
    assert Relocalizer(*tiny_map).precision in ("fp32", "bf16")


def test_bf16_on_a_cpu_runs_the_network_channels_last(tiny_map: tuple[Path, Path]) -> None:
    """bf16 on a CPU takes the channels-last layout (oneDNN's faster one there), fp32 the default:
    the layout changes the order of the sums only, so the coordinates stay within bf16's rounding
    of the default layout's at the same precision."""
    import torch

    gray = np.random.default_rng(2).random((120, 160)).astype(np.float32)
    fp32 = Relocalizer(*tiny_map, options=RelocalizeOptions(precision="fp32"))
    assert fp32.memory_format == torch.contiguous_format
    bf16 = Relocalizer(*tiny_map, options=RelocalizeOptions(precision="bf16"))
    assert bf16.memory_format == torch.channels_last
    first = next(p for p in bf16.regressor.parameters() if p.dim() == 4 and p.shape[1] > 1 and p.shape[2] > 1)
    assert first.is_contiguous(memory_format=torch.channels_last) and not first.is_contiguous()
    last = bf16.scene_coordinates(gray)
    bf16.memory_format = torch.contiguous_format
    bf16.regressor.to(memory_format=torch.contiguous_format)
    plain = bf16.scene_coordinates(gray)
    scale = np.abs(plain).max()
    assert np.abs(last - plain).max() < 0.02 * scale
    assert np.abs(last - fp32.scene_coordinates(gray)).max() < 0.05 * scale


def test_input_errors(tiny_map: tuple[Path, Path], tmp_path: Path) -> None:
    reloc = Relocalizer(*tiny_map)
    with pytest.raises(UsvcError, match="principal point .* outside the 160x120 image"):
        reloc.localize(photo(160, 120), (260.0, 250.0, 162.0, 118.0))  # intrinsics of a 2x photo
    with pytest.raises(UsvcError, match="camera is 320x240 but the image is 160x120"):
        reloc.localize(photo(160, 120), WORK_CAMERA.scaled(320, 240))
    with pytest.raises(UsvcError, match="image not found"):
        reloc.localize(tmp_path / "nope.jpg", 130.0)
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"not a jpeg at all")
    with pytest.raises(UsvcError, match="cannot decode image"):
        reloc.localize(garbage, 130.0)


def test_map_errors(tiny_map: tuple[Path, Path], tmp_path: Path) -> None:
    map_path, weights = tiny_map
    _, other_weights = make_map(tmp_path, seed=1)
    with pytest.raises(ModelError, match="another encoder"):
        Relocalizer(map_path, other_weights)
    truncated = tmp_path / "truncated.map.pt"
    data = map_path.read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelError, match="corrupt or truncated"):
        Relocalizer(truncated, weights)
    with pytest.raises(ModelError, match="map file does not exist"):
        Relocalizer(tmp_path / "missing.map.pt", weights)
    with pytest.raises(UsvcError, match=r"backend='magic' is not one of"):
        Relocalizer(map_path, weights, RelocalizeOptions(backend="magic"))
    with pytest.raises(UsvcError, match="map_path must be the path of a map.pt, got NoneType"):
        Relocalizer(None)  # type: ignore[arg-type]
    with pytest.raises(UsvcError, match="device='banana' is not a torch device usvc runs on"):
        Relocalizer(map_path, weights, device="banana")
    if not torch.cuda.is_available():
        with pytest.raises(UsvcError, match="CUDA is not available"):
            Relocalizer(map_path, weights, device="cuda")


@pytest.mark.parametrize("kwargs, message", [
    ({"max_error_px": -3.0}, r"max_error_px=-3.0 must be > 0"),
    ({"min_inliers": 0}, r"min_inliers=0 must be > 0"),
    ({"min_confidence": 1.5}, r"min_confidence=1.5 must be in \[0, 1\]"),
    ({"focal_tolerance": -0.1}, r"focal_tolerance=-0.1 must be >= 0"),
    ({"precision": "fp16"}, r"precision='fp16' is not one of \['auto', 'bf16', 'fp32'\]"),
    ({"features_final_images": -1}, r"features_final_images=-1 must be >= 0"),
    ({"features_final_comparisons": -1}, r"features_final_comparisons=-1 must be >= 0"),
])
def test_options_are_refused_as_typed(tiny_map: tuple[Path, Path], kwargs: dict, message: str) -> None:
    """The value named is the one given, not the threshold rescaled to the working size."""
    with pytest.raises(UsvcError, match=message):
        Relocalizer(*tiny_map, options=RelocalizeOptions(**kwargs))


def test_api_misuse_is_one_clear_error(tiny_map: tuple[Path, Path], exact: list) -> None:
    reloc = Relocalizer(*tiny_map)
    with pytest.raises(UsvcError, match="intrinsics must be .* got a dict"):
        reloc.localize(photo(160, 120), {"fx": 130.0, "fy": 125.0})  # type: ignore[arg-type]
    with pytest.raises(UsvcError, match="intrinsics must be .* got list"):
        reloc.localize(photo(160, 120), [130.0, "fx"])  # type: ignore[list-item]
    with pytest.raises(UsvcError, match="channels='hsv'"):
        reloc.localize(photo(160, 120), 130.0, channels="hsv")
    with pytest.raises(UsvcError, match=r"image is 4000x32, an aspect ratio of 125.0:1"):
        reloc.localize(photo(4000, 32), 130.0)


def test_bgr_arrays_are_read_as_bgr(tiny_map: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """channels='bgr' gives the network the same grey image as the RGB array would."""
    seen: list[np.ndarray] = []

    def fake(self: Relocalizer, gray01: np.ndarray) -> np.ndarray:
        seen.append(gray01.copy())
        return exact_coordinates(15, 20)

    monkeypatch.setattr(Relocalizer, "scene_coordinates", fake)
    reloc = Relocalizer(*tiny_map)
    rgb = photo(160, 120)
    reloc.localize(rgb, WORK_CAMERA)
    reloc.localize(np.ascontiguousarray(rgb[..., ::-1]), WORK_CAMERA, channels="bgr")
    reloc.localize(np.ascontiguousarray(rgb[..., ::-1]), WORK_CAMERA)  # the common mistake
    np.testing.assert_allclose(seen[0], seen[1], atol=1e-6)  # the weighted sum's order differs
    assert np.abs(seen[0] - seen[2]).max() > 0.05


def test_a_map_finds_the_shipped_encoder_it_names(tmp_path: Path) -> None:
    """A model=small_real map needs no --encoder-weights: it records which shipped file it used."""
    from usvc.model.encoder import encoder_fingerprint, load_encoder_weights
    from usvc.weights import WEIGHTS_DIR

    encoder = load_encoder_weights(WEIGHTS_DIR / "encoder_small_real.pt", width=0.5)
    map_path = tmp_path / "real.map.pt"
    save_map(map_path, Regressor(encoder, Head(in_channels=encoder.out_channels, width=64)),
             {"short_side": SHORT_SIDE, "encoder_file": "encoder_small_real.pt"})
    reloc = Relocalizer(map_path)
    assert encoder_fingerprint(reloc.regressor.encoder) == encoder_fingerprint(encoder)
