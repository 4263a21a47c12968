"""A differentiable Gaussian rasteriser in plain PyTorch (CPU and CUDA alike).

Follows the 3DGS forward model: EWA projection of each 3D covariance through the local affine
approximation of the pinhole projection (plus a 0.3 px^2 low-pass), then front-to-back alpha
compositing of the depth-sorted Gaussians at each pixel. Memory stays bounded by working in
screen tiles: each Gaussian is binned into the tiles its 3-sigma box touches, tiles are grouped
into chunks of similar length, and a chunk is one dense (tiles, pixels, Gaussians) block, so
autograd gives the backward pass. Pixel centres are at (j + 0.5, i + 0.5), the convention of
the scenes' intrinsics (COLMAP).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from usvc.splat.gaussians import Gaussians, covariances
from usvc.splat.gsplat_backend import gsplat_available, render_gsplat
from usvc.splat.sh import eval_sh, num_coeffs
from usvc.splat.view import RenderOutput, View

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99


@dataclass
class Projected:
    means2d: torch.Tensor  # (N, 2) px
    depths: torch.Tensor  # (N,) camera z
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c)
    radii: torch.Tensor  # (N,) px, 0 where culled
    colors: torch.Tensor  # (N, 3)
    opacities: torch.Tensor  # (N,)


def project(g: Gaussians, view: View, sh_degree: int | None = None, eps2d: float = 0.3,
            near: float = 0.01) -> Projected:
    """Screen-space Gaussians for `view`; culled ones (behind, degenerate, off-screen) get radius 0."""
    R, t, K = view.R, view.t, view.K
    p = g.means @ R.T + t
    z = p[:, 2]
    zc = z.clamp(min=near)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # Clamp the Jacobian's evaluation point as the reference does: far off-screen Gaussians would
    # otherwise get huge, meaningless footprints.
    limx, limy = 1.3 * 0.5 * view.width / fx, 1.3 * 0.5 * view.height / fy
    tx = (p[:, 0] / zc).clamp(-limx, limx) * zc
    ty = (p[:, 1] / zc).clamp(-limy, limy) * zc
    zero = torch.zeros_like(zc)
    J = torch.stack([fx / zc, zero, -fx * tx / zc**2, zero, fy / zc, -fy * ty / zc**2], -1).reshape(-1, 2, 3)
    T = J @ R
    cov = T @ covariances(g) @ T.transpose(1, 2)
    a = cov[:, 0, 0] + eps2d
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = (z > near) & (det > 1e-12)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1)
    means2d = torch.stack([fx * p[:, 0] / zc + cx, fy * p[:, 1] / zc + cy], -1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det).clamp(min=0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam))
        on_screen = ((means2d[:, 0] + radii > 0) & (means2d[:, 0] - radii < view.width)
                     & (means2d[:, 1] + radii > 0) & (means2d[:, 1] - radii < view.height))
        radii = torch.where(ok & on_screen, radii, torch.zeros_like(radii))
    degree = g.sh_degree if sh_degree is None else min(sh_degree, g.sh_degree)
    centre = -R.T @ t
    dirs = torch.nn.functional.normalize(g.means.detach() - centre, dim=-1)
    colors = eval_sh(degree, g.sh[:, : num_coeffs(degree)], dirs)
    return Projected(means2d, z, conics, radii, colors, g.opacities)


def bin_tiles(proj: Projected, width: int, height: int, tile: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """Sorted (tile, depth) list of Gaussian ids, with per-tile start and count."""
    dev = proj.means2d.device
    tw, th = math.ceil(width / tile), math.ceil(height / tile)
    with torch.no_grad():
        vis = torch.nonzero(proj.radii > 0).squeeze(1)
        m, r = proj.means2d[vis], proj.radii[vis]
        x0 = torch.floor((m[:, 0] - r) / tile).clamp(0, tw - 1).long()
        x1 = torch.floor((m[:, 0] + r) / tile).clamp(0, tw - 1).long()
        y0 = torch.floor((m[:, 1] - r) / tile).clamp(0, th - 1).long()
        y1 = torch.floor((m[:, 1] + r) / tile).clamp(0, th - 1).long()
        nx, ny = x1 - x0 + 1, y1 - y0 + 1
        cnt = nx * ny
        rep = torch.repeat_interleave(torch.arange(len(vis), device=dev), cnt)
        local = torch.arange(int(cnt.sum()), device=dev) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
        tile_id = (y0[rep] + local // nx[rep]) * tw + x0[rep] + local % nx[rep]
        n = len(proj.depths)
        rank = torch.empty(n, dtype=torch.long, device=dev)
        rank[torch.argsort(proj.depths.detach())] = torch.arange(n, device=dev)
        gid = vis[rep]
        order = torch.argsort(tile_id * n + rank[gid])
        gid = gid[order]
        counts = torch.bincount(tile_id, minlength=tw * th)
        starts = torch.cumsum(counts, 0) - counts
    return gid, starts, counts, tw


def _chunks(counts: torch.Tensor, pixels_per_tile: int, budget: int) -> list[tuple[torch.Tensor, int]]:
    """Non-empty tiles, longest list first, grouped so that tiles x pixels x longest list stays
    under `budget` elements (padding is small because neighbours in this order have similar lists)."""
    order = torch.argsort(counts, descending=True)
    c = counts[order].tolist()
    nonempty = sum(1 for x in c if x > 0)
    out, i = [], 0
    while i < nonempty:
        j = min(nonempty, i + max(1, budget // (pixels_per_tile * c[i])))
        out.append((order[i:j], c[i]))
        i = j
    return out


def _alphas(phi: torch.Tensor, q: torch.Tensor, op: torch.Tensor):
    """(raw opacity op * exp(power), alpha, transmittance before each Gaussian), all (T, P, k).
    In-place where possible: these blocks are the rasteriser's whole memory traffic."""
    raw = torch.matmul(phi, q).clamp_(max=0.0).exp_().mul_(op[:, None, :])  # power <= 0 for a PD conic
    alpha = raw.clamp(max=ALPHA_MAX).mul_(raw >= ALPHA_MIN)
    log_keep = torch.log1p(-alpha)
    trans = torch.cumsum(log_keep, dim=-1).sub_(log_keep).exp_()
    return raw, alpha, trans


def quadratic_form(local_means: torch.Tensor, conics: torch.Tensor) -> torch.Tensor:
    """Coefficients (T, 6, k) of the Gaussian exponent as a polynomial in tile-local pixel
    coordinates, power = [u^2, uv, v^2, u, v, 1] . q, so one matmul evaluates every pixel against
    every Gaussian of a tile. Local coordinates keep the terms small, so float32 cancels safely."""
    mx, my = local_means.unbind(-1)
    a, b, c = conics.unbind(-1)
    return torch.stack([-0.5 * a, -b, -0.5 * c, a * mx + b * my, c * my + b * mx,
                        -0.5 * a * mx * mx - b * mx * my - 0.5 * c * my * my], dim=1)


def pixel_basis(tile: int, device: torch.device | str) -> torch.Tensor:
    """(P, 6) monomials [u^2, uv, v^2, u, v, 1] of the pixel centres of one tile, row-major."""
    off = torch.arange(tile * tile, device=device)
    u, v = (off % tile).float() + 0.5, (off // tile).float() + 0.5
    return torch.stack([u * u, u * v, v * v, u, v, torch.ones_like(u)], -1)


class GatherRows(torch.autograd.Function):
    """src[index] with a deterministic backward: autograd's scatter-add for advanced indexing runs
    in parallel on CPU and sums in thread order, so the same fit gave different bits run to run;
    index_add_ adds the rows in index order."""

    @staticmethod
    def forward(ctx, src, index):
        ctx.save_for_backward(index)
        ctx.rows = src.shape[0]
        return src[index]

    @staticmethod
    def backward(ctx, grad):
        (index,) = ctx.saved_tensors
        out = torch.zeros((ctx.rows,) + grad.shape[index.dim():], dtype=grad.dtype, device=grad.device)
        return out.index_add_(0, index.reshape(-1), grad.reshape((-1,) + grad.shape[index.dim():])), None


class BlendTiles(torch.autograd.Function):
    """Alpha blending of one chunk of tiles, out[t, p] = sum_k alpha_k T_k f_k, with a hand-written
    backward that recomputes the (tiles, pixels, Gaussians) block instead of storing a dozen of
    them: less memory than autograd's graph, and fewer passes over the block.

    Shapes: phi (P, 6) pixel monomials; q (T, 6, k) exponent coefficients, op (T, k) opacities and
    f (T, k, C) features of each tile's depth-sorted Gaussians (padding columns have opacity 0)."""

    @staticmethod
    def forward(ctx, phi, q, op, f):
        _, alpha, trans = _alphas(phi, q, op)
        ctx.save_for_backward(phi, q, op, f)
        return torch.bmm(alpha.mul_(trans), f)

    @staticmethod
    def backward(ctx, grad_out):
        phi, q, op, f = ctx.saved_tensors
        raw, alpha, trans = _alphas(phi, q, op)
        w = alpha * trans
        grad_f = torch.bmm(w.transpose(1, 2), grad_out)
        G = torch.bmm(grad_out, f.transpose(1, 2))  # dL/d(w_k) per (pixel, Gaussian)
        behind = w.mul_(G)  # w is not needed any more
        behind = behind.sum(-1, keepdim=True) - torch.cumsum(behind, dim=-1)  # through later Gaussians' T
        # dL/d alpha_k = T_k G_k - sum_{j>k} w_j G_j / (1 - alpha_k); zero where alpha was clamped or culled.
        d_alpha = trans.mul_(G).sub_(behind.div_(1.0 - alpha))
        d_alpha.mul_((raw >= ALPHA_MIN) & (raw < ALPHA_MAX))
        d_pow = d_alpha.mul_(raw)  # d alpha / d power = raw
        grad_op = d_pow.sum(1) / op.clamp(min=1e-12)  # d alpha / d op = exp(power) = raw / op
        grad_q = phi.T @ d_pow
        return None, grad_q, grad_op, grad_f


def composite(proj: Projected, features: torch.Tensor, width: int, height: int, tile: int = 16,
              budget: int = 1 << 18) -> torch.Tensor:
    """Front-to-back alpha compositing of per-Gaussian `features` (N, C); returns (H, W, C + 1)
    with accumulated alpha as the last channel."""
    dev = features.device
    gid_sorted, starts, counts, tw = bin_tiles(proj, width, height, tile)
    n, ch = features.shape
    # One packed row per Gaussian (plus a transparent padding row n): one gather per chunk, and one
    # scatter-add in its backward, instead of one per attribute.
    packed = torch.cat([proj.means2d, proj.conics, proj.opacities[:, None], features,
                        torch.ones_like(features[:, :1])], 1)
    packed = torch.cat([packed, torch.zeros_like(packed[:1])], 0)
    ppt = tile * tile
    phi = pixel_basis(tile, dev).to(features.dtype)
    th = math.ceil(height / tile)
    done_tiles, done_blocks = [], []
    for tids, k in _chunks(counts, ppt, budget):
        ks = torch.arange(k, device=dev)
        valid = ks[None] < counts[tids][:, None]
        rows = (starts[tids][:, None] + ks[None]).clamp(max=max(len(gid_sorted) - 1, 0))
        gid = torch.where(valid, gid_sorted[rows], torch.full_like(rows, n))  # (T, k); n = padding
        origin = torch.stack([(tids % tw) * tile, (tids // tw) * tile], -1).to(packed.dtype)  # (T, 2)
        rows_g = GatherRows.apply(packed, gid)  # (T, k, 6 + C + 1)
        q = quadratic_form(rows_g[..., 0:2] - origin[:, None, :], rows_g[..., 2:5])
        done_blocks.append(BlendTiles.apply(phi, q, rows_g[..., 5], rows_g[..., 6:]))
        done_tiles.append(tids)
    tiles = torch.zeros(th * tw, ppt, ch + 1, dtype=features.dtype, device=dev)
    if done_tiles:
        tiles = tiles.index_copy(0, torch.cat(done_tiles), torch.cat(done_blocks))
    image = tiles.reshape(th, tw, tile, tile, ch + 1).permute(0, 2, 1, 3, 4).reshape(th * tile, tw * tile, ch + 1)
    return image[:height, :width]


BACKENDS = ("auto", "torch", "gsplat")


def render(g: Gaussians, view: View, sh_degree: int | None = None, background: tuple[float, float, float] = (0.0, 0.0, 0.0),
           tile: int = 16, budget: int = 1 << 18, backend: str = "auto") -> RenderOutput:
    """RGB, expected depth and alpha of `g` seen from `view` (differentiable in every parameter).

    backend "auto" uses gsplat's CUDA kernels when the Gaussians are on a GPU and gsplat is
    installed, this module's PyTorch rasteriser otherwise."""
    if backend not in BACKENDS:
        raise ValueError(f"render backend must be one of {BACKENDS}, got {backend!r}")
    if backend != "torch":

        if backend == "gsplat" or gsplat_available(g.means.device):
            return render_gsplat(g, view, sh_degree, background)
    proj = project(g, view, sh_degree)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    feats = torch.cat([proj.colors, proj.depths[:, None]], 1)
    out = composite(proj, feats, view.width, view.height, tile, budget)
    alpha = out[..., 4]
    bg = torch.tensor(background, dtype=out.dtype, device=out.device)
    rgb = out[..., :3] + (1.0 - alpha)[..., None] * bg
    depth = out[..., 3] / alpha.clamp(min=1e-6)
    depth = torch.where(alpha > 1e-6, depth, torch.zeros_like(depth))
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, means2d=proj.means2d, radii=proj.radii)
