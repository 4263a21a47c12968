"""Stage: encoder features of augmented mapping views, sampled per view, into buffer.h5."""

from usvc.buffer.options import BufferOptions
from usvc.buffer.run import Inputs, run
from usvc.model.options import ModelOptions
from usvc.pipeline.stage import Stage

stage = Stage("buffer", torch_device=True, model=ModelOptions, buffer=BufferOptions)


@stage.main
def main(cfg, paths, out):
    inputs = Inputs(scene=paths.scene_file, keypoints=paths.keypoints_file, render=paths.render_file)
    return run(inputs, out, stage.options(cfg, "buffer"), stage.options(cfg, "model"), seed=cfg.seed,
               device=stage.device)


if __name__ == "__main__":
    main()
