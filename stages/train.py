"""Stage: fit the scene's regression head on the buffer (ACE reprojection loss) -> map.pt."""

from usvc.model.options import ModelOptions
from usvc.pipeline.stage import Stage
from usvc.train.options import TrainOptions
from usvc.train.run import Inputs, run

stage = Stage("train", artifact="map", torch_device=True, model=ModelOptions, train=TrainOptions)


@stage.main
def main(cfg, paths, out):
    inputs = Inputs(buffer=paths.buffer_file, holdout=paths.holdout_file, tracks=paths.tracks_file)
    return run(inputs, out, stage.options(cfg, "train"), stage.options(cfg, "model"), seed=cfg.seed,
               scene=cfg.scene.name, method=cfg.method, device=stage.device)


if __name__ == "__main__":
    main()
