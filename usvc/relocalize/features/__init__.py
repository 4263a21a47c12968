"""Refinement by features: the query's SIFT keypoints matched to the map's landmarks, LO-RANSAC PnP.

The relocalizer reaches it through one entry point, `path.FeaturePath` (path.py: the order of the
hypotheses, the last pass, the focal verdicts). Below it: the query's SIFT (`sift`), the mapping
photos most like it (`retrieval`), the matching by descriptor (`matching`, on `byte_products`,
`tiled_matching`, `device_matching`), the passes that turn matches into poses (`passes`), SIFT +
PnP's verified matching (`verified_matching`) and the evidence that shares it (`evidence`), and
the answer's last pass (`last_pass`)."""
