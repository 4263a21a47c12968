"""Two methods compared query by query (usvc/metrics/paired.py, `python -m benchmarks.accuracy compare-poses`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO
from test_metrics_stage import N_QUERIES, _exact, inputs  # noqa: F401  (inputs: the stage's fixture)
from test_metrics_stage import _scene as stage_scene

from usvc.core.errors import UsvcError
from usvc.core.poses_file import write_poses_txt
from usvc.core.scene import Camera, Frame, Scene
from usvc.metrics.paired import QueryErrors, paired_comparison, query_errors, sign_test_p


def _errors(trans, rot=None) -> QueryErrors:
    trans = np.asarray(trans, float)
    rot = np.full(len(trans), 0.1) if rot is None else np.asarray(rot, float)
    return QueryErrors(tuple(f"q{i}" for i in range(len(trans))), rot, trans)


def test_the_sign_test_is_the_exact_binomial_one():
    assert sign_test_p(0, 0) == 1.0
    assert sign_test_p(5, 0) == pytest.approx(2 / 32)
    assert sign_test_p(0, 5) == pytest.approx(2 / 32)
    assert sign_test_p(8, 1) == pytest.approx(2 * (1 + 9) / 512)
    assert sign_test_p(3, 2) == 1.0


def test_a_method_against_itself_differs_by_nothing():
    rng = np.random.default_rng(1)
    a = _errors(rng.uniform(0.0, 0.1, 15), rng.uniform(0.0, 3.0, 15))
    out = paired_comparison(a, a, metric_scale=1.0, median_depth=1.5, resamples=200)
    assert out["per_query"] == {"a_closer": 0, "b_closer": 0, "equal": 15, "sign_test_p": 1.0,
                                "median_translation_ratio": 1.0}
    for key, fig in out["figures"].items():
        assert fig["difference"] == 0.0 and fig["interval"] == [0.0, 0.0], key
    assert out["median_translation_over"] == {"value": 1.0, "interval": [1.0, 1.0]}


def test_a_method_closer_on_every_query_is_told_apart_and_the_interval_says_by_how_much():
    rng = np.random.default_rng(2)
    b = _errors(rng.uniform(0.001, 0.03, 12))
    a = _errors(b.trans / 2)
    out = paired_comparison(a, b, metric_scale=1.0, median_depth=None, resamples=2000)
    pq = out["per_query"]
    assert (pq["a_closer"], pq["b_closer"], pq["equal"]) == (12, 0, 0)
    assert pq["sign_test_p"] == pytest.approx(2 / 2 ** 12)
    assert pq["median_translation_ratio"] == pytest.approx(0.5)
    med = out["figures"]["median_trans_cm"]
    assert med["difference"] == pytest.approx(-100 * np.sort(b.trans)[6] / 2)
    lo, hi = med["interval"]
    assert lo <= med["difference"] <= hi < 0  # every resample: a's median is half of b's
    assert out["median_translation_over"]["value"] == pytest.approx(0.5)
    assert out["median_translation_over"]["interval"] == pytest.approx([0.5, 0.5])
    assert "acc_rel_5cm_5deg" not in out["figures"]  # no median depth: no relative figures


def test_a_missing_answer_is_infinitely_wrong_and_the_other_method_is_closer_there():
    b = _errors([0.01, 0.02, 0.03, 0.04])
    a = _errors([0.01, 0.02, 0.03, np.inf])
    out = paired_comparison(a, b, metric_scale=1.0, median_depth=None, resamples=500)
    assert out["failed"] == {"a": 1, "b": 0}
    assert out["figures"]["acc_5cm_5deg"]["difference"] == pytest.approx(-0.25)
    assert (out["per_query"]["a_closer"], out["per_query"]["b_closer"]) == (0, 1)


def test_the_intervals_are_the_same_for_the_same_seed_and_hold_zero_for_two_draws_of_one_method():
    rng = np.random.default_rng(3)
    a, b = _errors(rng.uniform(0, 0.05, 40)), _errors(rng.uniform(0, 0.05, 40))
    one = paired_comparison(a, b, metric_scale=1.0, median_depth=1.5, resamples=1000, seed=7)
    two = paired_comparison(a, b, metric_scale=1.0, median_depth=1.5, resamples=1000, seed=7)
    assert one == two
    lo, hi = one["figures"]["median_trans_cm"]["interval"]
    assert lo < 0 < hi


def test_errors_of_other_queries_or_settings_are_refused():
    a, b = _errors([0.1, 0.2]), _errors([0.1, 0.2, 0.3])
    with pytest.raises(UsvcError, match="not of the same queries"):
        paired_comparison(a, b, 1.0, None)
    with pytest.raises(UsvcError, match="resamples"):
        paired_comparison(a, a, 1.0, None, resamples=0)
    with pytest.raises(UsvcError, match="level"):
        paired_comparison(a, a, 1.0, None, level=1.0)


def _scene() -> Scene:
    cam = Camera("SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0))
    frames = [Frame("train0.png", "train0.png", cam, "train", np.eye(3), np.zeros(3))]
    frames += [Frame(f"test{i}.png", f"test{i}.png", cam, "test", np.eye(3), np.array([0.0, 0.0, float(i)]))
               for i in range(3)]
    return Scene("toy", frames, metric_scale=1.0)


def test_query_errors_follow_the_split_and_refuse_poses_of_other_images():
    scene = _scene()
    est = {"test0.png": (np.eye(3), np.array([0.0, 0.0, 0.02])), "test2.png": (np.eye(3), np.array([0.0, 0.0, 2.0]))}
    err = query_errors(scene, est, "poses.txt")
    assert err.names == ("test0.png", "test1.png", "test2.png")
    assert err.trans == pytest.approx([0.02, np.inf, 0.0])
    assert list(err.failed) == [False, True, False]
    with pytest.raises(UsvcError, match="poses.txt has a pose for 'train0.png', which is not a test query of scene 'toy'"):
        query_errors(scene, {"train0.png": (np.eye(3), np.zeros(3))}, "poses.txt")


@pytest.mark.slow
def test_compare_poses_pairs_two_poses_files_of_the_scene(inputs):  # noqa: F811 (the imported fixture)
    """`benchmarks.accuracy compare-poses` on the stage's inputs: the relocalized poses (one query missing,
    one moved 3 cm) against the exact ones: the missing and the moved query are where the exact
    file is the closer, the rest are equal, and the shares differ by exactly those queries."""
    scene = stage_scene(metric_scale=1.0)
    exact = _exact(scene)
    names = sorted(exact)
    write_poses_txt(inputs / "exact.txt", names, np.stack([exact[n][0] for n in names]),
                    np.stack([exact[n][1] for n in names]))
    env = {**os.environ, "USVC_BENCHMARK_DIR": str(inputs / "reports"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.accuracy", "compare-poses", "--scene", "mini", "--a",
         str(inputs / "data/mini/relocalize/poses.txt"), "--b", str(inputs / "exact.txt"), "--a-name", "usvc",
         "--b-name", "exact", "--resamples", "300", f"data_dir={inputs / 'data'}"],
        cwd=REPO, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((inputs / "reports" / "accuracy_compare_poses_mini_usvc_vs_exact.json").read_text())
    n = N_QUERIES
    assert report["queries"] == n and report["failed"] == {"a": 1, "b": 0}
    assert report["per_query"]["b_closer"] == 2 and report["per_query"]["a_closer"] == 0
    assert report["per_query"]["equal"] == n - 2
    assert report["figures"]["acc_5cm_5deg"]["difference"] == pytest.approx(-1 / n)
    assert report["figures"]["acc_2cm_2deg"]["difference"] == pytest.approx(-2 / n)
    lo, hi = report["figures"]["acc_2cm_2deg"]["interval"]
    assert lo <= -2 / n <= hi <= 0
