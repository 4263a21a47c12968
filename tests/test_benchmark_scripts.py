"""Benchmarks that cannot rot: every family of benchmarks/ and every subcommand parses its
arguments (`--help` runs its imports and argument parser), no file edits `sys.path` (the package is
run as `python -m benchmarks.<family>`), and the subcommands with a tiny input run it, so a config or
API change that breaks one fails here rather than on the next person who measures."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import _cli

REPO = Path(__file__).resolve().parents[1]
SUBCOMMANDS = [(family, name) for family in _cli.FAMILIES
               for name in _cli.family_package(family).SUBCOMMANDS]


def test_no_benchmark_edits_sys_path():
    """The package imports as a package (`from benchmarks._report import ...`, usvc installed):
    nothing in benchmarks/ puts a folder on `sys.path`."""
    edits = [f"{p.relative_to(REPO)}:{n}" for p in sorted((REPO / "benchmarks").rglob("*.py"))
             for n, line in enumerate(p.read_text().splitlines(), 1) if re.search(r"\bsys\.path\b", line)]
    assert not edits, edits


def test_every_module_of_a_family_is_a_subcommand_or_a_helper():
    """A module in a family's folder is one of its subcommands, or a helper whose name starts with `_`
    or that a subcommand imports (the baseline's method, the map diagnosis)."""
    helpers = {"accuracy": {"sift_pnp", "diagnosis"}}
    for family in _cli.FAMILIES:
        modules = {p.stem for p in (REPO / "benchmarks" / family).glob("*.py") if not p.stem.startswith("_")}
        used = {module for module, _ in _cli.family_package(family).SUBCOMMANDS.values()}
        assert modules == used | helpers.get(family, set()), family


@pytest.mark.parametrize("family", _cli.FAMILIES)
def test_every_family_runs_as_a_module_and_lists_its_subcommands(family):
    proc = subprocess.run([sys.executable, "-m", f"benchmarks.{family}", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith(f"usage: python -m benchmarks.{family}")
    assert all(name in proc.stdout for name in _cli.family_package(family).SUBCOMMANDS)


@pytest.mark.parametrize("family, name", SUBCOMMANDS, ids=[f"{f}-{n}" for f, n in SUBCOMMANDS])
def test_every_subcommand_parses_its_arguments(family, name, capsys):
    with pytest.raises(SystemExit) as exit_:
        _cli.main(family, [name, "--help"])
    assert exit_.value.code in (0, None)
    out = capsys.readouterr().out
    assert out.startswith(f"usage: python -m benchmarks.{family} {name}") and "--variant" in out


def test_the_package_docstring_names_every_subcommand():
    import benchmarks

    assert all(re.search(rf"\b{re.escape(name)}\b", benchmarks.__doc__) for _, name in SUBCOMMANDS)


def test_relocalization_speed_runs_every_configured_model(tmp_path):
    """Each conf/model/*.yaml as the stages compose it (a model file sets only what differs)."""
    env = {**os.environ, "USVC_BENCHMARK_DIR": str(tmp_path), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.query", "models", "--runs", "1", "--warmup", "0",
                           "--sizes", "64x48", "--precision", "fp32"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "query_models_cpu.json").read_text())
    assert report["command"] == ("python -m benchmarks.query models --runs 1 --warmup 0 --sizes 64x48 "
                                 "--precision fp32")
    rows = report["rows"]
    models = sorted(p.stem for p in (REPO / "conf" / "model").glob("*.yaml"))
    assert [r["model"] for r in rows] == models
    by_model = {r["model"]: r for r in rows}
    assert by_model["default"]["head_width"] == 512 and by_model["small"]["head_width"] == 256
    assert all(r["encoder_ms"] > 0 and r["head_blocks"] >= 0 for r in rows)


def test_query_photos_at_a_size_keep_square_pixels():
    """A photo is cropped about its centre to the size's aspect ratio, then resized: the pixels stay
    square and a world point projects to the same place in the new photo as in the old one."""
    import numpy as np

    from benchmarks._photos import at_size

    rgb = np.zeros((960, 544, 3), np.uint8)  # portrait, bird's size: 480x640 asks for a 3:4 crop
    rgb[500, 300] = 255
    intrinsics = (800.0, 800.0, 272.0, 480.0)
    out, (fx, fy, cx, cy) = at_size(rgb, intrinsics, (640, 480))
    assert out.shape[:2] == (640, 480)
    assert fx == pytest.approx(fy, rel=1e-3)  # square pixels, not 1.32 as a straight resize gives
    x, y, z = 0.05, 0.03, 1.0  # a point in the camera frame: its pixel before and after
    before = np.array([800.0 * x / z + 272.0, 800.0 * y / z + 480.0])
    after = np.array([fx * x / z + cx, fy * y / z + cy])
    height = round(544 * 4 / 3)  # the 3:4 crop: 544 x 725, from row (960 - 725) // 2
    expected = [before[0] * 480 / 544, (before[1] - (960 - height) // 2) * 640 / height]
    assert after == pytest.approx(expected, abs=1e-6)
    wide, (wfx, wfy, _, _) = at_size(np.zeros((360, 640, 3), np.uint8), (500.0, 500.0, 320.0, 180.0), (640, 480))
    assert wide.shape[:2] == (480, 640) and wfx == pytest.approx(wfy, rel=1e-3)  # 16:9 cropped to 4:3


def test_device_pipeline_gives_the_stages_the_device_setting_as_asked(tmp_path, monkeypatch):
    """`pipeline device --device auto` runs the stages as `dvc repro` does with the default config
    (device=auto: a skipped 3DGS stage then loads no torch), not with the device it resolved to."""
    from benchmarks.pipeline import device as device_pipeline

    seen = []

    def run_stage(stage, scene, overrides, env):
        seen.append((stage, overrides))
        raise RuntimeError("stop after the first stage")

    monkeypatch.setattr(device_pipeline, "run_stage", run_stage)
    for setting, expected in ((None, "device=cpu"), ("auto", "device=auto")):
        with pytest.raises(RuntimeError, match="first stage"):
            device_pipeline.measure_scene("mini", "cpu", tmp_path, [], {}, [], 1, setting=setting)
        assert seen[-1][0] == "generate" and expected in seen[-1][1]


def test_step_profile_counts_a_steps_operators_and_ranks_them(monkeypatch):
    """`train profile` on a tiny buffer: per-step counts (the head's products are there once per
    layer and pass), its own times ranked, the step's wall; kernels only where there is a device."""
    monkeypatch.syspath_prepend(str(REPO / "tests"))
    from test_train_device import _bundle_buffer, _opts

    from benchmarks.train.step_profile import profile_training

    record = profile_training(_bundle_buffer(), 3.0, _opts(report_every=5), head_width=32, head_blocks=1,
                              device="cpu", iterations=10)
    assert record["iterations"] == 10 and record["cuda_graph"] is None
    assert record["kernels_per_step"] is None and record["kernel_ms_per_step"] is None
    assert record["wall_ms_per_step"] > 0 and record["operators_per_step"] > 50
    assert 0 < record["host_draw_ms_per_step"] < record["wall_ms_per_step"]
    top = record["top"]
    times = [r["self_us_per_step"] for r in top]
    assert times == sorted(times, reverse=True) and times[0] > 0
    products = {r["name"]: r["per_step"] for r in top if r["name"] in ("aten::mm", "aten::addmm")}
    # 2 blocks x 3 layers + fc1, fc2, out = 9 linear layers: 9 forward products (addmm) and their
    # backward products (mm: the input's gradient, but the first layer's, and every weight's)
    assert products.get("aten::addmm") == 9 and products.get("aten::mm", 0) >= 9


def test_wrong_prior_turns_and_moves_the_learned_pose_by_what_it_is_asked():
    """`accuracy wrong-prior`: the perturbed pose is turned by exactly the degrees asked about an
    axis through the camera centre, and its centre moved by exactly the shift asked."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from benchmarks.accuracy.wrong_prior import perturbed_pose
    from usvc.core.geometry import camera_centers

    rng = np.random.default_rng(3)
    R = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    t = np.array([0.4, -1.2, 2.5])
    for degrees, shift in [(0.0, 0.0), (10.0, 0.0), (0.0, 0.7), (120.0, 2.0)]:
        R2, t2 = perturbed_pose(R, t, degrees, shift, rng)
        turned = np.degrees(np.arccos(np.clip((np.trace(R2 @ R.T) - 1) / 2, -1, 1)))
        assert turned == pytest.approx(degrees, abs=1e-6)
        assert np.linalg.norm(camera_centers(R2, t2) - camera_centers(R, t)) == pytest.approx(shift, abs=1e-9)
        assert np.allclose(R2 @ R2.T, np.eye(3), atol=1e-12)


def test_pipeline_time_records_the_cpu_and_each_scenes_training_precision(tmp_path):
    """A mapping time is a figure of its CPU: `pipeline time` and `pipeline fresh` record the model,
    whether it runs bf16 natively, and the precision each scene's training resolved `auto` to."""
    from benchmarks.pipeline._stages import machine
    from usvc.core.precision import cpu_has_native_bf16

    results = tmp_path / "results"
    (results / "mini").mkdir(parents=True)
    (results / "mini" / "train.json").write_text(json.dumps({"precision": "bf16", "iterations": 500}))
    info = machine(results, ["mini", "office"])
    assert info["train_precision"] == {"mini": "bf16"}  # office has no train.json: not listed
    assert info["native_bf16"] is cpu_has_native_bf16()
    assert isinstance(info["cpu_model"], str) and info["cpu_model"]


def test_pipeline_maps_a_capture_only_in_a_fresh_clone(tmp_path):
    """`--map PHOTOS` times `usvc map` in a fresh clone (`pipeline fresh`); `pipeline time` runs in
    this checkout, where it would add the scene, so it has no `--map` and refuses one before anything
    runs."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.pipeline", "time", "--scene", "mini", "--map",
                           str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "unrecognized arguments: --map" in proc.stderr


def test_query_before_after_pairs_each_scene_with_the_revisions_folder():
    """`--before-scene-dir` gives the revision one folder per scene (a map's landmarks in the format
    that code reads); a count that does not pair up stops before any worktree is made."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.query", "before-after", "--before", "HEAD",
                           "--scene-dir", "data/mini", "data/office", "--before-scene-dir", "data/mini"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert "--before-scene-dir: 1 folders for 2 --scene-dir" in proc.stderr


def test_before_after_runs_each_tree_with_its_own_usvc(tmp_path):
    """Each timed run of `query before-after` is `_revision_run.py` with one tree first on its
    PYTHONPATH: `usvc` comes from that tree (here this checkout: it gets as far as the scene), and a
    tree whose `usvc` is not the one imported stops the run rather than timing the wrong code."""
    child = REPO / "benchmarks" / "query" / "_revision_run.py"
    args = [str(tmp_path / "nowhere"), "own", "1", "opencv", "default", str(tmp_path / "run.json")]
    for tree, expected in ((REPO, "prepared scene not found"), (tmp_path, f"not from {tmp_path}")):
        env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
        proc = subprocess.run([sys.executable, str(child), str(tree), *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode != 0 and expected in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "run.json").exists()


def _benchmark_called(step: str) -> tuple[str, str]:
    """(family, subcommand) of the `python -m benchmarks.<family> <subcommand>` a step runs; the
    subcommand must be one the family has."""
    words = step.split()
    k = words.index("-m")
    family = words[k + 1].removeprefix("benchmarks.")
    assert words[k + 1].startswith("benchmarks.") and words[k + 2] in _cli.family_package(family).SUBCOMMANDS
    return family, words[k + 2]


@pytest.mark.parametrize("quick", [False, True])
def test_device_check_runs_existing_benchmarks_within_one_call(quick):
    """scripts/device_check.sh (one call on a GPU machine, at most ten minutes): each step names a
    benchmark that exists, the steps' limits add up to under the budget and the budget to under a
    call's ten minutes, a real scene comes last, and the CUDA tests it runs are the files that carry
    the `cuda` mark."""
    args = ["bash", str(REPO / "scripts" / "device_check.sh"), "--dry-run"] + (["--quick"] if quick else [])
    *lines, budget = subprocess.run(args, capture_output=True, text=True, check=True, timeout=60).stdout.splitlines()
    names = [line.split(" ")[0] for line in lines]
    assert names == ["pytest_cuda", "pipeline", "query", "folder", "serve", "profile_8192"]
    limits = [int(line.split("(")[1].split(" s)")[0]) for line in lines]
    assert sum(limits) <= int(budget.split()[1]) <= (900 if quick else 570)  # every step's limit is cut to the budget
    called = [_benchmark_called(line) for line in lines[1:]]
    assert called == [("pipeline", "device"), ("query", "speed"), ("query", "folder"), ("query", "serve-load"),
                      ("train", "profile")]
    *with_bird, _ = subprocess.run(args + ["--real", "bird"], capture_output=True, text=True, check=True,
                                   timeout=60).stdout.splitlines()
    assert with_bird[:-1] == lines and with_bird[-1].startswith("real_bird (")  # last: it gets what is left
    assert _benchmark_called(with_bird[-1]) == ("pipeline", "device") and "--scene bird --work" in with_bird[-1]
    assert "--from prepare" in with_bird[-1]
    cuda_mark = re.compile(r"pytest\.mark\.cuda")
    marked = sorted(p.relative_to(REPO).as_posix() for p in (REPO / "tests").glob("test_*.py")
                    if cuda_mark.search(p.read_text()))
    assert sorted(w for w in lines[0].split() if w.startswith("tests/")) == marked and marked


def test_localize_cli_runs_the_command_line_a_user_types():
    """`query cli` times `usvc localize` itself: the command it builds parses as the CLI's own (the
    map, the photos in order, the intrinsics to the precision the photos' were given), and a command
    that fails stops the benchmark with the command and its error rather than a figure."""
    from benchmarks.query.cli import localize_command, run_command, summary
    from usvc.cli import build_parser

    cmd = localize_command(Path("m/map.pt"), (754.2609, 754.2609, 640.0, 360.0), [Path("b.jpg"), Path("a.jpg")], 2)
    assert cmd[:3] == [sys.executable, "-m", "usvc.cli"]
    args = build_parser().parse_args(cmd[3:])
    assert (args.threads, args.map, args.photos) == ("2", "m/map.pt", ["b.jpg", "a.jpg"])
    assert args.intrinsics == pytest.approx([754.261, 754.261, 640.0, 360.0], abs=1e-3)
    with pytest.raises(SystemExit, match="exit 2"):
        run_command([sys.executable, "-m", "usvc.cli", "localize", "--no-such-option"])
    assert summary([0.3, 0.1, 0.2]) == {"median": 0.2, "max": 0.3, "min": 0.1, "n": 3}


def test_device_check_cuts_every_step_to_what_is_left_of_its_budget(tmp_path):
    """One call on a lent machine has a hard limit: each step runs at most for what the budget has
    left, and a step with next to nothing left is skipped and said so (here every step is a command
    that takes 3 s, in a budget of 7 s: the first runs, the others are skipped); a real scene whose
    photos are missing stops the script before anything runs, with the command that brings them."""
    fake = tmp_path / "python"
    fake.write_text('#!/bin/sh\n[ "$1" = "-" ] && exit 0\nsleep 3\n')
    fake.chmod(0o755)
    env = {**os.environ, "PYTHON": str(fake), "OUT": str(tmp_path / "out"), "USVC_DEVICE_WORK": str(tmp_path / "w")}
    script = str(REPO / "scripts" / "device_check.sh")
    proc = subprocess.run(["bash", script, "--budget", "7", "--wheels", str(tmp_path / "none")], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    steps = (tmp_path / "out" / "steps.txt").read_text().splitlines()
    # bash's SECONDS counts whole clock seconds, so the first step may start in the budget's second second
    assert steps[0].startswith("pytest_cuda: exit 0 in ") and steps[0].endswith(("(limit 7 s)", "(limit 6 s)"))
    assert [line.split(":")[0] for line in steps[1:]] == ["pipeline", "query", "folder", "serve", "profile_8192"]
    assert all("skipped" in line and "of the 7 s budget" in line for line in steps[1:])
    checkout = tmp_path / "checkout"  # a checkout with a scene declared and its photos not there
    (checkout / "scripts").mkdir(parents=True)
    (checkout / "conf" / "scene").mkdir(parents=True)
    (checkout / "conf" / "scene" / "kitchen.yaml").write_text("defaults: [base_scene, _self_]\nname: kitchen\n")
    (checkout / "scripts" / "device_check.sh").write_text(Path(script).read_text())
    missing = subprocess.run(["bash", str(checkout / "scripts" / "device_check.sh"), "--real", "kitchen"], env=env,
                             capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "copy_shared_scene.sh kitchen" in missing.stderr
    assert not (tmp_path / "out" / "logs" / "real_kitchen.log").exists()


@pytest.mark.slow
def test_scaling_runs_every_stage_at_two_sizes_and_plots_them(tmp_path):
    """`pipeline scaling` at two tiny sizes of the generated room, in a copy of the checkout: each
    size's stages, bytes, query time and both accuracies in the JSON, the log-log plot beside it,
    the one-at-a-time query timed in alternated rounds once both are built, and the generated
    scenes' folders removed afterwards."""
    import shutil

    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for name in ("conf", "stages"):
        shutil.copytree(REPO / name, checkout / name)
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, checkout / name)
    env = {**os.environ, "USVC_BENCHMARK_DIR": str(tmp_path / "reports"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.pipeline", "scaling", "--frames", "8", "12",
                           "--threads", "1", "--checkout", str(checkout), "--variant", "smoke", "--query-rounds", "2",
                           "--",
                           "train.iterations=20",
                           "buffer.min_size=8192", "generate.n_query_frames=3", "generate.supersample=1"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "reports" / "pipeline_scaling_smoke.json").read_text())
    sizes = report["sizes"]
    assert [s["mapping_frames"] for s in sizes] == [8, 12] and [s["scene"] for s in sizes] == ["room8", "room12"]
    for s in sizes:
        assert set(s["stages"]) >= {"prepare", "sfm", "buffer", "train", "landmarks", "relocalize", "metrics"}
        assert all(v["seconds"] > 0 for v in s["stages"].values())
        assert s["map_bytes"] > 0 and s["landmarks_bytes"] > 0 and s["query_ms_median"] > 0
        assert s["query_latency_ms"]["total"] >= s["query_latency_ms"]["network"] > 0
        rounds = s["query_latency_rounds_ms"]
        assert len(rounds) == 2 and min(rounds) <= s["query_latency_ms"]["total"] <= max(rounds)
        assert s["queries"] == 3 and 0 <= s["share_without_fallback"] <= 1 and s["train_steps"] == 20
        assert "acc_5cm_5deg" in s["metrics"] and "initial_acc_5cm_5deg" in s["metrics"]
    assert report["query_rounds"] == 2
    rounds = [line.split(" query round")[0].strip() for line in proc.stdout.splitlines() if " query round" in line]
    assert rounds == ["room8", "room12", "room8", "room12"]  # after both are built, the sizes alternated
    lines = proc.stdout.splitlines()
    built = max(i for i, line in enumerate(lines) if line.split()[:2] == ["room12", "metrics"])
    assert built < min(i for i, line in enumerate(lines) if " query round" in line)
    assert (tmp_path / "reports" / "pipeline_scaling_smoke.png").stat().st_size > 10_000
    assert not any((checkout / "data").glob("room*")) and not any((checkout / "results").glob("room*"))


@pytest.mark.slow
def test_triangulation_benchmark_times_the_three_ways_on_one_scenes_matches(tmp_path):
    """`pipeline triangulation` on a small generated room: each way's seconds per round, its points
    (COLMAP's within 2 % of the groups'), and the groups' one model for one and two threads."""
    from usvc.generate.params import RoomParams
    from usvc.generate.writer import generate_scene
    from usvc.prepare.importers import load_scene
    from usvc.prepare.working_images import prepare_scene

    generate_scene(tmp_path / "raw", RoomParams(frames_per_map_sequence=8, n_query_frames=2, supersample=1))
    prepared = tmp_path / "room" / "prepared"
    prepared.mkdir(parents=True)
    prepare_scene(load_scene("ace", tmp_path / "raw", "room", "given"), prepared, working_width=0)
    env = {**os.environ, "USVC_BENCHMARK_DIR": str(tmp_path / "reports"), "OMP_NUM_THREADS": "2"}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.pipeline", "triangulation", "--scene-dir",
                           str(tmp_path / "room"), "--threads", "2", "--rounds", "2", "--points-per-problem", "200",
                           "--variant", "smoke"], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "reports" / "pipeline_triangulation_room_smoke.json").read_text())
    ways = report["ways"]
    assert list(ways) == ["colmap_one_problem_1_thread", "groups_1_thread", "groups_2_threads"]
    assert all(len(w["seconds"]) == 2 and w["median_s"] > 0 and w["same_model_every_round"] for w in ways.values())
    assert ways["groups_1_thread"]["points"] == ways["groups_2_threads"]["points"] > 300
    assert abs(ways["colmap_one_problem_1_thread"]["points"] - ways["groups_1_thread"]["points"]) <= \
        0.02 * ways["groups_1_thread"]["points"]
    assert report["groups_same_model_for_any_thread_count"] and report["mapping_frames"] == 16
