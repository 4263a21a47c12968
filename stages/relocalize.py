"""Stage: relocalize the scene's query images with its map -> poses.txt, queries.h5/json."""

from usvc.model.options import ModelOptions
from usvc.pipeline.stage import Stage
from usvc.pipeline.threads import query_workers
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.run import Inputs, run

stage = Stage("relocalize", torch_device=True, model=ModelOptions, relocalize=RelocalizeOptions)


@stage.main
def main(cfg, paths, out):
    inputs = Inputs(scene=paths.scene_file, map=paths.map_file, landmarks=paths.landmarks_file)
    return run(inputs, out, stage.options(cfg, "relocalize"), encoder_weights=stage.options(cfg, "model").encoder_weights,
               seed=cfg.seed, scene=cfg.scene.name, device=stage.device,
               workers=query_workers(cfg.query_workers, stage.threads))


if __name__ == "__main__":
    main()
