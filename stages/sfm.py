"""Stage: SIFT + matching + triangulation (poses fixed) of the mapping images with pycolmap."""

from usvc.pipeline.stage import Stage
from usvc.sfm.options import SfmOptions
from usvc.sfm.run import Inputs, run

stage = Stage("sfm", sfm=SfmOptions)


@stage.main
def main(cfg, paths, out):
    return run(Inputs(scene=paths.scene_file), out, stage.options(cfg, "sfm"), threads=stage.threads)


if __name__ == "__main__":
    main()
