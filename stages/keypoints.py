"""Stage: score every SfM point by descriptor consistency (paper eq. 1-3) and keep M >= tau."""

from usvc.keypoints.options import KeypointOptions
from usvc.keypoints.run import Inputs, run
from usvc.pipeline.stage import Stage

stage = Stage("keypoints", keypoints=KeypointOptions)


@stage.main
def main(cfg, paths, out):
    return run(Inputs(tracks=paths.tracks_file), out, stage.options(cfg, "keypoints"))


if __name__ == "__main__":
    main()
