"""Stage: fit a 3D Gaussian splatting model to the mapping images; splat PLY + held-out PSNR/SSIM."""

from usvc.gaussians.options import GaussiansOptions
from usvc.pipeline.stage import Stage

stage = Stage("gaussians", torch_device=True, for_rendered_views=True, gaussians=GaussiansOptions)


@stage.main
def main(cfg, paths, out):
    from usvc.gaussians.run import Inputs, run  # torch: loaded only where the model is fitted

    return run(Inputs(tracks=paths.tracks_file, scene=paths.scene_file), out, stage.options(cfg, "gaussians"),
               device=stage.device)


if __name__ == "__main__":
    main()
