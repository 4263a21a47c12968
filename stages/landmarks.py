"""Stage: the SfM points with one SIFT descriptor each -> landmarks.h5 (feature refinement)."""

from usvc.landmarks.options import LandmarksOptions
from usvc.landmarks.run import Inputs, run
from usvc.pipeline.stage import Stage

stage = Stage("landmarks", landmarks=LandmarksOptions)


@stage.main
def main(cfg, paths, out):
    return run(Inputs(tracks=paths.tracks_file, scene=paths.scene_file), out, stage.options(cfg, "landmarks"),
               scene=cfg.scene.name)


if __name__ == "__main__":
    main()
