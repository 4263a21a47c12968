"""The PyTorch Gaussian rasteriser: projection, tiled compositing against a dense reference,
gradients, densification bookkeeping, a small fit, PLY reload and novel-view geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from usvc.gaussians.densify import (
    DensityStats,
    densify_and_prune,
    reset_opacity,
)
from usvc.gaussians.fit import FitImage, fit_gaussians, psnr
from usvc.gaussians.options import GaussiansOptions
from usvc.render.novel_views import orbit_pose, visible_keypoints
from usvc.render.novel_views import project as project_np
from usvc.splat.gaussians import PARAM_NAMES, Gaussians, covariances, from_points
from usvc.splat.ply_file import read_splat_ply, write_splat_ply
from usvc.splat.rasterize import (
    ALPHA_MAX,
    ALPHA_MIN,
    BlendTiles,
    View,
    pixel_basis,
    project,
    quadratic_form,
    render,
)
from usvc.splat.sh import C0, rgb_to_dc


def _view(w: int = 48, h: int = 32, f: float = 40.0) -> View:
    return View(torch.eye(3), torch.zeros(3), torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]]), w, h)


def _scene(n: int = 60, seed: int = 0, degree: int = 1) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 2.0, 2 + 2 * torch.rand(n, 1, generator=g)], 1)
    return Gaussians(means=means, log_scales=torch.log(0.03 + 0.1 * torch.rand(n, 3, generator=g)),
                     quats=torch.randn(n, 4, generator=g), opacity_logits=torch.randn(n, generator=g),
                     sh_dc=torch.randn(n, 3, generator=g) * 0.5,
                     sh_rest=torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g) * 0.1)


def _dense_reference(g: Gaussians, view: View) -> tuple[torch.Tensor, torch.Tensor]:
    """Every pixel against every Gaussian, depth-sorted: the definition the tiles must match."""
    p = project(g, view)
    order = torch.argsort(p.depths)
    keep = order[p.radii[order] > 0]
    ys, xs = torch.meshgrid(torch.arange(view.height) + 0.5, torch.arange(view.width) + 0.5, indexing="ij")
    dx = xs.reshape(-1, 1) - p.means2d[keep, 0]
    dy = ys.reshape(-1, 1) - p.means2d[keep, 1]
    a, b, c = p.conics[keep].unbind(-1)
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = (p.opacities[keep] * torch.exp(power)).clamp(max=ALPHA_MAX)
    # The rasteriser bins each Gaussian into the tiles of its 3-sigma box; outside it contributes 0.
    inside = (dx.abs() <= p.radii[keep] + 8) & (dy.abs() <= p.radii[keep] + 8)
    alpha = torch.where((alpha >= ALPHA_MIN) & inside, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    w = alpha * trans
    rgb = (w @ p.colors[keep]).reshape(view.height, view.width, 3)
    return rgb, w.sum(1).reshape(view.height, view.width)


def test_projection_of_an_isotropic_gaussian():
    g = Gaussians(means=torch.tensor([[0.5, -0.25, 2.0]]), log_scales=torch.log(torch.full((1, 3), 0.05)),
                  quats=torch.tensor([[1.0, 0, 0, 0]]), opacity_logits=torch.zeros(1), sh_dc=torch.zeros(1, 3),
                  sh_rest=torch.zeros(1, 0, 3))
    view = _view()
    p = project(g, view)
    assert torch.allclose(p.means2d[0], torch.tensor([40 * 0.25 + 24, 40 * -0.125 + 16]))
    sigma2 = (40 * 0.05 / 2.0) ** 2  # centre of the image region: J ~ f / z, plus the 0.3 px^2 low-pass
    a, b, c = p.conics[0]
    cov = torch.linalg.inv(torch.tensor([[a, b], [b, c]]))
    # Off-axis the Jacobian's z-column adds anisotropy; on the diagonal the x term dominates.
    assert abs(float(cov[1, 1]) - (sigma2 + 0.3)) / (sigma2 + 0.3) < 0.05
    assert p.radii[0] == math.ceil(3 * math.sqrt(float(torch.linalg.eigvalsh(cov).max())))


def test_covariance_is_rotation_times_scales():
    g = _scene(5)
    cov = covariances(g)
    eig = torch.linalg.eigvalsh(cov)
    assert torch.allclose(eig.sort(dim=1).values, (g.scales**2).sort(dim=1).values, rtol=1e-4)


@pytest.mark.parametrize("tile,budget", [(8, 1 << 12), (16, 1 << 22), (4, 1 << 10)])
def test_tiles_match_dense_reference(tile, budget):
    g, view = _scene(), _view()
    out = render(g, view, tile=tile, budget=budget)
    rgb, alpha = _dense_reference(g, view)
    assert torch.allclose(out.alpha, alpha, atol=2e-5)
    assert torch.allclose(out.rgb, rgb, atol=2e-5)


def test_front_gaussian_occludes():
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    g = Gaussians(means=means, log_scales=torch.log(torch.full((2, 3), 0.2)), quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
                  opacity_logits=torch.tensor([20.0, 20.0]), sh_dc=rgb_to_dc(torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])),
                  sh_rest=torch.zeros(2, 0, 3))
    out = render(g, _view())
    centre = out.rgb[16, 24]
    assert centre[0] > 0.98 and centre[1] < 0.02  # red in front; alpha is clamped at 0.99
    assert abs(float(out.depth[16, 24]) - 2.0) < 0.02
    assert float(out.alpha[0, 0]) < 1e-3 and float(out.depth[0, 0]) == 0.0


def test_blend_backward_matches_numerical_gradients():
    torch.manual_seed(0)
    phi = pixel_basis(4, "cpu").double()
    m = (torch.rand(2, 5, 2, dtype=torch.float64) * 4).requires_grad_()
    L = torch.randn(2, 5, 2, 2, dtype=torch.float64) * 0.5
    inv = torch.linalg.inv(L @ L.transpose(-1, -2) + torch.eye(2, dtype=torch.float64))
    con = torch.stack([inv[..., 0, 0], inv[..., 0, 1], inv[..., 1, 1]], -1).requires_grad_()
    op = (torch.rand(2, 5, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    f = torch.randn(2, 5, 3, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda m, con, op, f: BlendTiles.apply(phi, quadratic_form(m, con), op, f),
                                    (m, con, op, f))


def test_render_gradients_match_dense_autograd():
    g = _scene(30, seed=3)
    params = {k: v.clone().requires_grad_() for k, v in g.tensors().items()}
    view = _view()
    target = torch.rand(view.height, view.width, 3, generator=torch.Generator().manual_seed(1))
    ((render(Gaussians(**params), view).rgb - target) ** 2).sum().backward()
    ref = {k: v.clone().requires_grad_() for k, v in g.tensors().items()}
    ((_dense_reference(Gaussians(**ref), view)[0] - target) ** 2).sum().backward()
    for k in PARAM_NAMES:
        assert torch.allclose(params[k].grad, ref[k].grad, rtol=1e-3, atol=1e-4), k


def test_densify_clones_splits_prunes_and_keeps_adam_state_aligned():
    g = _scene(10)
    params = {k: torch.nn.Parameter(v.clone()) for k, v in g.tensors().items()}
    params["log_scales"].data[:5] = math.log(0.001)  # small: cloned
    params["log_scales"].data[5:] = math.log(0.5)  # large: split
    params["opacity_logits"].data[9] = -10.0  # transparent: pruned
    opt = torch.optim.Adam([{"params": [params[k]], "lr": 0.01, "name": k} for k in PARAM_NAMES])
    sum(v.sum() for v in params.values()).backward()
    opt.step()
    parent_scales = params["log_scales"].detach()[[5, 6]].clone()
    stats = DensityStats(10)
    grads = torch.zeros(10, 2)
    grads[[0, 1, 5, 6]] = 1.0  # only these are "hot"
    stats.add(grads, torch.ones(10), 2, 2)
    info = densify_and_prune(params, opt, stats, extent=1.0, opts=GaussiansOptions(densify_grad_threshold=0.5),
                             generator=torch.Generator().manual_seed(0), prune_large=False)
    assert info == {"cloned": 2, "split": 2, "pruned": 1, "total": 10 - 2 - 1 + 2 + 4}
    for group in opt.param_groups:
        p = group["params"][0]
        assert p is params[group["name"]] and p.shape[0] == info["total"]
        assert opt.state[p]["exp_avg"].shape == p.shape
    children = params["log_scales"][-4:]
    assert torch.allclose(children, (parent_scales - math.log(1.6)).repeat(2, 1))
    reset_opacity(params, opt)
    assert float(torch.sigmoid(params["opacity_logits"].detach()).max()) <= 0.01 + 1e-6


def test_fit_recovers_a_small_scene():
    truth = _scene(40, seed=5, degree=0)
    truth.opacity_logits = torch.full((40,), 3.0)
    views = []
    for i in range(6):
        ang = (i - 2.5) * 0.05
        R = torch.tensor([[math.cos(ang), 0, math.sin(ang)], [0, 1.0, 0], [-math.sin(ang), 0, math.cos(ang)]])
        v = View(R, torch.tensor([0.1 * (i - 2.5), 0, 0]), _view().K, 48, 32)
        views.append(FitImage(f"v{i}", v, render(truth, v).rgb.detach().clamp(0, 1)))
    start = from_points(truth.means.numpy() + 0.02, np.full((40, 3), 128, np.uint8), sh_degree=0)
    before = np.mean([psnr(render(start, im.view).rgb, im.rgb) for im in views])
    res = fit_gaussians(start, views, GaussiansOptions(iterations=150, sh_degree=0, densify_from=1000, holdout_every=0,
                                                        opacity_reset_every=0, lr_means=1e-3))
    after = np.mean([psnr(render(res.gaussians, im.view).rgb, im.rgb) for im in views])
    assert after > before + 3, (before, after)
    assert res.metrics["iterations"] == 150 and res.metrics["gaussians"] == 40


def test_ply_reload_renders_the_same(tmp_path):
    g = _scene(50, degree=3)
    write_splat_ply(tmp_path / "s.ply", g)
    back = read_splat_ply(tmp_path / "s.ply")
    assert torch.equal(render(g, _view()).rgb, render(back, _view()).rgb)


def test_dc_colour_convention():
    assert torch.allclose(rgb_to_dc(torch.tensor([0.5])), torch.tensor([0.0]))
    assert abs(C0 - 0.5 / math.sqrt(math.pi)) < 1e-12


def test_orbit_keeps_the_centre_on_its_pixel_and_moves_the_camera():
    R, t = np.eye(3), np.array([0.0, 0.0, 0.0])
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    centre = np.array([[0.2, -0.1, 3.0]])
    rot = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    rot = np.eye(3) * np.cos(0.3) + (1 - np.cos(0.3)) * np.outer([0, 1, 0], [0, 1, 0]) + np.sin(0.3) * np.array(
        [[0, 0, 1], [0, 0, 0], [-1, 0, 0]])
    R2, t2 = orbit_pose(R, t, centre[0], rot, np.zeros(3))
    uv0, _ = project_np(centre, R, t, K)
    uv1, z1 = project_np(centre, R2, t2, K)
    assert np.allclose(uv0, uv1) and z1[0] > 0
    assert np.allclose(R2 @ R2.T, np.eye(3))
    assert np.linalg.norm(-R2.T @ t2) > 0.5  # the camera moved on the orbit


def test_visibility_uses_rendered_depth_and_alpha():
    K = np.array([[10.0, 0, 5], [0, 10, 5], [0, 0, 1]])
    depth = np.full((10, 10), 2.0, np.float32)
    alpha = np.ones((10, 10), np.float32)
    alpha[:, :2] = 0.0
    xyz = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [-0.8, 0.0, 2.0], [0.0, 0.0, -2.0], [5.0, 0, 2.0]])
    ids, uv = visible_keypoints(xyz, np.eye(3), np.zeros(3), K, depth, alpha, tol=0.05, min_alpha=0.5)
    # 0: on the surface; 1: behind it (occluded); 2: where nothing was rendered; 3: behind the camera; 4: outside.
    assert ids.tolist() == [0] and np.allclose(uv[0], [5, 5])


def _frames_and_keypoints(tmp_path):
    from usvc.core.scene import Camera, Frame
    from usvc.keypoints.keypoints_file import SceneKeypoints

    g = _scene(200, seed=7, degree=0)
    g.opacity_logits = torch.full((200,), 4.0)
    g.log_scales = torch.log(torch.full((200, 3), 0.12))
    cam = Camera("PINHOLE", 48, 32, (40.0, 40.0, 24.0, 16.0))
    frames = [Frame(name=f"f{i}.png", image_path=tmp_path / f"f{i}.png", camera=cam, split="train",
                    R=np.eye(3), t=np.array([0.05 * i, 0.0, 0.0])) for i in range(3)]
    xyz = g.means.numpy().astype(np.float64)
    by_image = {}
    for f in frames:
        uv, z = project_np(xyz, f.R, f.t, cam.K)
        ids = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 48) & (uv[:, 1] >= 0) & (uv[:, 1] < 32))
        by_image[f.name] = (ids, uv[ids])
    return g, frames, SceneKeypoints(xyz=xyz, by_image=by_image)


def test_novel_views_round_trip_through_the_render_artifact(tmp_path):
    from usvc.render.novel_views import render_novel_views
    from usvc.render.options import RenderOptions
    from usvc.render.views_file import read_rendered_views, write_rendered_views

    g, frames, kp = _frames_and_keypoints(tmp_path)
    opts = RenderOptions(views=4, max_angle_deg=10, cluster_radius_rel=0.5, min_cluster_keypoints=5,
                            min_visible_keypoints=3, min_alpha=0.3, depth_tolerance=0.2)
    views, stats = render_novel_views(g, frames, kp, opts)
    again, _ = render_novel_views(g, frames, kp, opts)
    assert [v.R.tolist() for v in views] == [v.R.tolist() for v in again]  # seeded
    assert stats["views"] == 4 and 0 < stats["mean_angle_deg"] <= 10 + 1e-6
    for v in views:
        uv, z = project_np(kp.xyz[v.keypoint_ids], v.R, v.t, v.K)
        assert np.allclose(uv, v.keypoint_uv, atol=1e-3) and (z > 0).all()
    write_rendered_views(tmp_path / "render" / "render.h5", views)
    rendered, obs = read_rendered_views(tmp_path / "render" / "render.h5")
    assert [f.name for f in rendered] == [f"render/{i:04d}.png" for i in range(4)]
    assert np.allclose(rendered[2].R, views[2].R) and np.allclose(rendered[2].camera.K, views[2].K)
    assert np.array_equal(obs["render/0001.png"][0], views[1].keypoint_ids)
    import cv2
    assert np.array_equal(cv2.imread(str(rendered[0].image_path))[..., ::-1], views[0].rgb)


def test_clear_errors_for_missing_inputs(tmp_path):
    from usvc.core.errors import UsvcError
    from usvc.core.scene import Camera, Frame
    from usvc.gaussians.fit import load_fit_images
    from usvc.render.novel_views import render_novel_views
    from usvc.render.options import RenderOptions
    from usvc.render.views_file import read_rendered_views

    with pytest.raises(UsvcError, match="run the render stage"):
        read_rendered_views(tmp_path / "nothing" / "render.h5")
    cam = Camera("OPENCV", 48, 32, (40.0, 40.0, 24.0, 16.0, 0.1, 0, 0, 0))
    with pytest.raises(UsvcError, match="undistorted pinhole"):
        load_fit_images([Frame("a.png", tmp_path / "a.png", cam, "train", np.eye(3), np.zeros(3))], 0)
    cam = Camera("PINHOLE", 48, 32, (40.0, 40.0, 24.0, 16.0))
    with pytest.raises(UsvcError, match="cannot read mapping image"):
        load_fit_images([Frame("a.png", tmp_path / "a.png", cam, "train", np.eye(3), np.zeros(3))], 0)
    g, frames, kp = _frames_and_keypoints(tmp_path)
    with pytest.raises(UsvcError, match="sees 10000 kept keypoints"):
        render_novel_views(g, frames, kp, RenderOptions(min_cluster_keypoints=10000))
    with pytest.raises(UsvcError, match="no novel view kept"):
        render_novel_views(g, frames, kp, RenderOptions(views=2, max_tries=2, cluster_radius_rel=0.5,
                                                           min_cluster_keypoints=5, min_visible_keypoints=10000))
    with pytest.raises(UsvcError, match="at least 4 3D points"):
        from_points(np.zeros((2, 3)), np.zeros((2, 3), np.uint8), 0)
