"""The cached pipeline on the miniature scene: a copy of the repo, a real `dvc repro`.

Proves that changing keypoints.tau marks only the keypoint stage (and what is downstream of it)
as changed, that `dvc repro` then reruns only that, and that a --multirun sweep writes to its
own job directories and never over the DVC-tracked artifact.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

pytestmark = pytest.mark.slow


# One thread in every stage (a ceiling for threads=auto): the same bits in the fixture's run and in
# the forced rerun below, whatever else runs beside the tests.
# dvc.yaml's commands say `python`: the interpreter running the tests (its environment's packages), whether
# or not that environment is activated.
ONE_THREAD = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}


def _run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=ONE_THREAD)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    """A git+DVC copy of the project's files (tracked and not ignored), reproduced once."""
    dst = tmp_path_factory.mktemp("pipeline") / "usvc"
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                            cwd=REPO, capture_output=True, text=True, check=True).stdout.split()
    for rel in listed:
        src = REPO / rel
        if src.is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / rel)
    # The whole pipeline runs, with mapping cut to a few seconds: this test is about caching and
    # wiring; accuracy on the miniature scene is measured by `.ci/run`'s own `dvc repro`.
    _set(dst / "conf/buffer/default.yaml", "\nsize: 0 ", "\nsize: 16384 ")
    _set(dst / "conf/train/default.yaml", "\niterations: 0 ", "\niterations: 20 ")
    _set(dst / "conf/train/default.yaml", "batch_size: 2048", "batch_size: 1024")
    _set(dst / "conf/gaussians/default.yaml", "iterations: 400", "iterations: 30")
    _set(dst / "conf/render/default.yaml", "views: 30", "views: 4")
    _run(["git", "init", "-q"], dst)
    _run(["git", "-c", "user.email=ci@usvc", "-c", "user.name=ci", "add", "-A"], dst)
    _run(["git", "-c", "user.email=ci@usvc", "-c", "user.name=ci", "commit", "-qm", "copy"], dst)
    _run([sys.executable, "-m", "dvc", "repro"], dst)
    return dst


def _set(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{path} has no line {old!r}"
    path.write_text(text.replace(old, new))


def _status(repo: Path) -> set[str]:
    out = _run([sys.executable, "-m", "dvc", "status", "--json"], repo).stdout
    return set(json.loads(out))


def test_repro_produces_every_artifact(repo):
    for rel in ["data/raw/mini/train/rgb", "data/mini/prepared/scene.h5", "data/mini/sfm/tracks.h5",
                "data/mini/sfm/points.ply", "data/mini/sfm/model/points3D.bin",
                "data/mini/keypoints/keypoints.h5", "data/mini/keypoints/keypoints.ply",
                "data/mini/gaussians/NOT_COMPUTED.txt", "data/mini/render/NOT_COMPUTED.txt",
                "data/mini/buffer/buffer.h5", "data/mini/map/map.pt", "data/mini/landmarks/landmarks.h5",
                "data/mini/relocalize/poses.txt",
                "data/mini/relocalize/queries.h5", "results/mini/metrics.json",
                "results/mini/plots/trajectory.png", "results/mini/plots/trans_cdf.csv"]:
        assert (repo / rel).exists(), rel
    sfm = json.loads((repo / "results/mini/sfm.json").read_text())
    assert sfm["points"] > 500 and sfm["median_reprojection_error_px"] < 1.0
    for stage in ("gaussians", "render"):  # the default method=multiview does not use them
        skipped = json.loads((repo / f"results/mini/{stage}.json").read_text())
        assert skipped["computed"] is False and "buffer.rendered_views is false" in skipped["reason"]
    metrics = json.loads((repo / "results/mini/metrics.json").read_text())
    assert metrics["n_queries"] == 20 and 0.0 <= metrics["acc_5cm_5deg"] <= 1.0
    shown = _run([sys.executable, "-m", "dvc", "metrics", "show"], repo).stdout
    assert "acc_5cm_5deg" in shown and "median_rot_deg" in shown
    # the default table is the headline; each stage's figures are shown when named
    assert "results/mini/headline.json" in shown and "median_reprojection_error_px" not in shown
    assert "mean_inliers" not in shown and "final_loss" not in shown
    detail = _run([sys.executable, "-m", "dvc", "metrics", "show", "results/mini/sfm.json"], repo).stdout
    assert "median_reprojection_error_px" in detail
    assert _status(repo) == set()


def test_a_forced_rerun_leaves_the_lock_as_it_was(repo):
    """Run timings live in *.timing.json, which DVC does not track, and nowhere in the artifacts:
    rerunning stages at the same thread count gives the same bytes, so dvc.lock (and a user's
    checkout) stays as it was; training and relocalization included."""
    lock = (repo / "dvc.lock").read_text()
    _run([sys.executable, "-m", "dvc", "repro", "--force", "--single-item", "keypoints@mini", "train@mini",
          "relocalize@mini", "metrics@mini"], repo)
    assert (repo / "dvc.lock").read_text() == lock
    timing = json.loads((repo / "results/mini/metrics.timing.json").read_text())
    assert timing["seconds"] > 0 and "seconds" not in json.loads((repo / "results/mini/metrics.json").read_text())
    for stage in ("train", "relocalize"):  # the torch device and its name: beside the timings, not in the lock
        ran_on = json.loads((repo / f"results/mini/{stage}.timing.json").read_text())
        assert ran_on["device"] in ("cpu", "cuda") and ran_on["device_name"]
        assert "device" not in json.loads((repo / f"results/mini/{stage}.json").read_text())


def test_relocalize_change_reruns_only_relocalize_and_metrics(repo):
    conf = repo / "conf/relocalize/default.yaml"
    map_digest = _digest(repo / "data/mini/map/map.pt")
    conf.write_text(conf.read_text().replace("max_error_px: 10.0", "max_error_px: 8.0"))
    assert _status(repo) == {"relocalize@mini"}  # metrics changes once relocalize has rerun
    out = _run([sys.executable, "-m", "dvc", "repro"], repo).stdout
    assert "Running stage 'relocalize@mini'" in out and "Running stage 'metrics@mini'" in out
    for stage in ("buffer@mini", "train@mini", "sfm@mini"):
        assert f"Running stage '{stage}'" not in out
    assert _digest(repo / "data/mini/map/map.pt") == map_digest
    assert _status(repo) == set()


def test_landmarks_change_reruns_landmarks_relocalize_metrics_only(repo):
    conf = repo / "conf/landmarks/default.yaml"
    map_digest = _digest(repo / "data/mini/map/map.pt")
    conf.write_text(conf.read_text().replace("descriptor: mean", "descriptor: medoid"))
    assert _status(repo) == {"landmarks@mini"}
    out = _run([sys.executable, "-m", "dvc", "repro"], repo).stdout
    for stage in ("landmarks@mini", "relocalize@mini", "metrics@mini"):
        assert f"Running stage '{stage}'" in out
    for stage in ("sfm@mini", "keypoints@mini", "buffer@mini", "train@mini"):
        assert f"Running stage '{stage}'" not in out
    assert _digest(repo / "data/mini/map/map.pt") == map_digest
    assert json.loads((repo / "results/mini/landmarks.json").read_text())["landmarks"] > 500
    records = json.loads((repo / "data/mini/relocalize/queries.json").read_text())
    assert all(r["refinement"]["method"] == "features" for r in records.values() if r["success"])
    assert _status(repo) == set()


def test_an_options_module_edit_marks_only_the_stages_that_read_it(repo):
    """A stage imports only the options modules of the groups it reads: editing one (here a comment)
    marks the stages reading that group, not every stage; DVC reruns their downstream stages once
    their outputs change."""
    cases = {"usvc/render/options.py": {"render@mini"},
             "usvc/keypoints/options.py": {"keypoints@mini"},
             "usvc/model/options.py": {"buffer@mini", "train@mini", "relocalize@mini"}}
    for module, marked in cases.items():
        path = repo / module
        text = path.read_text()
        path.write_text(text + "# an edited comment\n")
        try:
            assert _status(repo) == marked, module
        finally:
            path.write_text(text)
        assert _status(repo) == set()


def test_tau_change_reruns_keypoints_onward_only(repo):
    conf = repo / "conf/keypoints/default.yaml"
    before = json.loads((repo / "results/mini/keypoints.json").read_text())
    sfm_digest = _digest(repo / "data/mini/sfm/tracks.h5")
    conf.write_text(conf.read_text().replace("tau: 1.5", "tau: 2.0"))
    assert _status(repo) == {"keypoints@mini"}
    out = _run([sys.executable, "-m", "dvc", "repro"], repo).stdout
    for stage in ("keypoints@mini", "buffer@mini", "train@mini"):  # the buffer holds keypoint tuples
        assert f"Running stage '{stage}'" in out
    for stage in ("generate", "prepare@mini", "sfm@mini"):
        assert f"Running stage '{stage}'" not in out
    after = json.loads((repo / "results/mini/keypoints.json").read_text())
    assert after["tau"] == 2.0 and after["kept"] < before["kept"]
    assert _digest(repo / "data/mini/sfm/tracks.h5") == sfm_digest
    assert _status(repo) == set()


def test_multirun_writes_own_dirs_and_prints_table(repo):
    tracked = _digest(repo / "data/mini/keypoints/keypoints.h5")
    proc = _run([sys.executable, "-m", "stages.keypoints", "--multirun", "keypoints.tau=1.0,1.5,2.0",
                 "hydra.sweep.dir=multirun/test"], repo)
    assert _digest(repo / "data/mini/keypoints/keypoints.h5") == tracked
    jobs = sorted((repo / "multirun/test").glob("*/metrics.json"))
    kept = [json.loads(p.read_text())["kept"] for p in jobs]
    assert len(kept) == 3 and kept[0] > kept[1] > kept[2]
    table = proc.stdout
    assert "keypoints.tau=1.0" in table and "keypoints.tau=2.0" in table and "kept" in table
    assert (repo / "multirun/test/0_keypoints.tau=1.0/keypoints/keypoints.h5").is_file()
    assert _status(repo) == set()


def test_sweep_reruns_only_what_the_override_changes(repo):
    """tools.sweep on a relocalize value: relocalize + metrics per job, on links to the DVC artifacts."""
    tracked = _digest(repo / "data/mini/relocalize/poses.txt")
    proc = _run([sys.executable, "-m", "tools.sweep", "--multirun", "relocalize.max_error_px=5,10",
                 "hydra.sweep.dir=multirun/sweep"], repo)
    jobs = sorted(p for p in (repo / "multirun/sweep").iterdir() if p.is_dir())
    assert [j.name for j in jobs] == ["0_relocalize.max_error_px=5", "1_relocalize.max_error_px=10"]
    for job in jobs:
        metrics = json.loads((job / "metrics.json").read_text())
        timing = json.loads((job / "metrics.timing.json").read_text())
        assert metrics["first_stage"] == "relocalize" and metrics["n_queries"] == 20
        assert "acc_5cm_5deg" in metrics and "ms_per_query" in timing and "ms_per_query" not in metrics
        assert "train_seconds" not in metrics and "train_seconds" not in timing
        assert {p.name for p in (job / "logs").iterdir()} == {"relocalize", "relocalize.log", "metrics", "metrics.log"}
        data = job / "data/mini"
        for upstream in ("prepared", "sfm", "keypoints", "buffer", "map"):
            assert (data / upstream).is_symlink(), upstream
            assert (data / upstream).resolve() == (repo / "data/mini" / upstream).resolve()
        assert not (data / "relocalize").is_symlink() and (data / "relocalize/poses.txt").is_file()
        assert (job / "results/mini/relocalize.json").is_file()
    rows = [line for line in proc.stdout.splitlines() if line.startswith(("0 ", "1 ")) and " | " in line]
    assert len(rows) == 2 and "relocalize.max_error_px=5" in rows[0] and "relocalize.max_error_px=10" in rows[1]
    assert "acc_5cm_5deg" in proc.stdout and "ms_per_query" in proc.stdout
    assert _digest(repo / "data/mini/relocalize/poses.txt") == tracked
    assert _status(repo) == set()


def test_sweep_jobs_run_side_by_side_through_submitit(repo):
    """The cluster path with submitit's local executor: the jobs run at once, each its own process,
    and their concurrent `dvc repro` of the upstream stages waits for DVC's lock instead of failing."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    _run([sys.executable, "-m", "tools.sweep", "--multirun", "relocalize.max_error_px=6,12",
          "hydra/launcher=submitit_local", "hydra.launcher.submitit_folder=multirun/submitit",
          "hydra.launcher.timeout_min=20", "hydra.sweep.dir=multirun/sweep_submitit"], repo)
    jobs = sorted(p for p in (repo / "multirun/sweep_submitit").iterdir() if p.is_dir())
    assert [j.name for j in jobs] == ["0_relocalize.max_error_px=6", "1_relocalize.max_error_px=12"]
    for job in jobs:
        metrics = json.loads((job / "metrics.json").read_text())
        assert metrics["first_stage"] == "relocalize" and metrics["n_queries"] == 20
    assert len(list((repo / "multirun/submitit").glob("*_log.out"))) == 2
    assert _status(repo) == set()


def test_relocalize_refuses_another_scenes_map(repo, tmp_path):
    """A map copied into another scene's place is refused, naming both scenes; nothing is written."""
    data = tmp_path / "data"
    for sub in ("prepared", "map"):
        shutil.copytree(repo / "data/mini" / sub, data / "other" / sub)
    proc = subprocess.run([sys.executable, "-m", "stages.relocalize", "scene=mini", "scene.name=other",
                           f"data_dir={data}", f"results_dir={tmp_path / 'results'}",
                           f"hydra.run.dir={tmp_path / 'log'}"], cwd=repo, capture_output=True, text=True)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "Traceback" not in out, out
    assert "is a map of scene 'mini', not of 'other'" in out
    assert not (data / "other" / "relocalize").exists() and not (tmp_path / "results").exists()


def test_multiview_gs_fits_and_renders(repo, tmp_path):
    """With method=multiview_gs the 3DGS fit and the novel views are computed (on copies of the
    upstream artifacts, so the DVC-tracked ones stay as the lock says)."""
    data = tmp_path / "data"
    for sub in ("prepared", "sfm", "keypoints"):
        shutil.copytree(repo / "data/mini" / sub, data / "mini" / sub)
    for stage in ("gaussians", "render"):
        _run([sys.executable, "-m", f"stages.{stage}", "scene=mini", "method=multiview_gs", f"data_dir={data}",
              f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log' / stage}"], repo)
    splat = json.loads((tmp_path / "results/mini/gaussians.json").read_text())
    assert splat["computed"] is True and splat["heldout_views"] > 0 and splat["heldout_psnr"] > 10
    assert splat["ply_reload_max_abs_diff"] == 0.0 and (data / "mini/gaussians/splat.ply").is_file()
    render = json.loads((tmp_path / "results/mini/render.json").read_text())
    assert render["computed"] is True and render["views"] == 4
    assert (data / "mini/render/render.h5").is_file() and (data / "mini/render/images/0003.png").is_file()
