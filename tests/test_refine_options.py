"""One rule for the keypoint-guided refinement's values: RelocalizeOptions' refine_* fields (the
config) and RefineOptions (what refine_pose takes, built from them) both go through
`refine_problems`, so neither accepts what the other refuses."""

from __future__ import annotations

import dataclasses
import re

import pytest

from usvc.core.errors import UsvcError
from usvc.relocalize.keypoint_refinement import RefineOptions
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.relocalizer import refine_options


@pytest.mark.parametrize("name, bad", [
    ("max_iterations", 0), ("delta", 0.0), ("max_iterations", -1), ("delta", -1e-3),
    ("radius_px", 0.0), ("min_correspondences", 0), ("delta", float("inf")), ("radius_px", float("nan")),
])
def test_both_options_refuse_the_same_values(name, bad):
    config = RelocalizeOptions(**{f"refine_{name}": bad})
    problems = config.problems()
    assert len(problems) == 1 and problems[0].startswith(f"refine_{name}={bad!r} must be"), problems
    rule = problems[0].removeprefix("refine_")
    with pytest.raises(UsvcError, match=f"^refinement option {re.escape(rule)}$"):
        refine_options(config)  # the config path: RefineOptions built from RelocalizeOptions
    valid = refine_options(RelocalizeOptions())
    with pytest.raises(UsvcError, match=f"refinement option {name}="):
        dataclasses.replace(valid, **{name: bad})  # the library path: RefineOptions on its own


def test_zero_iterations_and_zero_delta_are_refused_on_both_paths():
    """T_max = 0 would never refine and delta = 0 would never converge: the config refused them,
    and RefineOptions (which accepted >= 0) now refuses them too."""
    config = RelocalizeOptions(refine_max_iterations=0, refine_delta=0.0)
    assert config.problems() == ["refine_max_iterations=0 must be > 0", "refine_delta=0.0 must be > 0"]
    with pytest.raises(UsvcError, match=r"max_iterations=0 must be > 0; refinement option delta=0.0 must be > 0"):
        RefineOptions(radius_px=8.0, max_iterations=0, delta=0.0, min_correspondences=20)


def test_the_defaults_pass_and_carry_over():
    config = RelocalizeOptions()
    assert config.problems() == []
    opts = refine_options(config)
    assert (opts.radius_px, opts.max_iterations, opts.delta, opts.min_correspondences) == (
        config.refine_radius_px, config.refine_max_iterations, config.refine_delta, config.refine_min_correspondences)
    assert RefineOptions(radius_px=0.5, max_iterations=1, delta=1e-9, min_correspondences=1).problems() == []
