"""How right the answers are: `python -m benchmarks.accuracy SUBCOMMAND [options]`.

Reports: results/benchmarks/accuracy_<subcommand>[_<scene>][_<variant>].json. `sift_pnp.py` (the
baseline's method) and `diagnosis.py` (the map diagnosis's measures) are the code behind two of them.
"""

SUBCOMMANDS = {  # subcommand: (module, what it measures)
    "baseline-sift": ("baseline_sift", "SIFT + PnP against an SfM model, the classical baseline"),
    "compare-poses": ("compare_poses", "two methods' poses on one scene's queries, query by query"),
    "confidence": ("confidence", "how well `success` and `confidence` separate right answers from wrong ones"),
    "diagnose-map": ("diagnose_map", "a map's fit, generalisation, keypoint error and track retrieval"),
    "focal": ("focal", "what not knowing the query's focal length costs"),
    "keypoints": ("keypoints", "how well a map predicts its scene keypoints (single against multiview)"),
    "pnp-solvers": ("pnp_solvers", "the PnP backends on synthetic scenes shaped like dense scene coordinates"),
    "sfm-posing": ("sfm_posing", "SfM poses of an unposed capture against the capture's given poses"),
    "wrong-prior": ("wrong_prior", "what a query answers when its learned pose is wrong on purpose"),
}
