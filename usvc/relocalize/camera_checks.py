"""Checks of a query's camera that do not need the map: a focal length no camera has (or, estimated
on the map's coordinates, none like the map's cameras'), non-square pixels or a principal point far
off the centre (warnings), and a photo that looks stretched to another aspect ratio (a camera with
non-square pixels explains its correspondences clearly better); and the words that refuse a given
focal length (`focal_reason`)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from usvc.core.geometry import field_of_view_deg
from usvc.core.scene import Camera
from usvc.relocalize.pnp import project_points, reprojection_inliers

# A pinhole focal length (px) over the photo's long side outside this range is no camera's: a
# field of view over ~157 deg or under ~3 deg (a fisheye's pinhole focal is ~0.3, a 10x zoom ~7).
FOCAL_RANGE = (0.1, 20.0)
# An estimated focal length (over the long side) more than this factor outside the range of the
# map's own cameras (metadata focal_range) is no reading of this photo: a phone's lenses span ~3x.
FOCAL_SPREAD = 3.0
MAX_PIXEL_ASPECT = 1.25  # fx / fy (either way) beyond this: the photo was resized to another aspect
PRINCIPAL_OFFSET = 0.1  # principal point farther than this fraction of the size from the centre: a warning
# A camera with non-square pixels is no better than the square-pixel one while the latter keeps
# this fraction of its support.
SQUARE_PIXEL_KEPT_FRACTION = 0.8
# The focal lengths a photo's matches allow: P4Pf's estimate this many standard deviations of
# ln(focal) either way (Gauss-Newton covariance at its inliers). The features refuse a given focal
# length only when none of them is within focal_tolerance of it, and vouch for it only when all are.
FOCAL_SIGMAS = 4.0


def implausible_focal(focal: float, width: int, height: int, what: str) -> str:
    """Why `focal` (px) is no camera's for a width x height photo ("" when it is plausible);
    `what` names it, its value included."""
    long_side = max(width, height)
    low, high = FOCAL_RANGE
    if np.isfinite(focal) and low * long_side <= focal <= high * long_side:
        return ""
    fovs = (field_of_view_deg(high * long_side, long_side), field_of_view_deg(low * long_side, long_side))
    return (f"{what} is implausible for a {width}x{height} photo: a field of view of "
            f"{field_of_view_deg(focal, long_side):.3g} deg across its long side, where cameras have "
            f"{fovs[0]:.0f}-{fovs[1]:.0f} deg")


def estimated_focal_problem(focal: float, width: int, height: int, focal_range: tuple[float, float] | None) -> str:
    """Why `focal` (px), estimated with the pose on the map's coordinates of a width x height photo,
    is no reading of the photo ("" when it is one): no camera's (`implausible_focal`), or over
    FOCAL_SPREAD x off the map's own cameras' (`focal_range`: theirs over the long side; None for a
    map without it)."""
    why = implausible_focal(focal, width, height, f"the focal length estimated with the pose ({focal:.4g} px)")
    ratio, lo_hi = focal / max(width, height), focal_range
    if not why and lo_hi and not lo_hi[0] / FOCAL_SPREAD <= ratio <= lo_hi[1] * FOCAL_SPREAD:
        why = (f"the focal length estimated with the pose ({focal:.4g} px, {ratio:.2f}x the long side) "
               f"is over {FOCAL_SPREAD:g}x off the map's cameras' ({lo_hi[0]:.2f}-{lo_hi[1]:.2f}x)")
    return why


def intrinsics_warnings(camera: Camera) -> list[str]:
    """Doubts about intrinsics that do not stop a query: non-square pixels (fx/fy beyond
    MAX_PIXEL_ASPECT: a photo stretched to another aspect ratio) and a principal point far from
    the image's centre (cx and cy swapped, or intrinsics of a crop)."""
    out = []
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    w, h = camera.width, camera.height
    if max(fx, fy) > MAX_PIXEL_ASPECT * min(fx, fy):
        out.append(f"fx/fy = {fx / fy:.2f}: a camera's pixels are square (fx = fy), so this photo was resized to "
                   "another aspect ratio, or the intrinsics are wrong; a stretched photo localizes poorly")
    dx, dy = abs(cx - w / 2) / w, abs(cy - h / 2) / h
    if max(dx, dy) > PRINCIPAL_OFFSET:
        swapped = abs(cy - w / 2) / w <= PRINCIPAL_OFFSET and abs(cx - h / 2) / h <= PRINCIPAL_OFFSET
        out.append(f"principal point ({cx:g}, {cy:g}) is {100 * dx:.0f} % of the width and {100 * dy:.0f} % of the "
                   f"height off the centre of the {w}x{h} photo (cameras: a few %): "
                   + ("cx and cy look swapped" if swapped else "intrinsics of another image or a crop?"))
    return out


def _project(points: np.ndarray, x: np.ndarray, f0: float, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of `points` under x = (rotation vector, t, log fx/f0, log fy/f0)."""
    fx, fy = f0 * np.exp(x[6]), f0 * np.exp(x[7])
    (cx, cy), w, h = camera.principal_point, camera.width, camera.height
    return project_points(Camera("PINHOLE", w, h, (fx, fy, cx, cy)), points,
                          Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6])


def stretch_verdict(pixels: np.ndarray, points: np.ndarray, camera: Camera, R: np.ndarray, t: np.ndarray,
                    max_error_px: float) -> str:
    """Why the photo looks stretched ("" when it does not): a pinhole camera with non-square pixels
    (fx/fy beyond MAX_PIXEL_ASPECT), fitted with the pose from (camera, R, t), explains clearly more
    correspondences than `camera` (square pixels) does: its inliers are at most
    SQUARE_PIXEL_KEPT_FRACTION of the fitted camera's. A photo resized to another aspect ratio
    looks like this; where the two explain about as much, the photo cannot tell and this says nothing."""
    p2 = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    p3 = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    base = reprojection_inliers(camera, p2, p3, R, t, max_error_px)
    if base.sum() < 8:
        return ""
    f0 = camera.focal[0]
    x = np.concatenate([Rotation.from_matrix(R).as_rotvec(), np.asarray(t, dtype=np.float64).reshape(3), [0.0, 0.0]])
    mask = base
    for _ in range(3):  # fit on the inliers, re-select them, as ACE's pose refinement does
        def residuals(v: np.ndarray, m: np.ndarray = mask) -> np.ndarray:
            uv, _ = _project(p3[m], v, f0, camera)
            return np.nan_to_num(uv - p2[m], nan=1e6, posinf=1e6, neginf=-1e6).reshape(-1)  # a point at z = 0

        x = least_squares(residuals, x, loss="soft_l1", f_scale=max_error_px, max_nfev=200).x
        uv, z = _project(p3, x, f0, camera)
        err = np.linalg.norm(uv - p2, axis=1)
        grown = np.isfinite(err) & (z > 0) & (err < max_error_px)
        if grown.sum() < 8:
            return ""
        mask = grown
    aspect = float(np.exp(x[6] - x[7]))
    support, kept = int(mask.sum()), int(base.sum())
    if max(aspect, 1.0 / aspect) <= MAX_PIXEL_ASPECT or kept > SQUARE_PIXEL_KEPT_FRACTION * support:
        return ""
    return (f"the photo looks stretched: a camera with fx/fy = {aspect:.2f} explains {support / kept:.1f}x as many "
            "of its correspondences as the square-pixel one estimated with the pose (a camera's pixels are square): was it "
            "resized to another aspect ratio? Localize the original photo, or give its intrinsics")


def focal_reason(evidence: str, ratio: float, tolerance: float, source: str) -> str:
    """Why a given focal length is refused; `source` names where it came from (e.g. EXIF)."""
    if source:
        return (f"{source} disagrees with the photo's content: {evidence} a focal length {ratio:.2f}x it "
                f"(tolerance {tolerance:g})")
    return f"{evidence} a focal length {ratio:.2f}x the given one (tolerance {tolerance:g}); check the intrinsics"
