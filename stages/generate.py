"""Stage: render the miniature synthetic scene (ACE layout) into scene.path."""

from pathlib import Path

from usvc.core.errors import UsvcError
from usvc.generate.params import RoomParams
from usvc.generate.run import run
from usvc.pipeline.stage import Stage, is_multirun, job_dir

# Reads the scene group's name, path and `generated` as plain values: its schema is the prepare
# step's, which runs after this one.
stage = Stage("generate", artifact=None, generate=RoomParams)


@stage.main
def main(cfg, paths, out):
    if not cfg.scene.generated:
        raise UsvcError(f"scene {cfg.scene.name!r} is not a generated scene (scene.generated=false)")
    return run(job_dir() / "raw" if is_multirun() else Path(cfg.scene.path), stage.options(cfg, "generate"))


if __name__ == "__main__":
    main()
