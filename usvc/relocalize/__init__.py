"""relocalize: each query photo's pose against a trained map.

From the stage down: `run` (every query of the scene, the files it writes) -> `relocalizer.Relocalizer`
(the map loaded; per photo the network, the dense PnP and the verdicts on the answer) ->
`features.path.FeaturePath` (refinement by features, the sub-package's one entry point)."""
