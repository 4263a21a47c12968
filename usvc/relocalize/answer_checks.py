"""Verdicts on a finished answer that no single piece of evidence gives: a pose from the photo's
features matched against every landmark alone, a camera far outside the map, a focal length that
nothing supports, and the notes on a given focal length that nothing could check
(docs/confidence.md)."""

from __future__ import annotations

import numpy as np

from usvc.core.geometry import camera_centers
from usvc.core.scene import Camera
from usvc.relocalize.options import RelocalizeOptions

FOCAL_UNCHECKED = ("the given focal length was not checked: this view is too shallow for the photo's features to "
                   "tell it, and the map did not read the photo well enough to; a wrong one would move the pose "
                   "along the optical axis")
MAP_DOES_NOT_JUDGE = ("the given focal length was not checked: this map does not tell its own photos' focal lengths "
                      "within focal_tolerance (a longer training lets it)")
FOCAL_UNCHECKED_MAP = (MAP_DOES_NOT_JUDGE + ", and this view is too shallow for the photo's features to; a wrong one "
                       "would move the pose along the optical axis")
# The learned pose "describes" the photo when it is this close to the feature pose.
AGREE_DEG, AGREE_DEPTH_FRACTION = 15.0, 0.5
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


def poses_agree(R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray, median_depth: float) -> bool:
    """Whether two world-to-camera poses are the same view up to what a coarse map gets wrong:
    within AGREE_DEG of rotation and AGREE_DEPTH_FRACTION of the median scene depth apart."""
    cos = (np.trace(R1 @ R2.T) - 1.0) / 2.0
    angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    gap = float(np.linalg.norm(camera_centers(R1, t1) - camera_centers(R2, t2)))
    return angle <= AGREE_DEG and gap <= AGREE_DEPTH_FRACTION * median_depth


def unsupported_focal(camera: Camera, dense_inliers: int, cells: int, from_map: bool,
                      options: RelocalizeOptions) -> str:
    """Why a feature pose of a photo without intrinsics is no answer: its focal length came
    neither from the photo's features (P4Pf) nor from a map that reads the photo (min_confidence
    of the cells agreeing), so nothing supports the camera the pose was solved with."""
    source = (f"the map's coordinates, which only {dense_inliers} of the {cells} cells agree with (confidence "
              f"{dense_inliers / cells:.3f} < min_confidence {options.min_confidence:g})" if from_map
              else "no evidence (the map's coordinates gave none)")
    return (f"no focal length to trust: the one the pose was solved with ({camera.focal[0]:.4g} px) comes from "
            f"{source}, and the photo's features give none: stretched, cropped or not of this place? Give its "
            "intrinsics")


def no_pose_reason(min_inliers: int, dense_inliers: int, cells: int, features_why: str | None) -> str:
    """Why neither the map's coordinates (`dense_inliers` of `cells` at best) nor the features
    (`features_why`; None where they did not run) gave a pose."""
    why = (f"no pose: RANSAC-PnP on the map's scene coordinates found none that min_inliers="
           f"{min_inliers} of the {cells} cells agree with ({dense_inliers} at best)")
    if features_why is not None:
        why += f", and the photo's features gave none ({features_why or 'no match to the landmarks'})"
    return why + ": not a view of this map's scene, or too dark, blurred or featureless?"
