"""Options of novel-view rendering from the Gaussian splatting model (the `render` config group,
paper 3.1.3): views orbiting keypoint clusters, kept where enough keypoints stay visible."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import non_negative, positive


@dataclass
class RenderOptions:
    """Novel views rendered from the 3DGS model around keypoint clusters (stages/render.py)."""

    views: int = 30  # novel views to render
    max_angle_deg: float = 20.0  # orbit about the keypoint cluster's centre, away from the source view (degrees)
    max_translation_rel: float = 0.1  # plus a camera translation up to this fraction of the cluster's depth
    cluster_radius_rel: float = 0.15  # a cluster: keypoints within this fraction of the centre's depth
    min_cluster_keypoints: int = 10  # smaller clusters are not orbited
    min_visible_keypoints: int = 20  # a sampled pose is kept when at least this many keypoints are visible
    max_tries: int = 20  # sampled poses per view before giving up on a source view
    width: int = 0  # render width, px; 0 = the prepared images' width
    depth_tolerance: float = 0.05  # a keypoint is visible where |rendered depth - z| < tol * z ...
    min_alpha: float = 0.5  # ... and the rendered opacity there is at least this
    seed: int = 0  # pose sampling seed

    def problems(self) -> list[str]:
        out = positive(self, "views", "max_tries", "depth_tolerance", "min_cluster_keypoints",
                       "min_visible_keypoints", "cluster_radius_rel")
        return out + non_negative(self, "width", "max_angle_deg", "max_translation_rel", "min_alpha")
