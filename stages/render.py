"""Stage: render novel views around keypoint clusters from the 3DGS model, with keypoint observations."""

from usvc.pipeline.stage import Stage, skipped_without_rendered_views
from usvc.render.options import RenderOptions
from usvc.render.run import Inputs, run

stage = Stage("render", torch_device=True, render=RenderOptions)


@stage.main
def main(cfg, paths, out):
    if not cfg.buffer.rendered_views:  # only method=multiview_gs uses the views
        return skipped_without_rendered_views(out, "render", cfg.method)
    inputs = Inputs(splat=paths.splat_file, scene=paths.scene_file, keypoints=paths.keypoints_file)
    return run(inputs, out, stage.options(cfg, "render"), tile=cfg.gaussians.tile, device=stage.device)


if __name__ == "__main__":
    main()
