"""Stage: import the scene from its source format and resize images to the working resolution."""

from usvc.pipeline.stage import Stage
from usvc.prepare.options import SceneOptions
from usvc.prepare.run import run
from usvc.sfm.options import SfmOptions

stage = Stage("prepare", artifact="prepared", record="prepared", scene=SceneOptions, sfm=SfmOptions)


@stage.main
def main(cfg, paths, out):
    return run(stage.options(cfg, "scene"), out, stage.options(cfg, "sfm"), threads=stage.threads)


if __name__ == "__main__":
    main()
