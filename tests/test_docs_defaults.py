"""The figures the README and docs quote for the defaults are the ones the code and the committed
results hold: the training steps (the rule and the count on the bundled scene), the precision, the
relocalization's default options and query SIFT, the default model and method, and what the
committed mini run (`results/mini/`) says about itself. Each checker finds the quoting sentences by
regex and returns what disagrees; a made-up sentence shows that each can fail.

docs/experiments_log.md is history (superseded figures, the defaults of their time) and is not
checked."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml

from usvc.buffer.options import BufferOptions
from usvc.core.precision import PRECISIONS
from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.options import RelocalizeOptions
from usvc.train.options import TrainOptions

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted(p for p in (REPO / "docs").glob("*.md") if p.name != "experiments_log.md")]
# a clause that speaks of an earlier time quotes the defaults of that time
HISTORY = re.compile(r"\b(then|of that time|when (?:this|it) was measured|was|were|before|earlier|former)\b")


def conf(path: str) -> dict:
    return yaml.safe_load((REPO / "conf" / path).read_text(encoding="utf-8"))


def committed(stage: str) -> dict:
    return json.loads((REPO / "results" / "mini" / f"{stage}.json").read_text(encoding="utf-8"))


def prose(text: str) -> str:
    """Text with its wrapped lines joined (table rows stay rows), code fences dropped."""
    text = re.sub(r"```.*?```", " ", text, flags=re.S)
    return re.sub(r"(?<=\S) {2,}", " ", re.sub(r"(?<![|\n])\n *(?![|\n])", " ", text))


def clauses(text: str) -> list[str]:
    """Sentences and their ';'-parts; a '.' inside a number does not end one."""
    return [c for c in re.split(r"(?<!\d)\.(?!\d)|;|\n", prose(text)) if c.strip()]


def number(s: str) -> float:
    return float(s.replace(",", ""))


def pages() -> dict[str, str]:
    return {p.relative_to(REPO).as_posix(): p.read_text(encoding="utf-8") for p in PAGES}


# ---------------------------------------------------------------- what the code and results hold

def train_defaults() -> TrainOptions:
    """TrainOptions as conf/train/default.yaml sets them (the file is generated from the dataclass)."""
    values = {k: v for k, v in conf("train/default.yaml").items() if k != "defaults"}
    return TrainOptions(**values)


def buffer_defaults() -> BufferOptions:
    values = {k: v for k, v in conf("buffer/default.yaml").items() if k != "defaults"}
    return BufferOptions(**values)


def default_steps(photos: int) -> int:
    return train_defaults().steps_for(buffer_defaults().cells_for(photos))


def smallest_steps() -> int:
    return default_steps(1)


def bound_photos() -> int:
    b = buffer_defaults()
    return -(-b.max_size // b.cells_per_image)


# ---------------------------------------------------------------- the checkers

STEP_RULE = re.compile(
    r"(?:`train\.passes` \((?P<passes>[\d.]+)\) passes over it|(?P<passes2>[\d.]+) by default), i\.e\. "
    r"(?P<small>[\d,]+) steps of (?P<batch>[\d,]+) cells on the smallest buffer(?: \(up to (?P<upto>\d+) photos\))?, "
    r"(?P<mid>[\d,]+) for (?P<mid_photos>[\d,]+) photos,? (?:and )?(?P<bound>[\d,]+) at the bound"
    r"(?: \((?P<bound_photos>\d+) photos and more\))?")


def step_rule_problems(text: str) -> list[str]:
    """The training-step rule as a page states it: passes over the buffer, the steps on the smallest
    buffer (and up to how many photos it is the smallest), at N photos and at the bound."""
    t, out = train_defaults(), []
    for m in STEP_RULE.finditer(prose(text)):
        passes = float(m["passes"] or m["passes2"])
        if passes != t.passes:
            out.append(f"{m[0]!r}: passes {passes} (the code: {t.passes})")
        if number(m["batch"]) != t.batch_size:
            out.append(f"{m[0]!r}: batch {m['batch']} (the code: {t.batch_size})")
        for claim, photos in ((m["small"], 1), (m["mid"], int(number(m["mid_photos"]))), (m["bound"], bound_photos())):
            if number(claim) != default_steps(photos):
                out.append(f"{m[0]!r}: {claim} steps for {photos} photos (the code: {default_steps(photos)})")
        b = buffer_defaults()
        if m["upto"] and int(m["upto"]) != b.min_size // b.cells_per_image:
            out.append(f"{m[0]!r}: the smallest buffer up to {m['upto']} photos (the code: {b.min_size // b.cells_per_image})")
        if m["bound_photos"] and int(m["bound_photos"]) != bound_photos():
            out.append(f"{m[0]!r}: the bound at {m['bound_photos']} photos (the code: {bound_photos()})")
    return out


DEFAULT_STEPS = re.compile(r"(?<![\d.,])(\d[\d,]*) (steps|iterations)\b")
DEFAULT_IS = re.compile(r"\bthe default(?: training)? is (?:now )?(\d[\d,]*)\b(?![.\d])")
OTHER_LENGTH = re.compile(r"train=(?:long|full|fast)|train\.(?:iterations|passes)=|twelve|four times|half|quarter")
DEFAULT_PASSES = re.compile(r"(?<![\d.])(\d+\.\d+)(?: passes| now\b)")
ON_LARGER = re.compile(r"^ (?:on|for) (?:bird|bird's|\d|\w+ photos)|^ at the bound")


def default_steps_problems(text: str) -> list[str]:
    """A step count a clause gives as the default's (or as today's: "now"), with no larger scene named
    after it, is the count on the smallest buffer (the bundled scene's); so is "the default is N" in a
    sentence about training; and passes given as the default's are the default passes."""
    out = []

    def other_length(c: str, m: re.Match) -> bool:
        """train=long, train=full, ... named just before the figure, in a parenthesis still open."""
        return bool(OTHER_LENGTH.search(c[max(0, m.start() - 60):m.start()].rsplit(")", 1)[-1]))

    def check(c: str, m: re.Match) -> None:
        if other_length(c, m):
            return
        if number(m[1]) != smallest_steps():
            out.append(f"{c.strip()!r}: {m[1]} (the default on the smallest buffer: {smallest_steps()} steps)")

    for sentence in re.split(r"(?<!\d)\.(?!\d)|\n", prose(text)):
        for c in sentence.split(";"):
            if not re.search(r"default|\bnow\b", c) or HISTORY.search(c):
                continue
            for m in DEFAULT_PASSES.finditer(c):
                if not other_length(c, m) and float(m[1]) != train_defaults().passes:
                    out.append(f"{c.strip()!r}: {m[1]} passes (the default: {train_defaults().passes})")
            # training's steps ("iterations" counts too where the clause is about training, not the 3DGS fit)
            for m in DEFAULT_STEPS.finditer(c):
                if (not ON_LARGER.match(c[m.end():m.end() + 20]) and not re.search(r"\d / $", c[:m.start()])
                        and (m[2] == "steps" or "train" in c)):
                    check(c, m)
            if re.search(r"step|iteration|train", sentence):
                for m in DEFAULT_IS.finditer(c):
                    check(c, m)
    return out


PRECISION_SETTING = re.compile(r"`(?:(?:train|buffer|relocalize)\.)?precision: (\w+)`")
PRECISION_CHOICES = re.compile(r"`(?:train|buffer|relocalize)\.precision`[^`]{0,120}?\(`((?:\w+ \| )+\w+)`")


def precision_problems(text: str) -> list[str]:
    """`precision: X` as a page writes the setting is the default; the choices it lists are the code's."""
    default = TrainOptions().precision
    out = [f"`precision: {m[1]}` (the default: {default})" for m in PRECISION_SETTING.finditer(text)
           if m[1] != default]
    out += [f"precision choices `{m[1]}` (the code: {' | '.join(PRECISIONS)})"
            for m in PRECISION_CHOICES.finditer(prose(text)) if tuple(m[1].split(" | ")) != PRECISIONS]
    return out


COMMITTED_PRECISION = re.compile(r"committed (?:mini run|run of mini|run's)(?:[^.;]|\.(?=\S)){0,120}?\b(bf16|fp32)\b")
COMMITTED_FIGURES = re.compile(r"committed(?:[^.;]|\.(?=\S)){0,160}?(\d+\.\d+) cm / (\d+\.\d+)°")


def committed_run_problems(text: str) -> list[str]:
    """What a page says the committed mini run used (its precision) and gave (its median errors) is
    what results/mini/ holds."""
    train, head = committed("train"), committed("headline")
    out = [f"{m[0]!r}: {m[1]} (results/mini/train.json: {train['precision']})"
           for m in COMMITTED_PRECISION.finditer(prose(text)) if m[1] != train["precision"]]
    for m in COMMITTED_FIGURES.finditer(prose(text)):
        for claim, key in ((m[1], "median_trans_cm"), (m[2], "median_rot_deg")):
            decimals = len(claim.split(".")[1])
            if round(head[key], decimals) != float(claim):
                out.append(f"{m[0]!r}: {claim} (results/mini/headline.json {key}: {head[key]:.{decimals}f})")
    return out


RELOCALIZE_FIELDS = ("refine", "prior", "features_extractor", "features_final", "features_pnp")
RELOCALIZE_DEFAULT = re.compile(
    r"`(?:relocalize\.)?(" + "|".join(RELOCALIZE_FIELDS) + r")(?:=|: )(\w+)`[^.;|]{0,12}?\(?(?:is )?the default\b"
    r"|`usvc localize --(final|prior|refine) (\w+)`,? the default")
CLI = {"final": "features_final", "prior": "prior", "refine": "refine"}


def relocalize_default_problems(text: str) -> list[str]:
    """`relocalize.<option>=<value>`, the default: the value is RelocalizeOptions' default, the one
    conf/relocalize/default.yaml and the default method (conf/method/multiview.yaml) set."""
    code = RelocalizeOptions()
    yaml_defaults = conf("relocalize/default.yaml")
    method = conf(f"method/{default_group('method')}.yaml").get("relocalize", {})
    out = []
    for m in RELOCALIZE_DEFAULT.finditer(prose(text)):
        field, value = (m[1], m[2]) if m[1] else (CLI[m[3]], m[4])
        expected = method.get(field, getattr(code, field))
        assert yaml_defaults[field] == getattr(code, field), f"conf/relocalize/default.yaml {field} is not the dataclass's"
        if value != expected:
            out.append(f"{m[0]!r}: {value} (the default: {expected})")
    return out


HOST_SIFT = re.compile(r"COLMAP's SIFT (?:on the (?:host|CPU))")
NOT_DEFAULT = re.compile(r"prior=none|features_extractor=colmap|`colmap`|--prior none")


def query_sift_problems(text: str) -> list[str]:
    """Where a page says the query's SIFT is COLMAP's on the host, the default extractor must give
    COLMAP's on a CPU (it gives OpenCV's there, and COLMAP's only on a GPU that pycolmap can use),
    unless the sentence is about prior=none or features_extractor=colmap."""
    default = RelocalizeOptions().features_extractor
    on_cpu = sift_module.choose_sift(default, "cpu", RelocalizeOptions().prior).kind
    if on_cpu == "colmap":
        return []
    return [f"{c.strip()!r}: the default query SIFT on the host is {on_cpu}'s" for c in clauses(text)
            if HOST_SIFT.search(c) and not NOT_DEFAULT.search(c)]


def default_group(group: str) -> str:
    for entry in conf("config.yaml")["defaults"]:
        if isinstance(entry, dict) and group in entry:
            return entry[group]
    raise KeyError(group)


def group_default_problems(text: str) -> list[str]:
    """`model=X` (default) and `method=X` (default): X is what conf/config.yaml picks."""
    out = []
    for m in re.finditer(r"`(model|method)=(\w+)`[^.;|\n]{0,4}\((?:the )?default(?: model| method)?\)", prose(text)):
        if m[2] != default_group(m[1]):
            out.append(f"{m[0]!r}: {m[2]} (conf/config.yaml: {m[1]}: {default_group(m[1])})")
    return out


CHECKERS = [step_rule_problems, default_steps_problems, precision_problems, committed_run_problems,
            relocalize_default_problems, query_sift_problems, group_default_problems]


# ---------------------------------------------------------------- the code's own figures

def test_the_defaults_the_checks_read():
    """What the checks compare against: the rule gives the committed mini run's steps, and the
    committed run's precision is what `auto` gives on the CPU it ran on (bf16 or fp32)."""
    assert train_defaults() == TrainOptions() and buffer_defaults() == BufferOptions()
    assert TrainOptions().iterations == 0  # steps come from passes over the buffer
    buf, train = committed("buffer"), committed("train")
    assert buffer_defaults().cells_for(buf["mapping_images"]) == buf["cells"]
    assert train["iterations"] == default_steps(buf["mapping_images"]) == smallest_steps()
    assert default_steps(bound_photos()) == default_steps(10 * bound_photos())  # capped at the bound
    assert train["precision"] in ("bf16", "fp32") and committed("relocalize")["precision"] == train["precision"]
    assert TrainOptions().precision == BufferOptions().precision == RelocalizeOptions().precision == "auto"
    assert default_group("model") == conf(f"model/{default_group('model')}.yaml")["name"]


# ---------------------------------------------------------------- the pages

@pytest.mark.parametrize("checker", CHECKERS, ids=lambda c: c.__name__)
def test_the_pages_quote_the_defaults_as_they_are(checker):
    problems = [f"{name}: {p}" for name, text in pages().items() for p in checker(text)]
    assert not problems, "\n".join(problems)


def test_the_step_rule_and_the_committed_run_are_quoted_somewhere():
    """The checks above find what they check: the rule in method.md, the committed run's precision in
    experiments.md (a checker that matched nothing would pass whatever the pages said)."""
    text = pages()
    assert STEP_RULE.search(prose(text["docs/method.md"]))
    assert COMMITTED_PRECISION.search(prose(text["docs/experiments.md"]))
    assert any(RELOCALIZE_DEFAULT.search(prose(t)) for t in text.values())
    assert any(re.search(r"`model=\w+` \(default\)", t) for t in text.values())


# ---------------------------------------------------------------- each checker can fail

def test_a_wrong_step_rule_is_found():
    s = smallest_steps()
    good = f"training takes `train.passes` ({TrainOptions().passes}) passes over it, i.e. {s} steps of 2,048 cells on the smallest buffer, {default_steps(128):,} for 128 photos, {default_steps(bound_photos()):,} at the bound."
    assert step_rule_problems(good) == []
    bad = good.replace(f"i.e. {s} steps", "i.e. 2,000 steps")
    assert step_rule_problems(bad)
    assert step_rule_problems(good.replace(str(TrainOptions().passes), "15.625"))


def test_a_wrong_default_step_count_is_found():
    assert default_steps_problems("The default training takes 500 steps on mini's buffer.") == []
    assert default_steps_problems("The default is 2,000 steps (15.625 passes).")
    # as docs/speed.md said it until 2026-12-07
    assert default_steps_problems("Even at that peak, the 6,000 iterations that were then the default (`train=full` now; "
                                  "the default is 2,000) would take 302 s")
    assert default_steps_problems("The default training (500 steps on mini, 1,258 on bird) runs on the card.") == []
    assert default_steps_problems("the default was 2,000 steps then") == []  # history
    # as docs/results.md said it until 2026-12-07
    assert default_steps_problems("passes over it: 46.875 when this was measured (6,000 steps on the smallest buffer; "
                                  "`train=full` today), 15.625 now (2,000 steps; below)")
    assert default_steps_problems("`train=long` (2,000 / 2,000 / 5,031 steps) trains four times the default") == []
    assert default_steps_problems("the default maps (500 / 500 / 1,258 steps on mini, office and bird)") == []


def test_a_wrong_precision_is_found():
    assert precision_problems("`precision: auto` is bf16 on a CPU with native bf16.") == []
    assert precision_problems("with `precision: fp32` (the default)")
    assert precision_problems("`train.precision` (`auto | fp16`) sets the arithmetic")


def test_a_wrong_committed_run_is_found():
    train, head = committed("train"), committed("headline")
    other = "bf16" if train["precision"] == "fp32" else "fp32"
    right = f"(the committed mini run says `{train['precision']}`, from CI)"
    assert committed_run_problems(right) == []
    assert committed_run_problems(right.replace(train["precision"], other))
    assert committed_run_problems(f"The committed run of mini (`results/mini/headline.json`, from CI, {other})")
    figures = f"The committed run of mini: {head['median_trans_cm']:.4f} cm / {head['median_rot_deg']:.4f}°."
    assert committed_run_problems(figures) == []
    assert committed_run_problems("mini's committed `dvc.lock` run: 0.04816 cm / 0.00996°")


def test_a_wrong_relocalize_default_is_found():
    assert relocalize_default_problems("`relocalize.features_final=confirmed`, the default, gives") == []
    assert relocalize_default_problems("`relocalize.features_final=guided`, the default, keeps the faster answer")
    assert relocalize_default_problems("`relocalize.features_extractor: colmap` (the default) extracts")
    assert relocalize_default_problems("(`usvc localize --final images`, the default)")


def test_a_query_sift_on_the_host_named_colmaps_is_found():
    assert query_sift_problems("On an H100 a query takes 198 ms, most of it COLMAP's SIFT on the host.")
    assert query_sift_problems("With `relocalize.prior=none`, COLMAP's SIFT on the CPU.") == []
    assert query_sift_problems("OpenCV's SIFT on the host.") == []


def test_the_default_extractor_is_opencvs_without_a_gpu_sift(monkeypatch):
    """What query_sift_problems relies on: `auto` takes OpenCV's SIFT on a CPU, and on a GPU where
    pycolmap has no CUDA (PyPI's); COLMAP's with prior=none."""
    assert sift_module.choose_sift("auto", "cpu").kind == "opencv"
    monkeypatch.setattr(sift_module, "pycolmap_has_cuda", lambda: False)
    assert sift_module.choose_sift("auto", "cuda").kind == "opencv"
    assert sift_module.choose_sift("auto", "cpu", prior="none").kind == "colmap"


def test_a_wrong_default_model_or_method_is_found():
    assert group_default_problems("| `model=small` (default) | half-width shipped encoder |") == []
    assert group_default_problems("Measured with `model=default` (the default model).")
    assert group_default_problems("| `method=single` (default) | the ACE-style baseline |")
