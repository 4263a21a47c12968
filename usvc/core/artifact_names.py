"""The file name of every artifact, spelled once. The module that reads or writes a file imports
its name from here, and so does `usvc.pipeline.paths` (which adds the folders: ScenePaths);
this module imports nothing, so any layer may use it.
"""

SCENE_H5 = "scene.h5"  # prepared/: images' cameras, poses and split
TRACKS_H5 = "tracks.h5"  # sfm/: the SfM model (points, observations, cameras, median depth)
POINTS_PLY = "points.ply"  # sfm/: the SfM points, for viewers
KEYPOINTS_H5 = "keypoints.h5"  # keypoints/: the kept tracks
KEYPOINTS_PLY = "keypoints.ply"  # keypoints/: the kept points, for viewers
LANDMARKS_H5 = "landmarks.h5"  # landmarks/: kept points with their SIFT descriptors
SPLAT_PLY = "splat.ply"  # gaussians/: the Gaussian splatting model
SPLAT_CHECK_PNG = "heldout_render_vs_image.png"  # gaussians/: a held-out render beside its photo
RENDER_H5 = "render.h5"  # render/: the rendered views' poses and keypoint tuples
BUFFER_H5 = "buffer.h5"  # buffer/: encoder features and their targets
HOLDOUT_H5 = "holdout.h5"  # buffer/: cells of the withheld images (buffer.holdout_every > 0)
MAP_PT = "map.pt"  # map/: the scene's map (encoder + head + metadata)
POSES_TXT = "poses.txt"  # relocalize/: one estimated pose per query
QUERIES_H5 = "queries.h5"  # relocalize/: per-query inliers, timings and refinement records
METRICS_JSON = "metrics.json"  # a --multirun job's record, in its own folder
