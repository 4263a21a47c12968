"""The optional gsplat backend against the PyTorch rasteriser. The comparisons need CUDA and the
gsplat package and are skipped elsewhere; the availability probe is checked everywhere."""

from __future__ import annotations

import math

import pytest
import torch

from usvc.splat.gaussians import Gaussians
from usvc.splat.gsplat_backend import gsplat_available, render_gsplat
from usvc.splat.rasterize import View, render

WIDTH, HEIGHT = 96, 64
BACKGROUND = (0.1, 0.2, 0.3)

needs_gsplat = pytest.mark.skipif(not (torch.cuda.is_available() and gsplat_available("cuda")),
                                  reason="needs a CUDA device and the gsplat package")


def _rot(axis: str, deg: float) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    if axis == "x":
        return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def make_scene(device: str, n: int = 300, sh_degree: int = 1, seed: int = 0) -> tuple[Gaussians, View]:
    """`n` anisotropic Gaussians 2-5 units in front of a rotated, translated 96x64 camera with a
    centred principal point; opacities 0.18-0.88, so no alpha reaches either backend's clamp."""
    gen = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=gen)  # noqa: E731
    f = 80.0
    K = torch.tensor([[f, 0.0, WIDTH / 2], [0.0, f, HEIGHT / 2], [0.0, 0.0, 1.0]])
    R = _rot("y", 12.0) @ _rot("x", -7.0)
    t = torch.tensor([0.3, -0.2, 0.5])
    z = 2.0 + 3.0 * u(n)
    x = (2 * u(n) - 1) * 0.95 * z * (WIDTH / 2) / f
    y = (2 * u(n) - 1) * 0.95 * z * (HEIGHT / 2) / f
    cam = torch.stack([x, y, z], 1)
    means = (cam - t) @ R  # world = R^T (cam - t), row-wise
    k = (sh_degree + 1) ** 2
    g = Gaussians(
        means=means,
        log_scales=math.log(0.03) + (math.log(0.15) - math.log(0.03)) * u(n, 3),
        quats=torch.randn(n, 4, generator=gen),  # unnormalised on purpose
        opacity_logits=-1.5 + 3.5 * u(n),
        sh_dc=0.6 * torch.randn(n, 3, generator=gen),
        sh_rest=0.1 * torch.randn(n, k - 1, 3, generator=gen),
    )
    return g.to(device), View(R, t, K, WIDTH, HEIGHT).to(device)


def weights(view: View, device: str, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(view.height, view.width, 4, generator=gen).to(device)


def _cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0))


def test_gsplat_unavailable_on_cpu():
    assert gsplat_available("cpu") is False
    assert gsplat_available(torch.device("cpu")) is False


@needs_gsplat
def test_forward_matches_torch_renderer():
    g, view = make_scene("cuda")
    with torch.no_grad():
        ours = render(g, view, background=BACKGROUND, backend="torch")
        theirs = render_gsplat(g, view, background=BACKGROUND)
    assert theirs.rgb.shape == (HEIGHT, WIDTH, 3) and theirs.depth.shape == (HEIGHT, WIDTH)
    assert theirs.alpha.shape == (HEIGHT, WIDTH)
    assert theirs.means2d.shape == (len(g), 2) and theirs.radii.shape == (len(g),)

    rgb_diff = (ours.rgb - theirs.rgb).abs()
    assert rgb_diff.mean() < 1e-2, float(rgb_diff.mean())
    assert rgb_diff.max() < 0.1, float(rgb_diff.max())
    alpha_diff = (ours.alpha - theirs.alpha).abs()
    assert alpha_diff.mean() < 1e-2, float(alpha_diff.mean())

    solid = (ours.alpha > 0.5) & (theirs.alpha > 0.5)
    assert solid.sum() > 0.2 * HEIGHT * WIDTH, int(solid.sum())  # the scene covers the view
    rel = ((ours.depth - theirs.depth).abs() / ours.depth)[solid]
    assert rel.median() < 1e-2, float(rel.median())

    # Same projection convention: visibility agrees and the 2D means coincide where both draw.
    vis = (ours.radii > 0) & (theirs.radii > 0)
    agree = ((ours.radii > 0) == (theirs.radii > 0)).float().mean()
    assert agree > 0.95, float(agree)
    assert torch.allclose(ours.means2d[vis], theirs.means2d[vis], atol=1e-2)


@needs_gsplat
def test_gradients_match_torch_renderer():
    g, view = make_scene("cuda")
    w = weights(view, "cuda")
    grads, means2d_grads = [], []
    torch_render = lambda *a, **k: render(*a, backend="torch", **k)  # noqa: E731
    for fn in (torch_render, render_gsplat):
        params = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = fn(Gaussians(**params), view, background=BACKGROUND)
        loss = (out.rgb * w[..., :3]).sum() + (out.alpha * w[..., 3]).sum()
        loss.backward()
        grads.append(params)
        assert out.means2d.grad is not None and out.means2d.grad.shape == (len(g), 2)
        means2d_grads.append(torch.where((out.radii > 0)[:, None], out.means2d.grad, 0.0))
    for name in ("means", "sh_dc"):
        cos = _cosine(grads[0][name].grad, grads[1][name].grad)
        assert cos > 0.95, (name, cos)
    # What densification reads: the screen-space gradient of the projected means.
    cos = _cosine(means2d_grads[0], means2d_grads[1])
    assert cos > 0.95, ("means2d", cos)


def test_auto_backend_is_torch_without_gsplat_on_cpu():
    from usvc.splat.gaussians import Gaussians as G
    from usvc.splat.rasterize import View as V

    g = G(means=torch.tensor([[0.0, 0.0, 2.0]] * 4) + torch.arange(4.0)[:, None] * 0.1,
          log_scales=torch.full((4, 3), -2.0), quats=torch.tensor([[1.0, 0, 0, 0]] * 4),
          opacity_logits=torch.zeros(4), sh_dc=torch.zeros(4, 3), sh_rest=torch.zeros(4, 0, 3))
    v = V(torch.eye(3), torch.zeros(3), torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]), 16, 16)
    assert torch.equal(render(g, v).rgb, render(g, v, backend="torch").rgb)
    with pytest.raises(ValueError, match="backend"):
        render(g, v, backend="fast")
