"""Which stages a sweep reruns: read from dvc.yaml, so it follows what DVC itself would rerun."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest
import yaml
from conftest import REPO

from usvc.core.errors import UsvcError
from usvc.pipeline.plan import (
    PlanError,
    first_affected_stage,
    load_plan,
    override_key,
    split_plan,
    stages_reading,
)
from usvc.pipeline.sweep import column_order, format_table, sweep_table

PLAN = load_plan(REPO / "dvc.yaml")


def test_plan_follows_dvc_yaml_order_and_outs():
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    assert [st.name for st in PLAN] == list(stages)
    by_name = {st.name: st for st in PLAN}
    assert not by_name["generate"].per_scene and by_name["relocalize"].per_scene
    assert by_name["train"].artifacts == ("map",) and by_name["prepare"].artifacts == ("prepared",)
    assert by_name["generate"].artifacts == () and by_name["metrics"].artifacts == ()
    assert by_name["train"].target("office") == "train@office" and by_name["generate"].target("mini") == "generate"
    assert ("conf/config.yaml", ("seed", "defaults")) in by_name["buffer"].params
    assert ("conf/keypoints/default.yaml", None) in by_name["keypoints"].params


@pytest.mark.parametrize("overrides, first", [
    (["keypoints.tau=2.0"], "keypoints"),
    (["train.bundle_weight=0.5"], "train"),
    (["method=single"], "gaussians"),  # the method files set buffer.rendered_views, which decides the 3DGS fit
    (["gaussians.iterations=100"], "gaussians"),
    (["render.max_angle_deg=30"], "render"),
    (["buffer.rendered_views=true"], "gaussians"),
    (["relocalize.refine_delta=0.01"], "relocalize"),
    (["relocalize.max_error_px=5"], "relocalize"),
    (["seed=1"], "buffer"),
    (["sfm.seed=3"], "prepare"),  # unposed scenes are posed by SfM in prepare
    (["model=default"], "buffer"),
    (["keypoints.tau=1.0", "relocalize.refine_radius_px=4"], "keypoints"),
    (["relocalize.refine_radius_px=4", "keypoints.tau=1.0"], "keypoints"),
    (["scene=mini", "++train.lr=0.001", "hydra.verbose=true", "data_dir=/tmp/x"], "train"),
    (["+buffer.size=1024"], "buffer"),
])
def test_first_affected_stage_on_real_dvc_yaml(overrides, first):
    assert first_affected_stage(overrides, PLAN) == first


def test_method_files_are_read_per_key():
    assert stages_reading("train.bundle_weight", PLAN) == ["train"]
    assert stages_reading("relocalize.refine", PLAN) == ["relocalize"]
    assert stages_reading("landmarks.descriptor", PLAN) == ["landmarks"]
    assert stages_reading("method", PLAN) == ["gaussians", "render", "buffer", "train", "relocalize"]
    assert stages_reading("buffer.rendered_views", PLAN) == ["gaussians", "render", "buffer"]
    assert stages_reading("buffer.size", PLAN) == ["buffer"]  # the others track only rendered_views
    assert stages_reading("gaussians.tile", PLAN) == ["gaussians", "render"]
    assert stages_reading("gaussians.iterations", PLAN) == ["gaussians"]
    assert stages_reading("seed", PLAN) == ["buffer", "train", "relocalize"]


def test_scene_group_starts_at_generate_only_for_the_generated_scene():
    assert first_affected_stage(["scene.working_width=160"], PLAN, generated=True) == "generate"
    assert first_affected_stage(["scene=office", "scene.working_width=320"], PLAN, generated=False) == "prepare"


def test_split_plan_reuses_everything_before_the_first_stage():
    upstream, rerun = split_plan(PLAN, "relocalize", generated=True)
    assert [st.name for st in upstream] == ["generate", "prepare", "sfm", "gaussians", "keypoints", "render",
                                            "buffer", "train", "landmarks"]
    assert [st.name for st in rerun] == ["relocalize", "metrics"]
    upstream, rerun = split_plan(PLAN, "keypoints", generated=False)
    assert [st.name for st in upstream] == ["prepare", "sfm", "gaussians"]  # a tau sweep reuses the 3DGS fit
    assert [st.name for st in rerun] == ["keypoints", "render", "buffer", "train", "landmarks", "relocalize",
                                         "metrics"]
    upstream, rerun = split_plan(PLAN, "landmarks", generated=False)  # a landmarks sweep reuses the map
    assert [st.name for st in upstream][-1] == "train"
    assert [st.name for st in rerun] == ["landmarks", "relocalize", "metrics"]


def test_unknown_key_is_named():
    with pytest.raises(UsvcError, match="no stage reads foo.bar"):
        first_affected_stage(["keypoints.tau=1", "foo.bar=1"], PLAN)
    with pytest.raises(PlanError, match="no stage reads colour"):
        first_affected_stage(["colour=red"], PLAN)


def test_scene_alone_is_nothing_to_sweep():
    with pytest.raises(PlanError, match="nothing to sweep"):
        first_affected_stage(["scene=mini"], PLAN)
    with pytest.raises(PlanError, match="nothing to sweep"):
        first_affected_stage(["hydra.job.name=x", "results_dir=/tmp/r"], PLAN)


def test_generate_only_key_on_a_real_scene_is_refused():
    assert stages_reading("generate.seed", PLAN) == ["generate"]
    assert first_affected_stage(["generate.seed=1"], PLAN, generated=True) == "generate"
    with pytest.raises(PlanError, match="only for the generated scene"):
        first_affected_stage(["scene=office", "generate.seed=1"], PLAN, generated=False)


def test_override_key():
    assert override_key("++train.lr=1e-3") == "train.lr"
    assert override_key("~seed") == "seed"
    assert override_key("model@foo=small") == "model"
    for ignored in ("scene=office", "data_dir=x", "results_dir=y", "hydra.run.dir=z", "hydra/launcher=basic"):
        assert override_key(ignored) is None


SYNTHETIC = """
stages:
  make:
    cmd: python -m stages.make
    params:
      - conf/make/default.yaml:
    outs:
      - data/raw/toy
  first:
    foreach: ${scenes}
    do:
      cmd: python -m stages.first scene=${item}
      params:
        - conf/alpha/a.yaml:
        - conf/config.yaml:
            - gamma
      outs:
        - data/${item}/one
        - data/${item}/two:
            cache: false
  second:
    foreach: ${scenes}
    do:
      cmd: python -m pkg.second scene=${item}
      params:
        - conf/mode/x.yaml:
            - beta
        - conf/mode/y.yaml:
            - beta
        - conf/beta/default.yaml:
        - plain_key
      outs:
        - data/${item}/three
  third:
    foreach: ${scenes}
    do:
      cmd: python -m stages.third scene=${item}
      params:
        - conf/mode/x.yaml:
            - delta
        - conf/config.yaml:
      outs:
        - results/${item}/three.json
"""


@pytest.fixture
def synthetic(tmp_path):
    path = tmp_path / "dvc.yaml"
    path.write_text(textwrap.dedent(SYNTHETIC))
    return load_plan(path)


def test_synthetic_plan(synthetic):
    assert [st.name for st in synthetic] == ["make", "first", "second", "third"]
    assert [st.artifacts for st in synthetic] == [(), ("one", "two"), ("three",), ()]
    assert synthetic[2].module == "pkg.second"
    assert ("params.yaml", ("plain_key",)) in synthetic[2].params


@pytest.mark.parametrize("overrides, first", [
    (["alpha.k=1"], "first"),
    (["alpha=other"], "first"),
    (["beta.k=1"], "second"),  # conf/beta/ and key beta of the mode files
    (["mode=y"], "second"),
    (["delta.k=1"], "third"),  # only as a top-level key of a mode file
    (["gamma=2"], "first"),
    (["epsilon=2"], "third"),  # a top-level key of the primary config, which `third` tracks whole
    (["make.size=3"], "make"),
    (["delta.k=1", "gamma=0"], "first"),
])
def test_synthetic_first_stage(synthetic, overrides, first):
    assert first_affected_stage(overrides, synthetic) == first


def test_synthetic_errors_and_scene_filter(synthetic):
    with pytest.raises(PlanError, match="no stage reads zeta.k"):
        first_affected_stage(["zeta.k=1"], synthetic)
    with pytest.raises(PlanError, match="no stage reads plain_key.x"):  # params.yaml keys are not Hydra config
        first_affected_stage(["plain_key.x=1"], synthetic)
    with pytest.raises(PlanError, match="only for the generated scene"):
        first_affected_stage(["make.size=3"], synthetic, generated=False)
    upstream, rerun = split_plan(synthetic, "second", generated=False)
    assert [s.name for s in upstream] == ["first"] and [s.name for s in rerun] == ["second", "third"]


def test_column_order_puts_headlines_first():
    keys = ["n_queries", "kept", "acc_10cm_5deg", "median_rot_deg", "first_stage", "acc_1cm_1deg", "ms_per_query",
            "initial_acc_5cm_5deg", "acc_5cm_5deg", "median_trans_cm", "train_seconds"]
    assert column_order(keys) == ["acc_1cm_1deg", "acc_5cm_5deg", "acc_10cm_5deg", "median_rot_deg", "median_trans_cm",
                                  "initial_acc_5cm_5deg", "train_seconds", "ms_per_query", "kept", "n_queries",
                                  "first_stage"]


def test_sweep_table_reads_job_dirs(tmp_path):
    for num, (value, acc) in enumerate([(5, 0.5), (10, 0.75)]):
        job = tmp_path / f"{num}_relocalize.max_error_px={value}"
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(f"- relocalize.max_error_px={value}\n")
        (job / "metrics.json").write_text(json.dumps({"n_queries": 20, "ms_per_query": 12.5, "acc_5cm_5deg": acc,
                                                      "first_stage": "relocalize", "nested": {"a": 1}}))
    lines = sweep_table(tmp_path).splitlines()
    assert [c.strip() for c in lines[0].split(" | ")] == ["job", "overrides", "acc_5cm_5deg", "ms_per_query"]
    assert len(lines) == 5 and "relocalize.max_error_px=10" in lines[3] and "0.75" in lines[3]
    assert lines[4] == "same in every job: n_queries=20, first_stage=relocalize"  # not a headline, not swept
    one = format_table([{"job": "0", "overrides": "seed=1", "n_queries": 20}])
    assert one.splitlines()[0].split(" | ")[-1] == "n_queries"  # one row: nothing to fold
    assert format_table([]) == "(no job wrote metrics)"


@pytest.mark.slow
def test_sweep_refuses_scene_only_before_running_anything(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "tools.sweep", "scene=mini", f"hydra.run.dir={tmp_path}/job"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert "nothing to sweep" in proc.stderr + proc.stdout
    assert not (tmp_path / "job" / "logs").exists()
