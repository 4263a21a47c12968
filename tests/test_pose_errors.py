from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from usvc.core.errors import UsvcError
from usvc.core.pose_errors import rotation_error_deg, summarize, translation_error
from usvc.core.poses_file import read_poses_txt, write_poses_txt

KEYS = {
    "acc_10cm_5deg", "acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "acc_5deg_3pct", "median_rot_deg",
    "median_trans_cm", "median_trans_rel", "median_trans", "ms_per_query", "n_queries", "n_failed",
    "acc_rel_5cm_5deg", "acc_rel_2cm_2deg", "acc_rel_1cm_1deg", "median_trans_rel_cm",
}


def rz(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def test_rotation_error_known_angles():
    I = np.eye(3)
    assert rotation_error_deg(I, I) == 0.0
    assert rotation_error_deg(rz(90), I) == pytest.approx(90.0, abs=1e-12)
    assert rotation_error_deg(I, rz(90)) == pytest.approx(90.0, abs=1e-12)
    assert rotation_error_deg(rz(180), I) == pytest.approx(180.0, abs=1e-12)
    # relative angle, independent of a common rotation
    G = Rotation.from_euler("xyz", [10, -40, 70], degrees=True).as_matrix()
    assert rotation_error_deg(rz(30) @ G, G) == pytest.approx(30.0, abs=1e-10)
    # tiny angles stay accurate (arccos alone would read ~1e-6 deg here)
    assert rotation_error_deg(Rotation.from_rotvec([0, 1e-10, 0]).as_matrix(), I) == pytest.approx(
        np.degrees(1e-10), rel=1e-3)


def test_rotation_error_vectorised():
    R_est = np.stack([np.eye(3), rz(90), rz(-45)])
    R_gt = np.stack([np.eye(3)] * 3)
    np.testing.assert_allclose(rotation_error_deg(R_est, R_gt), [0.0, 90.0, 45.0], atol=1e-12)


def test_translation_error_is_distance_of_camera_centres():
    I = np.eye(3)
    assert translation_error(I, np.zeros(3), I, np.zeros(3)) == 0.0
    assert translation_error(I, np.array([1.0, 2.0, 2.0]), I, np.zeros(3)) == pytest.approx(3.0)
    # same centre, different orientation: no translation error
    c = np.array([1.0, -2.0, 0.5])
    R1, R2 = rz(90), rz(-30)
    assert translation_error(R1, -R1 @ c, R2, -R2 @ c) == pytest.approx(0.0, abs=1e-12)
    # vectorised
    t_est = np.array([[0.0, 0.0, 1.0], [3.0, 4.0, 0.0]])
    d = translation_error(np.stack([I, I]), t_est, np.stack([I, I]), np.zeros((2, 3)))
    np.testing.assert_allclose(d, [1.0, 5.0])


def test_summarize_thresholds_failures_and_medians():
    rot = [1.0, 4.9, 5.0, 1.0, 0.5, 0.0]
    trans = [0.04, 0.049, 0.01, 0.05, 0.009, 0.0]
    failed = [False, False, False, False, False, True]
    s = summarize(rot, trans, metric_scale=1.0, median_depth=None, failed=failed, ms_per_query=12.5)
    assert set(s) == KEYS
    assert s["acc_5cm_5deg"] == pytest.approx(3 / 6)  # rot 5.0 and trans 0.05 are not "< threshold"
    assert s["acc_10cm_5deg"] == pytest.approx(4 / 6)
    assert s["acc_2cm_2deg"] == pytest.approx(1 / 6)
    assert s["acc_1cm_1deg"] == pytest.approx(1 / 6)
    # N = 6: element 3 of the sorted lists, with the failure sorted last as infinity
    assert s["median_rot_deg"] == 4.9
    assert s["median_trans"] == 0.049
    assert s["median_trans_cm"] == pytest.approx(4.9)
    assert s["median_trans_rel"] is None and s["acc_5deg_3pct"] is None
    assert (s["n_queries"], s["n_failed"], s["ms_per_query"]) == (6, 1, 12.5)


def test_summarize_median_takes_floor_half_element():
    s = summarize([4.0, 1.0, 3.0, 2.0], [0.4, 0.1, 0.3, 0.2], 1.0, None, None, 0.0)
    assert s["median_rot_deg"] == 3.0  # third smallest of four, not the mean 2.5
    assert s["median_trans"] == 0.3


def test_summarize_failures_dominate_median_and_nonfinite_counts_as_failed():
    s = summarize([1.0, np.nan, 2.0], [0.01, 0.01, np.inf], 1.0, None, None, 0.0)
    assert s["n_failed"] == 2
    assert s["median_rot_deg"] == np.inf and s["median_trans"] == np.inf
    assert s["acc_5cm_5deg"] == pytest.approx(1 / 3)


def test_summarize_metric_scale_conversion():
    # 0.5 m per unit: 0.1, 0.08, 0.02 units are 5, 4, 1 cm
    s = summarize([1.0, 1.0, 1.0], [0.1, 0.08, 0.02], metric_scale=0.5, median_depth=None, failed=None,
                  ms_per_query=0.0)
    assert s["acc_10cm_5deg"] == 1.0
    assert s["acc_5cm_5deg"] == pytest.approx(2 / 3)
    assert s["acc_2cm_2deg"] == pytest.approx(1 / 3)
    assert s["acc_1cm_1deg"] == 0.0
    assert s["median_trans"] == 0.08
    assert s["median_trans_cm"] == pytest.approx(4.0)


def test_summarize_without_metric_scale():
    s = summarize([1.0, 1.0, 6.0], [0.06, 0.05, 0.0], metric_scale=None, median_depth=2.0, failed=None,
                  ms_per_query=0.0)
    for key in ("acc_10cm_5deg", "acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "median_trans_cm"):
        assert s[key] is None
    assert s["acc_5deg_3pct"] == pytest.approx(1 / 3)  # 0.06 is exactly 3 % of 2.0: not inside
    assert s["median_trans"] == 0.05
    assert s["median_trans_rel"] == pytest.approx(0.025)
    s = summarize([1.0], [0.1], None, None, None, 0.0)
    assert s["acc_5deg_3pct"] is None and s["median_trans_rel"] is None and s["median_trans"] == 0.1


def test_depth_relative_thresholds_read_a_scene_like_7_scenes():
    # a scene scaled to a 1.5 m median depth scores the same at acc_rel_* as at the metric thresholds
    rot = [0.5, 1.5, 1.5, 4.0, 0.5]
    trans_m = [0.009, 0.011, 0.019, 0.049, 0.06]
    metric = summarize(rot, trans_m, metric_scale=1.0, median_depth=1.5, failed=None, ms_per_query=0.0)
    for scale in (0.01, 1.0, 37.0):  # the same geometry in arbitrary units
        s = summarize(rot, [t * scale for t in trans_m], metric_scale=None, median_depth=1.5 * scale,
                      failed=None, ms_per_query=0.0)
        for cm in (5, 2, 1):
            assert s[f"acc_rel_{cm}cm_{cm}deg"] == pytest.approx(metric[f"acc_{cm}cm_{cm}deg"]), (scale, cm)
        assert s["median_trans_rel_cm"] == pytest.approx(metric["median_trans_cm"])
    assert (metric["acc_rel_5cm_5deg"], metric["acc_rel_2cm_2deg"], metric["acc_rel_1cm_1deg"]) == (0.8, 0.6, 0.2)
    s = summarize(rot, trans_m, None, None, None, 0.0)
    assert s["acc_rel_5cm_5deg"] is None and s["median_trans_rel_cm"] is None


def test_summarize_rejects_bad_input():
    with pytest.raises(UsvcError):
        summarize([], [], 1.0, None, None, 0.0)
    with pytest.raises(UsvcError):
        summarize([1.0, 2.0], [0.1], 1.0, None, None, 0.0)
    with pytest.raises(UsvcError):
        summarize([1.0], [0.1], 1.0, None, [True, False], 0.0)


def test_poses_txt_round_trip_and_sign(tmp_path):
    rots = Rotation.from_euler("xyz", [[0, 0, 0], [10, 20, 30], [170, -80, 5], [0, 0, 190]], degrees=True)
    R = rots.as_matrix()
    assert Rotation.from_matrix(R[3]).as_quat()[3] < 0  # scipy hands back w < 0 here: must be flipped
    t = np.array([[0.0, 0.0, 0.0], [1.5, -2.25, 3.0], [1e-9, 123456.789, -0.1], [0.1, 0.2, 0.3]])
    names = ["a.png", "seq 01/frame 2.png", "c", "d"]
    path = tmp_path / "poses.txt"
    write_poses_txt(path, names, R, t)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 5
    for line in lines[1:]:
        q = np.array([float(v) for v in line.split()[-7:-3]])
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    poses = read_poses_txt(path)
    assert list(poses) == names
    for name, Ri, ti in zip(names, R, t):
        np.testing.assert_allclose(poses[name][0], Ri, atol=1e-12)
        np.testing.assert_array_equal(poses[name][1], ti)


def test_poses_txt_negated_and_unnormalised_quaternions_read_the_same(tmp_path):
    R = Rotation.from_euler("y", 40, degrees=True)
    x, y, z, w = R.as_quat()
    path = tmp_path / "poses.txt"
    path.write_text(
        f"# header\n\np {w} {x} {y} {z} 1 2 3\nn {-w} {-x} {-y} {-z} 1 2 3\ns {2*w} {2*x} {2*y} {2*z} 1 2 3\n"
    )
    poses = read_poses_txt(path)
    for name in "pns":
        np.testing.assert_allclose(poses[name][0], R.as_matrix(), atol=1e-12)


@pytest.mark.parametrize("bad", ["x 1 0 0 0 1 2", "x 1 0 0 0 1 2 oops", "x 0 0 0 0 1 2 3", "x 1 0 0 0 nan 2 3"])
def test_poses_txt_malformed_line_names_file_and_line(tmp_path, bad):
    path = tmp_path / "poses.txt"
    path.write_text(f"# name qw qx qy qz tx ty tz\nok 1 0 0 0 0 0 0\n{bad}\n")
    with pytest.raises(UsvcError, match=r"poses\.txt:3"):
        read_poses_txt(path)


def test_poses_txt_duplicate_and_missing_file(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("a 1 0 0 0 0 0 0\na 1 0 0 0 0 0 0\n")
    with pytest.raises(UsvcError, match=r"poses\.txt:2.*duplicate"):
        read_poses_txt(path)
    with pytest.raises(UsvcError, match="missing"):
        read_poses_txt(tmp_path / "missing.txt")
