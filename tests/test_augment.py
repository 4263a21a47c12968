from __future__ import annotations

import cv2
import numpy as np
import pytest

from usvc.buffer.augment import augment, roll_rotation, warp_view

H, W = 480, 640


def _texture(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A smooth pattern, so bilinear resampling error stays far below a half-pixel shift's."""
    return 0.5 + 0.2 * np.sin(0.05 * u + 0.03 * v) + 0.2 * np.cos(0.04 * v - 0.02 * u)


def _image(h: int = H, w: int = W) -> np.ndarray:
    """The texture sampled at COLMAP pixel centres (j + 0.5, i + 0.5)."""
    v, u = np.mgrid[0:h, 0:w] + 0.5
    return _texture(u, v).astype(np.float32)


def _camera(fx: float, fy: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    K = np.array([[fx, 0.0, 331.7], [0.0, fy, 228.4], [0.0, 0.0, 1.0]])
    R, _ = cv2.Rodrigues(rng.normal(size=3))
    return K, R, rng.normal(size=3)


def _points(K: np.ndarray, R: np.ndarray, t: np.ndarray, seed: int, n: int = 200) -> np.ndarray:
    """World points that project inside a 640x480 image at depths 1..20."""
    rng = np.random.default_rng(seed + 100)
    uv1 = np.c_[rng.uniform(0, W, n), rng.uniform(0, H, n), np.ones(n)]
    p = rng.uniform(1, 20, (n, 1)) * (np.linalg.inv(K) @ uv1.T).T
    return (p - t) @ R  # R^T (p - t) row-wise


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    h = (K @ (X @ R.T + t).T).T
    return h[:, :2] / h[:, 2:]


def _apply(A: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return uv @ A[:2, :2].T + A[:2, 2]


@pytest.mark.parametrize("fx,fy", [(525.0, 525.0), (500.0, 560.0)])
@pytest.mark.parametrize("seed", range(4))
def test_projection_consistency_random_draws(fx: float, fy: float, seed: int) -> None:
    K, R, t = _camera(fx, fy, seed)
    X = _points(K, R, t, seed)
    view = augment(_image(), K, R, t, np.random.default_rng(seed))
    np.testing.assert_allclose(view.R_world_to_cam @ view.R_world_to_cam.T, np.eye(3), atol=1e-12)
    expected = _apply(view.pixel_transform, _project(K, R, t, X))
    np.testing.assert_allclose(_project(view.K, view.R_world_to_cam, view.t_world_to_cam, X), expected, atol=1e-6)


@pytest.mark.parametrize("angle", [-12.0, 12.0])
@pytest.mark.parametrize("fx,fy", [(525.0, 525.0), (500.0, 560.0)])
def test_projection_consistency_both_signs(angle: float, fx: float, fy: float) -> None:
    K, R, t = _camera(fx, fy, 7)
    X = _points(K, R, t, 7)
    view = warp_view(_image(), K, R, t, scale=1.1, angle_deg=angle)
    expected = _apply(view.pixel_transform, _project(K, R, t, X))
    np.testing.assert_allclose(_project(view.K, view.R_world_to_cam, view.t_world_to_cam, X), expected, atol=1e-6)
    np.testing.assert_allclose(view.K, np.diag([1.1, 1.1, 1.0]) @ K, rtol=1e-12)


@pytest.mark.parametrize("scale", [1.0, 1.3, 0.75])
@pytest.mark.parametrize("angle", [-10.0, 10.0])
def test_image_content_follows_pixel_transform(scale: float, angle: float) -> None:
    """The warped image at pixel q shows the source texture at pixel_transform^-1 q."""
    K, R, t = _camera(525.0, 525.0, 1)
    view = warp_view(_image(), K, R, t, scale=scale, angle_deg=angle)
    h, w = view.image.shape
    v, u = np.mgrid[0:h, 0:w] + 0.5
    q = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    src = np.linalg.inv(view.pixel_transform) @ q
    inside = (src[0] > 3) & (src[0] < W - 3) & (src[1] > 3) & (src[1] < H - 3)
    assert inside.mean() > 0.7
    err = np.abs(view.image.ravel()[inside] - _texture(src[0], src[1])[inside])
    assert err.max() < 2e-3  # a half-pixel offset would give ~1e-2
    assert view.mask.ravel()[inside].all()


@pytest.mark.parametrize("seed", range(3))
def test_scene_point_looks_the_same_before_and_after(seed: int) -> None:
    """Sample a random texture at a point's projection in both images (coarse check)."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.uniform(0, 1, (H, W)).astype(np.float32), (0, 0), 6)
    image = (noise - noise.min()) / (noise.max() - noise.min())
    K, R, t = _camera(525.0, 525.0, seed)
    X = _points(K, R, t, seed, n=500)
    view = augment(image, K, R, t, rng, brightness=(1.0, 1.0), contrast=(1.0, 1.0))

    def sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
        m = (uv - 0.5).astype(np.float32).reshape(-1, 1, 2)
        return cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR).ravel()

    uv0 = _project(K, R, t, X)
    uv1 = _project(view.K, view.R_world_to_cam, view.t_world_to_cam, X)
    h, w = view.image.shape
    keep = (
        (uv0 > 8).all(1) & (uv0[:, 0] < W - 8) & (uv0[:, 1] < H - 8)
        & (uv1 > 8).all(1) & (uv1[:, 0] < w - 8) & (uv1[:, 1] < h - 8)
    )
    assert keep.sum() > 100
    diff = np.abs(sample(image, uv0[keep]) - sample(view.image, uv1[keep]))
    assert np.median(diff) < 0.01 and diff.max() < 0.05


def test_rotation_sign_matches_opencv() -> None:
    K, R, t = _camera(525.0, 525.0, 2)
    for angle in (-15.0, 4.0, 15.0):
        view = warp_view(_image(), K, R, t, angle_deg=angle)
        cx, cy = K[0, 2], K[1, 2]
        # In OpenCV's integer-centre coordinates the principal point is (cx - 0.5, cy - 0.5).
        M = cv2.getRotationMatrix2D((cx - 0.5, cy - 0.5), angle, 1.0)
        shift = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1.0]])
        A_ocv = np.linalg.inv(shift) @ view.pixel_transform @ shift
        np.testing.assert_allclose(A_ocv[:2], M, atol=1e-9)
        np.testing.assert_allclose(view.R_world_to_cam, roll_rotation(angle) @ R, atol=1e-12)
    # Positive angle: a point right of the principal point moves up on screen (y decreases).
    view = warp_view(_image(), K, R, t, angle_deg=10.0)
    moved = _apply(view.pixel_transform, np.array([[K[0, 2] + 100.0, K[1, 2]]]))
    assert moved[0, 1] < K[1, 2]


def test_scale_changes_size_and_intrinsics() -> None:
    K, R, t = _camera(525.0, 525.0, 3)
    view = warp_view(_image(), K, R, t, scale=1.5)
    assert view.image.shape == (720, 960)
    np.testing.assert_allclose(view.K, np.diag([1.5, 1.5, 1.0]) @ K)
    np.testing.assert_array_equal(view.R_world_to_cam, R)
    # Rounded sizes scale each axis by its own factor.
    view = warp_view(_image(481, 641), K, R, t, scale=0.7)
    assert view.image.shape == (336, 448)
    np.testing.assert_allclose(view.K, np.diag([448 / 641, 336 / 481, 1.0]) @ K)
    # Portrait images keep the short side at short_side * scale too.
    view = warp_view(_image(600, 400), K, R, t, scale=1.0)
    assert view.image.shape == (720, 480)


def test_scale_draws_stay_in_range() -> None:
    K, R, t = _camera(525.0, 525.0, 4)
    rng = np.random.default_rng(0)
    for _ in range(20):
        view = augment(_image(), K, R, t, rng, max_rotation_deg=0.0, short_side=96)
        assert 1 / 1.5 <= view.scale <= 1.5
        assert view.image.shape[0] == round(96 * view.scale)


def test_mask_all_valid_without_rotation_and_invalid_corners_with() -> None:
    K, R, t = _camera(525.0, 525.0, 5)
    view = warp_view(_image(), K, R, t, scale=1.0, angle_deg=0.0)
    assert view.image.shape == (H, W) and view.mask.shape == (H, W)
    assert view.mask.all()
    np.testing.assert_array_equal(view.image, _image())
    view = warp_view(_image(), K, R, t, scale=1.0, angle_deg=15.0)
    assert view.mask.dtype == bool and not view.mask.all()
    assert not view.mask[0, 0] and not view.mask[-1, -1] and view.mask[H // 2, W // 2]
    # Valid exactly where the pixel centre maps back inside the source image (up to OpenCV's
    # fixed-point rounding on the border); more than a pixel outside, the image is 0.
    v, u = np.mgrid[0:H, 0:W] + 0.5
    src = np.linalg.inv(view.pixel_transform) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    inside = ((src[0] >= 0) & (src[0] < W) & (src[1] >= 0) & (src[1] < H)).reshape(H, W)
    assert (view.mask != inside).mean() < 1e-3
    far = ((src[0] < -1) | (src[0] > W + 1) | (src[1] < -1) | (src[1] > H + 1)).reshape(H, W)
    assert far.any() and (view.image[far] == 0).all()


def test_brightness_and_contrast() -> None:
    K, R, t = _camera(525.0, 525.0, 6)
    flat = np.full((H, W), 0.5, dtype=np.float32)
    view = warp_view(flat, K, R, t, brightness=1.08)
    np.testing.assert_allclose(view.image, 0.54, atol=1e-6)
    img = _image()
    view = warp_view(img, K, R, t, contrast=0.9)
    assert view.image.mean() == pytest.approx(img.mean(), abs=1e-5)
    assert view.image.std() == pytest.approx(0.9 * img.std(), rel=1e-4)
    rng = np.random.default_rng(1)
    for _ in range(20):
        view = augment(img, K, R, t, rng, short_side=96)
        assert 0.9 <= view.brightness <= 1.1 and 0.9 <= view.contrast <= 1.1
        assert -15.0 <= view.angle_deg <= 15.0
        assert view.image.dtype == np.float32
        assert view.image.min() >= 0.0 and view.image.max() <= 1.0
    bright = warp_view(np.clip(img * 1.5, 0, 1), K, R, t, brightness=1.1)
    assert bright.image.max() <= 1.0


def test_deterministic_given_rng() -> None:
    K, R, t = _camera(525.0, 525.0, 8)
    a = augment(_image(), K, R, t, np.random.default_rng(42))
    b = augment(_image(), K, R, t, np.random.default_rng(42))
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_array_equal(a.K, b.K)
    for name in ("scale", "angle_deg", "brightness", "contrast"):
        assert getattr(a, name) == getattr(b, name)


def test_rejects_colour_image() -> None:
    K, R, t = _camera(525.0, 525.0, 9)
    with pytest.raises(ValueError):
        warp_view(np.zeros((H, W, 3), dtype=np.float32), K, R, t)
