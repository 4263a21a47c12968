"""Config: every YAML file sets every schema field, and bad keys/values fail naming the key."""

import subprocess
import sys
from dataclasses import fields

import pytest
import yaml
from conftest import REPO
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from usvc.pipeline.config import ConfigError, group_schemas, register_configs, validate

register_configs()
GROUP_SCHEMAS = group_schemas()


@pytest.mark.parametrize("group", sorted(GROUP_SCHEMAS))
def test_every_yaml_sets_only_fields_of_its_schema(group):
    """default.yaml (generated from the dataclass) sets every field; another option of the group
    sets what differs from it, and nothing the schema does not have."""
    names = {f.name for f in fields(GROUP_SCHEMAS[group])}
    files = sorted((REPO / "conf" / group).glob("*.yaml"))
    assert files
    for path in files:
        keys = set(yaml.safe_load(path.read_text())) - {"defaults"}
        assert keys <= names, f"{path}: unknown {keys - names}"
        if path.name == "default.yaml":
            assert keys == names, f"{path}: missing {names - keys}"


def _compose(overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        return compose("config", overrides=overrides)


@pytest.mark.parametrize("scene", sorted(p.stem for p in (REPO / "conf" / "scene").glob("*.yaml")))
def test_every_scene_composes_and_validates(scene):
    cfg = _compose([f"scene={scene}"])
    validate(cfg)
    assert cfg.scene.name == scene
    assert cfg.scene.path == f"data/raw/{scene}", "dvc.yaml depends on data/raw/<scene>"


def test_unknown_key_and_wrong_type_fail_at_compose():
    with pytest.raises((ConfigCompositionException, ConfigKeyError), match="taux"):
        _compose(["keypoints.taux=1"])
    with pytest.raises((ConfigCompositionException, ValidationError), match="keypoints.tau"):
        _compose(["keypoints.tau=abc"])


@pytest.mark.parametrize("override, message", [
    ("+keypoints.taux=1", r"keypoints.taux is not a setting of usvc \(did you mean keypoints.tau\?\)"),
    ("+keypoint.tau=1000", r"config key keypoint is not a setting of usvc \(did you mean keypoints\?\)"),
    ("++train.iteration=5", r"train.iteration is not a setting"),
])
def test_keys_added_with_plus_are_refused(override, message):
    """Hydra composes `+key=value` even where the schema has no such key; validation refuses it."""
    with pytest.raises(ConfigError, match=message):
        validate(_compose([override]))


def test_value_outside_choices_names_the_key():
    with pytest.raises(ConfigError, match=r"sfm.matching='fancy'"):
        validate(_compose(["sfm.matching=fancy"]))
    with pytest.raises(ConfigError, match=r"keypoints.sigma"):
        validate(_compose(["keypoints.sigma=0"]))


@pytest.mark.slow
def test_stage_reports_bad_config_in_one_line():
    proc = subprocess.run([sys.executable, "-m", "stages.keypoints", "keypoints.weights=foo"],
                          cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 1
    assert "keypoints.weights='foo'" in proc.stderr + proc.stdout
    assert "Traceback" not in proc.stderr + proc.stdout


@pytest.mark.parametrize("override, message", [
    ("model.max_short_side=-1", "model.max_short_side=-1 must be >= 0"),
    ("relocalize.min_confidence=1.5", "relocalize.min_confidence=1.5 must be in"),
    ("relocalize.focal_tolerance=-0.1", "relocalize.focal_tolerance=-0.1 must be >= 0"),
])
def test_relocalize_thresholds_are_checked(override, message):
    with pytest.raises(ConfigError, match=message):
        validate(_compose([override]))


def test_scripts_compose_the_stage_config_with_its_validation():
    from usvc.pipeline.config import compose_for_script

    cfg = compose_for_script("office", ["buffer.holdout_every=8", "model=xfeat"])
    assert (cfg.scene.name, cfg.buffer.holdout_every, cfg.model.encoder) == ("office", 8, "xfeat")
    with pytest.raises(ConfigError, match="model.encoder='foo'"):
        compose_for_script("office", ["model.encoder=foo"])


@pytest.mark.parametrize("scene, overrides, message", [
    ("nosuch", [], r"config scene=nosuch: .*'scene/nosuch' \(available options in 'scene': .*bird, mini, office\)$"),
    ("office", ["model=nosuch"], r"'model/nosuch' \(available options in 'model': .*small.*\)$"),
    ("office", ["relocalize.nokey=1"], r"config scene=office relocalize.nokey=1: Could not override"),
    ("office", ["relocalize.refine=["], r"config scene=office relocalize.refine=\[: "),
])
def test_a_script_asked_for_a_config_that_is_not_there_gets_one_line_naming_it(scene, overrides, message):
    from usvc.core.errors import UsvcError
    from usvc.pipeline.config import compose_for_script

    with pytest.raises(UsvcError, match=message) as err:
        compose_for_script(scene, overrides)
    assert "\n" not in str(err.value)


def test_a_benchmark_given_bad_input_says_so_in_one_line():
    proc = subprocess.run([sys.executable, "-m", "benchmarks.accuracy", "compare-poses", "--scene", "nosuch",
                           "--a", "a.txt", "--b", "b.txt"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("python -m benchmarks.accuracy compare-poses: config scene=nosuch:")
    assert "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "benchmarks.accuracy", "baseline-sift", "--scene", "nosuch"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("python -m benchmarks.accuracy baseline-sift: config scene=nosuch:")


def test_shipped_ace_encoders_work_at_a_192_px_short_side():
    """The shipped encoders learned from 320x240 renders; maps of larger photos are made at a 192 px
    short side unless asked otherwise (each cell sees more of the scene: better learned poses, a
    faster query); XFeat keeps the photos' own size."""
    for model in ("default", "small", "small_real"):
        assert _compose([f"model={model}"]).model.max_short_side == 192, model
    assert _compose(["model=xfeat"]).model.max_short_side == 0


def test_multiview_methods_share_the_train_groups_bundle_weight():
    """method=multiview and multiview_gs differ only in the rendered views, and the train group's
    own value is the multi-view one, so composing without a method group trains the same map."""
    weights = {m: _compose([f"method={m}"]).train.bundle_weight for m in ("single", "multiview", "multiview_gs")}
    own = yaml.safe_load((REPO / "conf" / "train" / "default.yaml").read_text())["bundle_weight"]
    assert weights["single"] == 0.0
    assert weights["multiview"] == weights["multiview_gs"] == own > 0, (weights, own)
