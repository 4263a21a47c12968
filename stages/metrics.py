"""Stage: score the relocalized query poses against ground truth; write metrics.json, headline.json and plots."""

from usvc.metrics.evaluate import HEADLINE_FILE
from usvc.metrics.run import Inputs, run
from usvc.pipeline.stage import Stage

stage = Stage("metrics", artifact="plots")  # reads no config group: only the scene's artifacts


@stage.main
def main(cfg, paths, out):
    inputs = Inputs(scene=paths.scene_file, tracks=paths.tracks_file, poses=paths.poses_file,
                    queries=paths.queries_file)
    return run(inputs, out, headline=stage.outputs(cfg)[1].with_name(HEADLINE_FILE))


if __name__ == "__main__":
    main()
