"""An answer from the photo's features matched against every landmark (the global pass, not guided
by the learned pose) that the map does not read (few of its cells agree) stands only on clearly
more feature inliers than matches by chance give a pose: a photo stretched out of shape, or
landmarks whose descriptors are not this map's, got `success: true` from some 20-odd random matches
before (docs/confidence.md). Right answers of either kind of support keep their poses.

The rule itself (`features_alone_verdict`), then the relocalizer on the synthetic scene of
test_fallback (points on a smooth surface, random SIFT-like descriptors, five mapping cameras).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_fallback import N_POINTS, WRONG, _map, scene
from test_refinement import CAM, errors, photo

from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.relocalizer import Relocalizer, features_alone_verdict

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both

CELLS = 768  # a 320 x 192 working image's 8 x 8 cells


def test_a_global_answer_from_a_handful_of_inliers_that_the_map_does_not_read_is_refused():
    opts = RelocalizeOptions()
    # the stretched photo (2 of the cells agree) and the scrambled landmarks (22 random matches)
    for inliers, dense in ((26, 2), (22, 1), (39, 0)):
        why = features_alone_verdict("global", inliers, dense, CELLS, opts)
        assert f"{inliers} inliers < features_min_inliers_alone 40" in why, why
        assert f"confidence {dense / CELLS:.3f} < min_confidence 0.1" in why, why


@pytest.mark.parametrize("path, inliers, dense", [
    ("global", 40, 0),  # enough features alone (office's sideways photos: hundreds)
    ("global", 22, 77),  # the map reads the photo: 10 % of the cells agree with the pose
    ("guided", 22, 0),  # guided by the learned pose: not this rule's
    ("verified", 22, 0),  # SIFT + PnP's verified pairs: not this rule's
    ("dense", 0, 0),
])
def test_answers_with_support_of_either_kind_stand(path: str, inliers: int, dense: int):
    assert features_alone_verdict(path, inliers, dense, CELLS, RelocalizeOptions()) == ""


def test_the_threshold_is_an_option_and_zero_turns_the_check_off():
    assert features_alone_verdict("global", 22, 0, CELLS, RelocalizeOptions(features_min_inliers_alone=0)) == ""
    assert features_alone_verdict("global", 22, 0, CELLS, RelocalizeOptions(features_min_inliers_alone=20)) == ""
    assert "features_min_inliers_alone 60" in features_alone_verdict(
        "global", 59, 0, CELLS, RelocalizeOptions(features_min_inliers_alone=60))
    assert RelocalizeOptions(features_min_inliers_alone=-1).problems() == [
        "features_min_inliers_alone=-1 must be >= 0 (0: no check)"]
    assert RelocalizeOptions().problems() == []


def _few_matches() -> tuple:
    """The synthetic scene with only 25 of the photo's keypoints on landmarks (the rest distractors)."""
    landmarks, feats = scene()
    keep = np.r_[np.arange(25), np.arange(N_POINTS, 2 * N_POINTS)]
    return landmarks, QueryFeatures(feats.uv[keep], feats.descriptor[keep])


def test_the_relocalizer_refuses_a_global_answer_on_a_few_dozen_inliers(tmp_path: Path, monkeypatch):
    """The learned pose is far off (the map does not read the photo) and the matches to every
    landmark give a pose on 25 inliers: refused, the evidence and its confidence still reported;
    the check off, the same pose is the answer."""
    landmarks, feats = _few_matches()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=WRONG)
    est = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), CAM)
    assert not est.success and est.pose_found and np.isnan(est.R).all()
    assert "inliers < features_min_inliers_alone 40" in est.rejected and "map does not read" in est.rejected
    assert est.feature_inliers < 40 and est.confidence < 0.1
    record = est.to_json()
    assert record["rejected"] == est.rejected and "evidence" in record
    assert "global" in [h["path"] for h in record["evidence"]["hypotheses"]]
    off = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(features_min_inliers_alone=0)).localize(
        photo(), CAM)
    assert off.success and off.refine_path == "global", off.rejected
    assert off.feature_inliers == est.feature_inliers and errors(off.R, off.t)[0] < 0.5


def test_a_global_answer_on_many_inliers_still_stands(tmp_path: Path, monkeypatch):
    """Every keypoint of the photo on its landmark: the same far-off learned pose, and the features'
    answer stands on hundreds of inliers though none of the map's cells agree with it."""
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=WRONG)
    est = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), CAM)
    assert est.success and est.refine_path in ("global", "verified") and est.confidence < 0.1, est.rejected
    assert est.feature_inliers >= 40 and errors(est.R, est.t)[0] < 0.2


def test_a_camera_far_outside_the_map_is_no_answer():
    """A degenerate fit (a squeezed photo's few matches explained by a far camera with a huge focal
    length: bird's query 161 squeezed to 3:4 came out 1.3e5 map radii away) is refused; cameras
    around the map, as mapping photos sit (bird's orbit: up to 4.8 radii), stand."""
    from usvc.relocalize.relocalizer import FAR_RADII, far_camera_verdict, map_extent

    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(2000, 3)) + np.array([5.0, -2.0, 1.0])
    extent = map_extent(xyz)
    centre, radius = extent
    np.testing.assert_allclose(centre, [5.0, -2.0, 1.0], atol=0.1)
    assert 2.3 < radius < 2.7  # the 90th percentile of a 3D unit Gaussian cloud's distances: 2.5 sigma
    assert far_camera_verdict(centre + np.array([0.0, 0.0, 5 * radius]), extent) == ""
    assert far_camera_verdict(centre + np.array([0.0, 0.0, 0.99 * FAR_RADII * radius]), extent) == ""
    why = far_camera_verdict(centre + np.array([1.3e5 * radius, 0.0, 0.0]), extent)
    assert "1.3e+05 map radii" in why and "degenerate" in why
    assert far_camera_verdict(np.array([np.nan] * 3), extent) == ""  # no pose: other checks say why
    assert far_camera_verdict(centre * 1e9, None) == "" and map_extent(np.zeros((0, 3))) is None
