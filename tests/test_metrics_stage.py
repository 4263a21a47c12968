"""The metrics stage: per-query evaluation, plots, and the stage end to end.

Every input is synthetic and built in tmp_path, so these tests do not need the pipeline to
have run (the relocalize stage in particular).
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import REPO, tracks_of
from scipy.spatial.transform import Rotation

from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers
from usvc.core.poses_file import write_poses_txt
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import write_scene_h5
from usvc.metrics.evaluate import (
    HEADLINE_KEYS_METRIC,
    HEADLINE_KEYS_RELATIVE,
    PER_QUERY_COLUMNS,
    evaluate_initial_poses,
    evaluate_poses,
    headline_figures,
)
from usvc.metrics.plots import error_cdf, principal_axes, write_plots
from usvc.pipeline.metrics_file import TIMING_KEYS
from usvc.relocalize.queries_file import (
    QueryStats,
    read_query_stats,
    read_refinement_records,
)
from usvc.sfm.tracks_file import write_tracks

CAM = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
N_QUERIES = 8


def _look_at(centre: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at `centre` looking at `target` (OpenCV axes, y down)."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def _scene(metric_scale: float | None = 1.0, name: str = "mini") -> Scene:
    """Cameras on a 2 m circle around the origin; even indices map, queries are interleaved."""
    frames = []
    for i in range(2 * N_QUERIES):
        a = 2 * np.pi * i / (2 * N_QUERIES)
        R, t = _look_at(np.array([2.0 * np.cos(a), 0.1 * i, 2.0 * np.sin(a)]), np.zeros(3))
        split, fname = ("test", f"q{i // 2:02d}.png") if i % 2 else ("train", f"m{i // 2:02d}.png")
        frames.append(Frame(fname, Path(fname), CAM, split, R, t))
    return Scene(name, frames, metric_scale)


def _stats(scene: Scene, seconds: float = 0.05) -> dict[str, QueryStats]:
    return {f.name: QueryStats(100 + k, seconds, True) for k, f in enumerate(scene.split("test"))}


def _exact(scene: Scene) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {f.name: (f.R.copy(), f.t.copy()) for f in scene.split("test")}


def _rotated(R: np.ndarray, t: np.ndarray, deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Same centre, rotation off by `deg` degrees."""
    c = camera_centers(R, t)
    R2 = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.6, 0.8])).as_matrix() @ R
    return R2, -R2 @ c


def _moved(R: np.ndarray, t: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Same rotation, centre moved by `offset`."""
    return R, -R @ (camera_centers(R, t) + offset)


# --- evaluate_poses -------------------------------------------------------------------------

def test_exact_poses_score_perfectly():
    scene = _scene()
    summary, rows = evaluate_poses(scene, _exact(scene), _stats(scene), median_depth=2.0)
    assert summary["acc_1cm_1deg"] == 1.0 and summary["acc_5deg_3pct"] == 1.0
    assert summary["n_queries"] == N_QUERIES and summary["n_failed"] == 0
    assert summary["median_trans_cm"] == pytest.approx(0.0, abs=1e-9)
    assert summary["ms_per_query"] == pytest.approx(50.0)
    assert summary["mean_inliers"] == pytest.approx(100 + (N_QUERIES - 1) / 2)
    assert summary["median_depth"] == 2.0
    assert [r["name"] for r in rows] == [f"q{k:02d}.png" for k in range(N_QUERIES)]
    assert all(set(r) == set(PER_QUERY_COLUMNS) for r in rows)


def test_known_perturbations_give_known_errors():
    scene = _scene(metric_scale=0.5)  # 1 scene unit = 50 cm
    est = _exact(scene)
    est["q00.png"] = _rotated(*est["q00.png"], deg=3.0)
    est["q01.png"] = _moved(*est["q01.png"], np.array([0.0, 0.072, 0.096]))  # 0.12 units = 6 cm
    est["q02.png"] = _moved(*est["q02.png"], np.array([0.03, 0.0, 0.04]))  # 0.05 units = 2.5 cm
    del est["q03.png"]
    summary, rows = evaluate_poses(scene, est, _stats(scene), median_depth=2.0)
    by = {r["name"]: r for r in rows}
    assert by["q00.png"]["rot_deg"] == pytest.approx(3.0, abs=1e-9)
    assert by["q00.png"]["trans"] == pytest.approx(0.0, abs=1e-9)
    assert by["q01.png"]["trans"] == pytest.approx(0.12)
    assert by["q01.png"]["trans_cm"] == pytest.approx(6.0)
    assert by["q01.png"]["rot_deg"] == pytest.approx(0.0, abs=1e-9)
    assert by["q02.png"]["trans_cm"] == pytest.approx(2.5)
    missing = by["q03.png"]
    assert missing["failed"] and math.isnan(missing["rot_deg"]) and math.isnan(missing["est_x"])
    assert not any(by[n]["failed"] for n in ("q00.png", "q01.png", "q02.png"))
    assert summary["n_failed"] == 1
    n = N_QUERIES
    assert summary["acc_5cm_5deg"] == pytest.approx((n - 2) / n)  # q01 (6 cm) and q03 (missing) miss
    assert summary["acc_10cm_5deg"] == pytest.approx((n - 1) / n)
    assert summary["acc_2cm_2deg"] == pytest.approx((n - 4) / n)
    # relative: 3 % of depth 2.0 = 0.06 units: q01 (0.12) is out, q02 (0.05) is in
    assert summary["acc_5deg_3pct"] == pytest.approx((n - 2) / n)
    gt = by["q01.png"]
    assert np.linalg.norm([gt["est_x"] - gt["gt_x"], gt["est_y"] - gt["gt_y"], gt["est_z"] - gt["gt_z"]]) \
        == pytest.approx(0.12)


def test_unsuccessful_query_fails_but_keeps_its_errors():
    scene = _scene()
    est = _exact(scene)
    stats = _stats(scene)
    stats["q04.png"] = QueryStats(3, 0.05, False)
    summary, rows = evaluate_poses(scene, est, stats, median_depth=2.0)
    row = next(r for r in rows if r["name"] == "q04.png")
    assert row["failed"] and row["rot_deg"] == pytest.approx(0.0, abs=1e-9) and row["inliers"] == 3
    assert summary["n_failed"] == 1
    assert summary["acc_1cm_1deg"] == pytest.approx((N_QUERIES - 1) / N_QUERIES)


def test_non_metric_scene_reports_relative_figures_only():
    scene = _scene(metric_scale=None)
    est = _exact(scene)
    est["q00.png"] = _moved(*est["q00.png"], np.array([0.0, 0.0, 1.0]))
    summary, rows = evaluate_poses(scene, est, _stats(scene), median_depth=4.0)
    assert summary["acc_5cm_5deg"] is None and summary["median_trans_cm"] is None
    assert summary["acc_5deg_3pct"] == pytest.approx((N_QUERIES - 1) / N_QUERIES)
    assert all(math.isnan(r["trans_cm"]) for r in rows)


def test_headline_is_the_same_few_figures_for_every_scene():
    metric, _ = evaluate_poses(_scene(), _exact(_scene()), _stats(_scene()), median_depth=2.0)
    relative, _ = evaluate_poses(_scene(None), _exact(_scene(None)), _stats(_scene(None)), median_depth=2.0)
    head = headline_figures(metric, metric=True)
    assert list(head) == list(HEADLINE_KEYS_METRIC) and head["acc_5cm_5deg"] == 1.0 and head["n_queries"] == N_QUERIES
    head = headline_figures(relative, metric=False)
    assert list(head) == list(HEADLINE_KEYS_RELATIVE) and head["acc_rel_5cm_5deg"] == 1.0
    assert all(v is not None for v in head.values())
    # the same figures, scaled to a 1.5 m median depth
    assert [k.replace("_rel", "") for k in HEADLINE_KEYS_RELATIVE] == list(HEADLINE_KEYS_METRIC)
    assert not any(k in TIMING_KEYS for k in HEADLINE_KEYS_METRIC + HEADLINE_KEYS_RELATIVE)


def test_unknown_estimate_name_is_an_error():
    scene = _scene()
    est = _exact(scene)
    est["m00.png"] = est["q00.png"]  # a mapping image, not a query
    with pytest.raises(UsvcError, match="'m00.png'.*not a test query of scene 'mini'"):
        evaluate_poses(scene, est, _stats(scene), median_depth=2.0)


def test_unknown_stats_name_is_an_error():
    scene = _scene()
    stats = {**_stats(scene), "elsewhere.png": QueryStats(1, 0.1, True)}
    with pytest.raises(UsvcError, match="elsewhere.png"):
        evaluate_poses(scene, _exact(scene), stats, median_depth=2.0)


def _write_queries_h5(path: Path, stats: dict[str, QueryStats],
                      initial: dict[str, tuple[np.ndarray, np.ndarray]] | None = None) -> None:
    """queries.h5 as the relocalize stage writes it; without `initial`, as it did before refinement."""
    with h5py.File(path, "w") as h5:
        h5.create_dataset("name", data=np.array(list(stats), dtype=object), dtype=h5py.string_dtype())
        h5["inliers"] = np.array([s.inliers for s in stats.values()], dtype=np.int64)
        h5["seconds"] = np.array([s.seconds for s in stats.values()], dtype=np.float64)
        h5["success"] = np.array([s.success for s in stats.values()], dtype=bool)
        if initial is not None:
            nan = (np.full((3, 3), np.nan), np.full(3, np.nan))
            h5["initial_R"] = np.stack([initial.get(n, nan)[0] for n in stats])
            h5["initial_t"] = np.stack([initial.get(n, nan)[1] for n in stats])
            h5["refine_iterations"] = np.array([2 * (k % 2) for k in range(len(stats))], dtype=np.int64)
            h5["refine_kept"] = np.array([k % 2 == 1 for k in range(len(stats))], dtype=bool)


def _initial_poses(scene: Scene) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Pre-refinement poses: q02 off by 8 cm, q03 by 4 degrees, q05 missing (its dense solve failed)."""
    initial = _exact(scene)
    initial["q02.png"] = _moved(*initial["q02.png"], np.array([0.0, 0.08, 0.0]))
    initial["q03.png"] = _rotated(*initial["q03.png"], deg=4.0)
    del initial["q05.png"]
    return initial


def test_initial_poses_are_scored_like_the_final_ones(tmp_path):
    scene = _scene(metric_scale=1.0)
    stats = _stats(scene)
    stats["q05.png"] = QueryStats(0, 0.05, False)
    _write_queries_h5(tmp_path / "queries.h5", stats, _initial_poses(scene))
    records = read_refinement_records(tmp_path / "queries.h5")
    assert records is not None and records.names == list(stats)
    assert records.initial_R.shape == (N_QUERIES, 3, 3) and np.isnan(records.initial_t[5]).all()
    out = evaluate_initial_poses(scene, records, stats, median_depth=2.0)
    n = N_QUERIES
    assert out["initial_acc_5cm_5deg"] == pytest.approx((n - 2) / n)  # q02 (8 cm) and q05 (failed)
    assert out["initial_acc_2cm_2deg"] == pytest.approx((n - 3) / n)  # and q03 (4 degrees)
    assert out["initial_acc_10cm_5deg"] == pytest.approx((n - 1) / n)
    assert out["initial_median_rot_deg"] == pytest.approx(0.0, abs=1e-6)
    assert "initial_median_trans_cm" in out and "initial_median_trans_rel" in out
    assert not {"initial_median_depth", "initial_ms_per_query", "initial_n_queries"} & set(out)
    # odd queries kept their refinement (2 iterations), even ones did not; q05 failed and is not counted
    assert out["refine_kept_fraction"] == pytest.approx(3 / 7)
    assert out["refine_mean_iterations"] == pytest.approx(6 / 7)
    # the same machinery as the final poses: exact initial poses give the final figures
    queries = scene.split("test")
    exact = replace(records, initial_R=np.stack([f.R for f in queries]), initial_t=np.stack([f.t for f in queries]))
    exact_initial = evaluate_initial_poses(scene, exact, stats, 2.0)
    final, _ = evaluate_poses(scene, _exact(scene), stats, 2.0)
    assert all(exact_initial[f"initial_{k}"] == pytest.approx(final[k]) for k in ("acc_5cm_5deg", "median_rot_deg"))


def test_non_metric_initial_figures_skip_missing_values(tmp_path):
    scene = _scene(metric_scale=None)
    _write_queries_h5(tmp_path / "queries.h5", _stats(scene), _exact(scene))
    records = read_refinement_records(tmp_path / "queries.h5")
    out = evaluate_initial_poses(scene, records, _stats(scene), median_depth=2.0)
    assert out["initial_acc_5deg_3pct"] == 1.0
    assert "initial_acc_5cm_5deg" not in out and "initial_median_trans_cm" not in out
    assert all(isinstance(v, (int, float)) for v in out.values())


def test_old_queries_file_has_no_refinement_records(tmp_path):
    scene = _scene()
    _write_queries_h5(tmp_path / "queries.h5", _stats(scene))
    assert read_refinement_records(tmp_path / "queries.h5") is None
    with h5py.File(tmp_path / "queries.h5", "a") as h5:
        h5["refine_kept"] = np.zeros(N_QUERIES, bool)
    with pytest.raises(UsvcError, match="lacks dataset"):
        read_refinement_records(tmp_path / "queries.h5")


def test_query_stats_round_trip(tmp_path):
    stats = {"a b.png": QueryStats(12, 0.25, True), "c.png": QueryStats(0, 0.5, False)}
    _write_queries_h5(tmp_path / "queries.h5", stats)
    assert read_query_stats(tmp_path / "queries.h5") == stats
    with pytest.raises(UsvcError, match="relocalize"):
        read_query_stats(tmp_path / "missing.h5")


# --- plots ----------------------------------------------------------------------------------

def test_error_cdf_counts_failures_in_the_denominator():
    x, frac = error_cdf(np.array([3.0, 1.0, np.nan, 2.0]), np.array([False, False, True, True]))
    assert list(x) == [0.0, 1.0, 3.0]
    assert list(frac) == [0.0, 0.25, 0.5]


def test_principal_axes_find_the_floor_plane():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-5, 5, 50), rng.uniform(-0.01, 0.01, 50), rng.uniform(-2, 2, 50)]
    mean, axes = principal_axes(pts)
    assert np.allclose(axes @ axes.T, np.eye(2))
    assert abs(np.cross(axes[0], axes[1]) @ [0, 1, 0]) > 0.999  # the view looks down the thin y axis
    assert np.allclose(mean, pts.mean(axis=0))


def _read_cdf(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and set(rows[0]) == {"error", "fraction"}
    return np.array([float(r["error"]) for r in rows]), np.array([float(r["fraction"]) for r in rows])


@pytest.mark.parametrize("metric_scale", [1.0, None])
def test_plots_are_written(tmp_path, metric_scale):
    scene = _scene(metric_scale)
    est = _exact(scene)
    rng = np.random.default_rng(1)
    for name in list(est)[:5]:
        est[name] = _moved(*_rotated(*est[name], rng.uniform(0, 4)), rng.normal(0, 0.05, 3))
    del est["q07.png"]
    _, rows = evaluate_poses(scene, est, _stats(scene), median_depth=2.0)
    files = write_plots(tmp_path, rows, PER_QUERY_COLUMNS, metric_scale, 2.0, "mini")
    for f in files:
        assert f.is_file() and f.stat().st_size > 0, f
    for png in ("cdf.png", "trajectory.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (tmp_path / png).stat().st_size < 200_000
    for name in ("trans_cdf.csv", "rot_cdf.csv"):
        x, frac = _read_cdf(tmp_path / name)
        assert np.all(np.diff(x) >= 0) and np.all(np.diff(frac) > 0)
        assert frac[0] == 0.0 and frac[-1] == pytest.approx((N_QUERIES - 1) / N_QUERIES)
    with open(tmp_path / "per_query.csv", newline="") as fh:
        per_query = list(csv.DictReader(fh))
    assert len(per_query) == N_QUERIES and list(per_query[0]) == list(PER_QUERY_COLUMNS)


# --- the stage, end to end ------------------------------------------------------------------

@pytest.fixture
def inputs(tmp_path) -> Path:
    """data/mini/{prepared,sfm,relocalize} for a synthetic scene; one query missing, one moved 3 cm."""
    data = tmp_path / "data" / "mini"
    scene = _scene(metric_scale=1.0)
    for sub in ("prepared", "sfm", "relocalize"):
        (data / sub).mkdir(parents=True)
    write_scene_h5(data / "prepared" / "scene.h5", scene)
    train = scene.split("train")
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-0.5, 0.5, (20, 3))
    obs_image = np.concatenate([rng.choice(len(train), 3, replace=False) for _ in range(20)])
    write_tracks(data / "sfm" / "tracks.h5", tracks_of(
        np.stack([f.R for f in train]), np.stack([f.t for f in train]), xyz, list(range(0, 61, 3)), obs_image,
        K=CAM.K))
    est = _exact(scene)
    est["q01.png"] = _moved(*est["q01.png"], np.array([0.03, 0.0, 0.0]))
    del est["q05.png"]
    names = sorted(est)
    write_poses_txt(data / "relocalize" / "poses.txt", names,
                    np.stack([est[n][0] for n in names]), np.stack([est[n][1] for n in names]))
    _write_queries_h5(data / "relocalize" / "queries.h5", _stats(scene, seconds=0.02))
    return tmp_path


def _run_stage(tmp_path: Path, *extra: str, flags: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "stages.metrics", *flags, "scene=mini", f"data_dir={tmp_path / 'data'}",
         f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log'}",
         f"hydra.sweep.dir={tmp_path / 'sweep'}", *extra],
        cwd=REPO, capture_output=True, text=True,
    )


@pytest.mark.slow
def test_stage_writes_metrics_and_plots(inputs):
    proc = _run_stage(inputs)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    metrics = json.loads((inputs / "results/mini/metrics.json").read_text())
    for key in ("acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "acc_10cm_5deg", "acc_5deg_3pct",
                "median_rot_deg", "median_trans_cm", "median_trans_rel", "median_trans",
                "n_queries", "n_failed", "median_depth", "mean_inliers"):
        assert key in metrics, key
    timing = json.loads((inputs / "results/mini/metrics.timing.json").read_text())
    assert set(timing) == {"ms_per_query", "seconds", "peak_memory_mb"} and not set(timing) & set(metrics)
    n = N_QUERIES
    assert metrics["n_queries"] == n and metrics["n_failed"] == 1
    assert metrics["acc_5cm_5deg"] == pytest.approx((n - 1) / n)
    assert metrics["acc_2cm_2deg"] == pytest.approx((n - 2) / n)
    assert timing["ms_per_query"] == pytest.approx(20.0)
    assert metrics["median_depth"] > 0
    for name in ("per_query.csv", "trans_cdf.csv", "rot_cdf.csv", "cdf.png", "trajectory.png"):
        assert (inputs / "results/mini/plots" / name).stat().st_size > 0, name
    assert not any(k.startswith(("initial_", "refine_")) for k in metrics)  # a queries.h5 from before refinement
    # the headline (dvc metrics show): a few of metrics.json's figures, no timings
    headline = json.loads((inputs / "results/mini/headline.json").read_text())
    assert list(headline) == sorted(HEADLINE_KEYS_METRIC)
    assert all(headline[k] == metrics[k] for k in headline)
    assert not (inputs / "results/mini/headline.timing.json").exists()


@pytest.mark.slow
def test_stage_scores_initial_poses_when_recorded(inputs):
    scene = _scene(metric_scale=1.0)
    initial = _initial_poses(scene)
    _write_queries_h5(inputs / "data/mini/relocalize/queries.h5", _stats(scene, seconds=0.02), initial)
    proc = _run_stage(inputs)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    metrics = json.loads((inputs / "results/mini/metrics.json").read_text())
    n = N_QUERIES
    assert metrics["acc_5cm_5deg"] == pytest.approx((n - 1) / n)  # the final poses, as before
    assert metrics["initial_acc_5cm_5deg"] == pytest.approx((n - 2) / n)
    assert metrics["initial_acc_2cm_2deg"] == pytest.approx((n - 3) / n)
    assert metrics["refine_kept_fraction"] == pytest.approx(0.5)  # stats say every query succeeded
    assert metrics["refine_mean_iterations"] == pytest.approx(1.0)


@pytest.mark.slow
def test_stage_multirun_leaves_the_tracked_results_alone(inputs):
    proc = _run_stage(inputs, "seed=0,1", "hydra.sweep.subdir=${hydra.job.num}", flags=("--multirun",))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not (inputs / "results").exists()
    jobs = sorted(p for p in (inputs / "sweep").iterdir() if p.is_dir())
    assert len(jobs) == 2
    for job in jobs:
        assert json.loads((job / "metrics.json").read_text())["n_queries"] == N_QUERIES
        assert json.loads((job / "headline.json").read_text())["n_queries"] == N_QUERIES
        assert (job / "plots" / "trajectory.png").is_file()


@pytest.mark.slow
def test_multirun_through_submitits_local_executor(inputs):
    """The cluster path (hydra/launcher=submitit_slurm) with submitit's local executor: every job is
    submitted, runs in its own process, and writes its own directory."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    proc = _run_stage(inputs, "seed=0,1", "hydra.sweep.subdir=${hydra.job.num}", "hydra/launcher=submitit_local",
                      f"hydra.launcher.submitit_folder={inputs / 'submitit'}", "hydra.launcher.timeout_min=10",
                      flags=("--multirun",))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not (inputs / "results").exists()
    for job in ("0", "1"):
        assert json.loads((inputs / "sweep" / job / "metrics.json").read_text())["n_queries"] == N_QUERIES
    logs = sorted((inputs / "submitit").glob("*_log.out"))
    assert len(logs) == 2, logs  # one submitit job each


@pytest.mark.slow
def test_stage_without_poses_fails_in_one_line(inputs):
    (inputs / "data/mini/relocalize/poses.txt").unlink()
    proc = _run_stage(inputs)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "Traceback" not in out
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "poses.txt" in errors[0], out
    assert not (inputs / "results/mini/metrics.json").exists()
    assert not (inputs / "results/mini/plots").exists()


# --- a learned pose never computed (relocalize.prior=none) ------------------------------------

def _nowhere(stats: dict[str, QueryStats]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """No learned pose for any query: initial_R/initial_t NaN, as relocalize.prior=none writes them."""
    return {n: (np.full((3, 3), np.nan), np.full(3, np.nan)) for n in stats}


def test_a_learned_pose_never_computed_is_null_not_zero(tmp_path):
    from usvc.metrics.evaluate import initial_pose_computed

    scene = _scene()
    stats = _stats(scene)
    _write_queries_h5(tmp_path / "queries.h5", stats, _nowhere(stats))
    records = read_refinement_records(tmp_path / "queries.h5")
    assert records.success.all() and not initial_pose_computed(records)
    out = evaluate_initial_poses(scene, records, stats, median_depth=2.0)
    initial = {k: v for k, v in out.items() if k.startswith("initial_")}
    assert "initial_acc_5cm_5deg" in initial and "initial_median_rot_deg" in initial
    assert all(v is None for v in initial.values()), initial  # not 0.0 and inf
    # a learned pose that failed on some queries is still scored; nothing answered stays as it was
    _write_queries_h5(tmp_path / "some.h5", stats, {**_nowhere(stats), **dict(list(_exact(scene).items())[:2])})
    assert initial_pose_computed(read_refinement_records(tmp_path / "some.h5"))
    none = {n: QueryStats(s.inliers, s.seconds, False) for n, s in stats.items()}
    _write_queries_h5(tmp_path / "none.h5", none, _nowhere(stats))
    assert initial_pose_computed(read_refinement_records(tmp_path / "none.h5"))


@pytest.mark.slow
def test_stage_says_not_computed_without_a_learned_pose(inputs):
    scene = _scene(metric_scale=1.0)
    stats = _stats(scene, seconds=0.02)
    _write_queries_h5(inputs / "data/mini/relocalize/queries.h5", stats, _nowhere(stats))
    proc = _run_stage(inputs)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    metrics = json.loads((inputs / "results/mini/metrics.json").read_text())
    assert metrics["acc_5cm_5deg"] == pytest.approx((N_QUERIES - 1) / N_QUERIES)  # the answers, as before
    assert metrics["initial_acc_5cm_5deg"] is None and metrics["initial_median_trans_cm"] is None
    assert "before refinement: not computed" in out and "before refinement acc" not in out, out
