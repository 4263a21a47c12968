import numpy as np
import pytest

from usvc.core.errors import KeypointError
from usvc.keypoints.keypoints_file import write_keypoints
from usvc.keypoints.scoring import KeypointOptions, score_points, select_keypoints
from usvc.sfm.tracks_file import Tracks

OPTS = KeypointOptions(tau=1.5, sigma=0.25, weights="uniform", reprojection_scale_px=1.0, min_track_length=2)


def make_tracks(descs_per_point, errors=None):
    lengths = [len(d) for d in descs_per_point]
    desc = np.concatenate(descs_per_point).astype(np.uint8)
    n, t = len(lengths), len(desc)
    return Tracks(
        image_names=[f"im{i}" for i in range(max(lengths))], R=np.tile(np.eye(3), (max(lengths), 1, 1)),
        t=np.zeros((max(lengths), 3)), K=np.tile(np.eye(3), (max(lengths), 1, 1)),
        point_id=np.arange(n) + 100, xyz=np.random.default_rng(0).normal(size=(n, 3)),
        rgb=np.zeros((n, 3), np.uint8), error=np.zeros(n, np.float32),
        offset=np.concatenate([[0], np.cumsum(lengths)]),
        obs_image=np.concatenate([np.arange(k) for k in lengths]).astype(np.int32),
        obs_uv=np.zeros((t, 2), np.float32), obs_descriptor=desc,
        obs_error=np.zeros(t, np.float32) if errors is None else np.asarray(errors, np.float32),
    )


def unit(v):
    return v / np.linalg.norm(v)


def test_score_matches_the_paper_formula():
    rng = np.random.default_rng(1)
    d = rng.integers(0, 255, size=(3, 128)).astype(np.uint8)
    tracks = make_tracks([d])
    score, phi = score_points(tracks, OPTS)
    dn = d.astype(np.float64) / np.linalg.norm(d.astype(np.float64), axis=1, keepdims=True)
    mean = dn.mean(0)
    expected = np.exp(-np.sum((dn - mean) ** 2, axis=1) / (2 * 0.25**2)).sum()
    assert score[0] == pytest.approx(expected, rel=1e-5)
    np.testing.assert_allclose(phi[0], mean, atol=1e-6)


def test_consistent_track_is_kept_and_inconsistent_dropped():
    rng = np.random.default_rng(2)
    base = rng.integers(0, 200, size=128)
    consistent = np.stack([np.clip(base + rng.integers(-3, 4, 128), 0, 255) for _ in range(4)])
    inconsistent = rng.integers(0, 255, size=(4, 128))
    kp = select_keypoints(make_tracks([consistent, inconsistent]), OPTS)
    assert kp.index.tolist() == [0]
    assert kp.score[0] > 3.5 and kp.score[1] < 1.5


def test_identical_descriptors_score_equals_weight_sum():
    d = np.tile(np.arange(128, dtype=np.uint8), (5, 1))
    score, _ = score_points(make_tracks([d]), OPTS)
    assert score[0] == pytest.approx(5.0)
    errs = [0.0, 1.0, 1.0, 3.0, 0.0]
    opts = KeypointOptions(1.5, 0.25, "reprojection", 1.0, 2)
    score, _ = score_points(make_tracks([d], errs), opts)
    assert score[0] == pytest.approx(1 + 0.5 + 0.5 + 0.1 + 1)


def test_short_tracks_score_zero():
    d = np.tile(np.arange(128, dtype=np.uint8), (1, 1))
    score, _ = score_points(make_tracks([d, np.tile(d, (3, 1))]), OPTS)
    assert score[0] == 0.0 and score[1] == pytest.approx(3.0)


def test_tau_that_keeps_nothing_is_a_clear_error():
    d = np.tile(np.arange(128, dtype=np.uint8), (2, 1))
    with pytest.raises(KeypointError, match="keypoints.tau=9.*keeps no keypoint"):
        select_keypoints(make_tracks([d]), KeypointOptions(9.0, 0.25, "uniform", 1.0, 2))


def test_written_keypoints_keep_their_observations(tmp_path):
    import h5py

    rng = np.random.default_rng(3)
    base = rng.integers(0, 200, size=128)
    pts = [np.tile(base, (k, 1)) for k in (2, 3, 4)]
    pts[1] = rng.integers(0, 255, size=(3, 128))
    tracks = make_tracks(pts)
    kp = select_keypoints(tracks, OPTS)
    write_keypoints(tmp_path / "k.h5", kp, tracks)
    with h5py.File(tmp_path / "k.h5") as h5:
        assert h5["keypoints/id"][()].tolist() == [100, 102]
        assert h5["keypoints/track_offset"][()].tolist() == [0, 2, 6]
        assert h5["obs/image"][()].tolist() == [0, 1, 0, 1, 2, 3]
