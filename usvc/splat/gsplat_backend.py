"""Optional CUDA backend: the same render as `usvc.splat.rasterize.render`, through gsplat's
fused kernels (gsplat >= 1.0, `gsplat.rasterization`). gsplat is imported lazily, so this module
imports everywhere; `gsplat_available` says whether the backend can be used on a device.

What is kept identical to the PyTorch rasteriser: world-to-camera view matrix, pinhole K with
pixel centres at (j + 0.5, i + 0.5) (gsplat's kernel samples there too), 0.3 px^2 low-pass
(eps2d), near plane 0.01, quaternions normalised inside (gsplat accepts unnormalised wxyz), the
reference SH basis with the +0.5 offset clamped at 0 and view directions from the camera centre,
alpha skipped below 1/255, background blended with the final transmittance, depth normalised by
alpha as ours is (0 where alpha is ~0).

Known remaining differences, and why they exist:

- gsplat ends a pixel once its transmittance would drop to 1e-4: its kernel loops over a pixel's
  Gaussians, and stopping early is the speed-up. Ours blends a whole tile block at once and has
  no loop to leave. What is dropped is below 1e-4 of the pixel's colour.
- Alpha clamp: the reference (and ours) caps a Gaussian's alpha at 0.99; most released gsplat
  kernels cap at 0.999, a different constant (current gsplat sources use 0.99 again, chosen so
  that two opaque Gaussians end a pixel). Only opacities above 0.99 are affected.
- Footprints: recent gsplat bounds each Gaussian by an opacity-aware per-axis box (up to 3.33
  sigma, less for faint Gaussians, and none below opacity 1/255), ours by 3 sigma of the major
  axis as the reference does. gsplat's bound exists to cut tile intersections (speed); the two
  evaluate slightly different pixels at a footprint's edge, `radii` differ in value, and a
  Gaussian too faint to ever be drawn counts as visible (radius > 0) in ours but not in gsplat.
- The Jacobian clamp for Gaussians far outside the view uses limits around the principal point
  in gsplat, around the image centre in ours: identical when the principal point is centred.
- Gradients: gsplat back-propagates through the SH view direction into the means (as the
  reference does); `rasterize.project` detaches that direction. So the mean gradients agree at
  SH degree 0 and differ by the (small) view-dependent colour term above it.
- `means2d` is what gsplat writes: only meaningful where `radii > 0` (ours is defined for every
  Gaussian), which is how the densification statistics read it anyway.
"""

from __future__ import annotations

import functools
import logging
import weakref

import torch

from usvc.core.errors import UsvcError
from usvc.splat.gaussians import Gaussians
from usvc.splat.view import RenderOutput, View

log = logging.getLogger(__name__)

NEAR_PLANE = 0.01  # same as rasterize.project
EPS2D = 0.3  # same low-pass as rasterize.project


@functools.lru_cache(maxsize=1)
def _gsplat_importable() -> bool:
    try:
        import gsplat  # noqa: F401  (optional dependency, imported only on demand)
    except Exception as exc:  # ImportError, or a broken install failing while it loads
        log.debug("gsplat is not usable: %s", exc)
        return False
    return hasattr(gsplat, "rasterization")


def gsplat_available(device: str | torch.device) -> bool:
    """True when `device` is a CUDA device that exists here and `gsplat` imports."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        return False
    if dev.type != "cuda" or not torch.cuda.is_available():
        return False
    return _gsplat_importable()


def _viewmat(view: View, like: torch.Tensor) -> torch.Tensor:
    """(4, 4) world-to-camera [R t; 0 1] in the dtype and device of `like`."""
    m = torch.eye(4, dtype=like.dtype, device=like.device)
    m[:3, :3] = view.R.to(like)
    m[:3, 3] = view.t.to(like)
    return m


def _tap_means2d(full: torch.Tensor, n: int) -> torch.Tensor:
    """(N, 2) view of gsplat's projected means (shape (1, N, 2), or (N, 2)) whose `.grad` is
    filled after backward, as `render`'s is. The view itself is not in the autograd graph
    (gsplat's rasteriser consumes `full`), so `retain_grad` alone would leave it empty: a hook on
    `full` copies (accumulating, like `retain_grad`) the camera's slice of its gradient. (A loss
    taken on the returned tensor itself would reach `.grad` twice; losses here are on images.)"""
    out = full.reshape(n, 2)
    if not full.requires_grad:
        return out
    out.retain_grad()  # marks it as wanting .grad: reading it later gives no non-leaf warning
    ref = weakref.ref(out)  # no cycle full -> hook -> out -> full keeping GPU memory alive

    def copy_grad(grad: torch.Tensor) -> None:
        target = ref()
        if target is None:
            return
        g = grad.detach().reshape(n, 2)
        target.grad = g.clone() if target.grad is None else target.grad + g

    full.register_hook(copy_grad)
    return out


def _per_gaussian_radii(radii: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """gsplat's radii for our one camera, (1, N) ints in older releases or (1, N, 2) per axis in
    newer ones, as (N,) floats like ours: the larger axis, so > 0 exactly where it was drawn."""
    r = radii[0]
    if r.dim() == 2:
        r = r.amax(dim=-1)
    return r.to(like.dtype)


def render_gsplat(g: Gaussians, view: View, sh_degree: int | None = None,
                  background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> RenderOutput:
    """RGB, expected depth and alpha of `g` seen from `view` via gsplat's CUDA rasteriser; same
    arguments and outputs as `usvc.splat.rasterize.render` (see the module docstring for what
    still differs). `g` and `view` must be on a CUDA device."""
    try:
        from gsplat import rasterization
    except ImportError as exc:
        raise UsvcError("the gsplat backend needs the 'gsplat' package (pip install gsplat)") from exc
    if g.means.device.type != "cuda":
        raise UsvcError(f"the gsplat backend renders on CUDA only; the Gaussians are on {g.means.device}")
    n = len(g)
    degree = g.sh_degree if sh_degree is None else min(sh_degree, g.sh_degree)
    means = g.means
    viewmats = _viewmat(view, means)[None]  # (C=1, 4, 4)
    Ks = view.K.to(means)[None]  # (1, 3, 3)
    backgrounds = torch.tensor([background], dtype=means.dtype, device=means.device)  # (1, 3)
    # "RGB+D" (accumulated depth) rather than "RGB+ED": we divide by alpha below with the same
    # clamp and zeroing as `render`, instead of gsplat's 1e-10 clamp that leaves faint pixels
    # with a depth.
    colors, alphas, meta = rasterization(
        means=means,
        quats=g.quats,  # unnormalised wxyz: gsplat normalises (with the gradient through it)
        scales=g.scales,
        opacities=g.opacities,
        colors=g.sh,  # (N, K, 3) SH coefficients; gsplat uses the first (degree + 1)^2
        viewmats=viewmats,
        Ks=Ks,
        width=int(view.width),
        height=int(view.height),
        near_plane=NEAR_PLANE,
        eps2d=EPS2D,
        sh_degree=degree,
        packed=False,  # keep per-Gaussian (C, N, ...) meta, not the packed visible-only list
        tile_size=16,
        backgrounds=backgrounds,
        render_mode="RGB+D",
        rasterize_mode="classic",
    )
    out = colors[0]  # (H, W, 4): rgb (background blended in), accumulated depth
    alpha = alphas[0, ..., 0]
    depth = out[..., 3] / alpha.clamp(min=1e-6)
    depth = torch.where(alpha > 1e-6, depth, torch.zeros_like(depth))
    return RenderOutput(rgb=out[..., :3], depth=depth, alpha=alpha,
                        means2d=_tap_means2d(meta["means2d"], n),
                        radii=_per_gaussian_radii(meta["radii"], means))
