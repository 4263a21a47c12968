"""Stage: render novel views around keypoint clusters from the 3DGS model, with keypoint observations."""

from usvc.pipeline.stage import Stage
from usvc.render.options import RenderOptions

stage = Stage("render", torch_device=True, for_rendered_views=True, render=RenderOptions)


@stage.main
def main(cfg, paths, out):
    from usvc.render.run import Inputs, run  # torch: loaded only where views are rendered

    inputs = Inputs(splat=paths.splat_file, scene=paths.scene_file, keypoints=paths.keypoints_file)
    return run(inputs, out, stage.options(cfg, "render"), tile=cfg.gaussians.tile, device=stage.device)


if __name__ == "__main__":
    main()
