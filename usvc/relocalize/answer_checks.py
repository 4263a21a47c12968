"""Verdicts on a finished answer that no single piece of evidence gives: a pose from the photo's
features matched against every landmark alone, and a camera far outside the map
(docs/confidence.md)."""

from __future__ import annotations

import numpy as np

from usvc.relocalize.options import RelocalizeOptions

UNGUIDED_PATHS = ("global",)  # feature answers not guided by the learned pose: the matches to every landmark


def features_alone_verdict(path: str, feature_inliers: int, dense_inliers: int, cells: int,
                           options: RelocalizeOptions) -> str:
    """Why a feature answer is no answer ("" when it stands): it came from unguided matches
    (UNGUIDED_PATHS), the map does not read the photo (fewer than `min_confidence` of the `cells`
    agree with the pose) and fewer than `features_min_inliers_alone` of the photo's features
    support it. Matching against every landmark finds some pose with a few dozen inliers among
    random matches (a photo stretched out of shape, landmarks that are not this map's); an answer
    that the map's cells or clearly more features than that do not back is not trusted
    (docs/confidence.md)."""
    need = options.features_min_inliers_alone
    if path not in UNGUIDED_PATHS or need <= 0 or feature_inliers >= need \
            or dense_inliers >= options.min_confidence * cells:
        return ""
    return (f"the pose rests on the photo's features matched against every landmark alone: {feature_inliers} "
            f"inliers < features_min_inliers_alone {need}, and the map does not read the photo (confidence "
            f"{dense_inliers / cells:.3f} < min_confidence {options.min_confidence:g}): matches by chance give such "
            "poses (a photo stretched or cropped out of shape, another place, or landmarks that are not this map's?)")


FAR_RADII = 100.0  # a camera this many map radii from the map's centre sees it as a few pixels: no answer


def map_extent(xyz: np.ndarray | None) -> tuple[np.ndarray, float] | None:
    """(centre, radius) of the map's 3D points: their per-axis median and the 90th percentile of
    the points' distances from it; None without points."""
    if xyz is None or len(xyz) == 0:
        return None
    centre = np.median(np.asarray(xyz, dtype=np.float64), axis=0)
    radius = float(np.percentile(np.linalg.norm(xyz - centre, axis=1), 90))
    return centre, max(radius, 1e-12)


def far_camera_verdict(center: np.ndarray, extent: tuple[np.ndarray, float] | None) -> str:
    """Why a pose is no answer ("" when it stands): it puts the camera over FAR_RADII map radii
    from the map's centre (mapping cameras sit within a few), where the map would be a speck in
    the photo: a degenerate fit (a far camera with a huge focal length explains a squeezed photo's
    few matches), not a view of the map."""
    if extent is None or not np.all(np.isfinite(center)):
        return ""
    far = float(np.linalg.norm(np.asarray(center, dtype=np.float64) - extent[0])) / extent[1]
    if far <= FAR_RADII:
        return ""
    return (f"the pose puts the camera {far:.3g} map radii from the map's centre (over {FAR_RADII:g}; its mapping "
            "photos are within a few): a degenerate fit, not a view of this map (a photo stretched or cropped out "
            "of shape, or another place?)")
