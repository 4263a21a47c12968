"""Stage: fit a 3D Gaussian splatting model to the mapping images; splat PLY + held-out PSNR/SSIM."""

from usvc.gaussians.options import GaussiansOptions
from usvc.gaussians.run import Inputs, run
from usvc.pipeline.stage import Stage, skipped_without_rendered_views

stage = Stage("gaussians", torch_device=True, gaussians=GaussiansOptions)


@stage.main
def main(cfg, paths, out):
    if not cfg.buffer.rendered_views:  # only method=multiview_gs uses the model
        return skipped_without_rendered_views(out, "gaussians", cfg.method)
    return run(Inputs(tracks=paths.tracks_file, scene=paths.scene_file), out, stage.options(cfg, "gaussians"),
               device=stage.device)


if __name__ == "__main__":
    main()
