"""The agreement check of refinement by features: a guided answer against the matches to every
landmark (`usvc.relocalize.features.evidence.QueryEvidence.agreement`, `refine_by_features`'s
`agreement`)."""

from __future__ import annotations

from test_feature_refinement import N_POINTS, OPTS, mislead_the_guided_passes, prior, scene
from test_refinement import CAM, R_TRUE, T_TRUE, errors

from usvc.relocalize.features.byte_products import scaled
from usvc.relocalize.features.path import refine_by_features


def test_a_guided_answer_that_the_matches_to_every_landmark_disagree_with_meets_them(monkeypatch):
    """A confident learned pose that is wrong may lead the guided passes to a wrong pose with some
    support, and nothing else is tried. The agreement check (the matches to every landmark: how many
    the answer explains, against how many their own P4Pf pose explains) catches it: below
    AGREEMENT, the global hypothesis competes and the better-supported pose wins. A right guided
    answer passes the check alone, and its record says what the check found."""
    from usvc.relocalize.features import path as fr
    from usvc.relocalize.features.evidence import QueryEvidence

    landmarks, feats = scene()
    desc = scaled(landmarks.descriptor)
    R0, t0 = prior(5.0, 0.10)
    evidence = QueryEvidence(landmarks, desc, None, feats, OPTS, CAM, seed=0)
    explained, reference = evidence.agreement(R_TRUE, T_TRUE, CAM)
    assert reference >= 0.8 * N_POINTS and explained >= 0.95 * reference
    off, _ = evidence.agreement(prior(3.0, 0.0)[0], T_TRUE, CAM)
    assert off < 0.2 * reference  # 3 deg off: few of the matches within 1.5 px

    def check(result):
        return evidence.agreement(result.R, result.t, CAM)

    right = refine_by_features(landmarks, desc, feats, CAM, R0, t0, OPTS, global_pairs=evidence.global_pairs,
                               agreement=check)
    assert right.path == "guided" and errors(right.R, right.t)[0] < 0.1
    assert len(right.tried) == 1 and right.tried[0]["by_their_own_pose"] == reference
    assert right.tried[0]["global_matches_explained"] >= fr.AGREEMENT * reference
    mislead_the_guided_passes(monkeypatch)
    asked = []
    caught = refine_by_features(landmarks, desc, feats, CAM, R0, t0, OPTS, verified=lambda: asked.append(1),
                                global_pairs=evidence.global_pairs, agreement=check)
    assert caught.path == "global" and errors(caught.R, caught.t)[0] < 0.1
    assert [h["path"] for h in caught.tried] == ["guided", "global"] and asked == []
    assert caught.tried[0]["global_matches_explained"] < fr.AGREEMENT * caught.tried[0]["by_their_own_pose"]
    unchecked = refine_by_features(landmarks, desc, feats, CAM, R0, t0, OPTS, global_pairs=evidence.global_pairs)
    assert unchecked.path == "guided" and [h["path"] for h in unchecked.tried] == ["guided"]  # no check asked
