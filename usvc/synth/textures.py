"""Procedural surface textures: corner-rich, never periodic over a whole face, distinct per face.

Each face draws its shapes from its own seeded generator, so no two surfaces (and no two
seeds) share a pattern that SIFT could confuse. Shapes span 2 cm to tens of cm so they stay
visible at the 0.5-4 m viewing distances of the room.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np

from usvc.errors import UsvcError
from usvc.synth.params import RoomParams
from usvc.synth.room import Layout, face_normal, shading

_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)
_CHARS = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#&%@"
_SHAPES = ("rect", "checker", "stripes", "ellipse", "text", "poster", "lines", "dots")
_SHAPE_WEIGHTS = np.array([0.2, 0.09, 0.09, 0.17, 0.2, 0.06, 0.12, 0.07])


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def scene_palette(seed: int) -> dict[str, np.ndarray]:
    """Per-scene colours: muted walls, a darker floor, and 16 accent colours in [0, 1]."""
    rng = np.random.default_rng([seed, 202])
    accents = np.array([_hsv(rng.random(), rng.uniform(0.2, 0.95), rng.uniform(0.2, 0.95)) for _ in range(16)])
    return {
        "wall": _hsv(rng.random(), rng.uniform(0.05, 0.35), rng.uniform(0.55, 0.85)),
        "floor": _hsv(rng.random(), rng.uniform(0.1, 0.5), rng.uniform(0.3, 0.6)),
        "ceiling": _hsv(rng.random(), rng.uniform(0.0, 0.1), rng.uniform(0.75, 0.9)),
        "accents": accents,
        "tile": np.array([rng.uniform(0.25, 0.55), rng.uniform(0.45, 0.8)]),  # floor, ceiling tile size (m)
    }


def _colour(rng: np.random.Generator, accents: np.ndarray) -> tuple[int, int, int]:
    """An accent colour with jitter, or now and then a fully random one, as 8-bit RGB."""
    c = rng.random(3) if rng.random() < 0.3 else accents[rng.integers(len(accents))] * rng.uniform(0.7, 1.15)
    r, g, b = (np.clip(c, 0.0, 1.0) * 255).astype(int)
    return int(r), int(g), int(b)


def _smooth_field(rng: np.random.Generator, h: int, w: int, cell_px: float, channels: int) -> np.ndarray:
    """Band-limited noise in roughly [-1, 1]: a coarse random grid, cubic-upsampled."""
    gh, gw = max(2, int(h / cell_px) + 2), max(2, int(w / cell_px) + 2)
    grid = rng.standard_normal((gh, gw, channels)).astype(np.float32)
    field = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
    return field.reshape(h, w, channels)


def _tiles(canvas: np.ndarray, rng: np.random.Generator, tile_px: float, grout: tuple[int, int, int]) -> None:
    """A tile grid with a per-tile shade and random offset, so no two tiles look the same."""
    h, w = canvas.shape[:2]
    ox, oy = rng.uniform(0, tile_px, 2)
    ty = ((np.arange(h) + oy) // tile_px).astype(int)
    tx = ((np.arange(w) + ox) // tile_px).astype(int)
    shade = rng.normal(1.0, 0.09, (ty.max() + 1, tx.max() + 1, 3)).astype(np.float32)
    canvas[:] = np.clip(canvas * shade[ty][:, tx], 0, 255).astype(np.uint8)
    width = max(1.0, tile_px / 40)
    canvas[((np.arange(h) + oy) % tile_px) < width] = grout
    canvas[:, ((np.arange(w) + ox) % tile_px) < width] = grout


def _shape(canvas: np.ndarray, rng: np.random.Generator, size: float, region: tuple[int, int, int, int],
           accents: np.ndarray, depth: int = 0) -> None:
    """Draw one random shape of about ``size`` px centred inside ``region`` (x0, y0, x1, y1)."""
    x0, y0, x1, y1 = region
    kind = _SHAPES[rng.choice(len(_SHAPES), p=_SHAPE_WEIGHTS / _SHAPE_WEIGHTS.sum())]
    aspect = float(np.exp(rng.uniform(-0.7, 0.7)))
    sw, sh = max(3.0, size * aspect), max(3.0, size / aspect)
    cx, cy = rng.uniform(x0, x1), rng.uniform(y0, y1)
    xa, ya = int(np.clip(cx - sw / 2, 0, canvas.shape[1] - 1)), int(np.clip(cy - sh / 2, 0, canvas.shape[0] - 1))
    xb, yb = int(np.clip(cx + sw / 2, xa + 1, canvas.shape[1])), int(np.clip(cy + sh / 2, ya + 1, canvas.shape[0]))
    colour = _colour(rng, accents)
    if kind == "rect":
        cv2.rectangle(canvas, (xa, ya), (xb - 1, yb - 1), colour, -1 if rng.random() < 0.7 else max(1, int(size / 15)))
    elif kind in ("checker", "stripes"):
        yy, xx = np.mgrid[0:yb - ya, 0:xb - xa]
        period = rng.uniform(max(3.0, size / 10), max(4.0, size / 3))
        if kind == "checker":
            mask = ((yy // period + xx // period) % 2).astype(bool)
        else:
            angle = rng.uniform(0, np.pi)
            mask = (((xx * np.cos(angle) + yy * np.sin(angle)) // period) % 2).astype(bool)
        canvas[ya:yb, xa:xb] = np.where(mask[..., None], colour, _colour(rng, accents)).astype(np.uint8)
    elif kind == "ellipse":
        axes = (max(1, int(sw / 2)), max(1, int(sh / 2)))
        cv2.ellipse(canvas, (int(cx), int(cy)), axes, rng.uniform(0, 180), 0, 360, colour, -1, cv2.LINE_AA)
    elif kind == "text":
        text = "".join(rng.choice(list(_CHARS), rng.integers(2, 8)))
        font = _FONTS[rng.integers(len(_FONTS))]
        (tw, th), _ = cv2.getTextSize(text, font, 1.0, 1)
        scale = max(0.25, sh / max(th, 1))
        thickness = max(1, int(round(scale * rng.uniform(0.8, 2.5))))
        cv2.putText(canvas, text, (xa, yb), font, scale, colour, thickness, cv2.LINE_AA)
    elif kind == "poster" and depth == 0 and min(sw, sh) > 24:
        cv2.rectangle(canvas, (xa, ya), (xb - 1, yb - 1), _colour(rng, accents), -1)
        cv2.rectangle(canvas, (xa, ya), (xb - 1, yb - 1), colour, max(2, int(min(sw, sh) / 25)))
        inner = (xa + sw * 0.15, ya + sh * 0.15, xb - sw * 0.15, yb - sh * 0.15)
        for sub in sorted(rng.uniform(0.1, 0.45, rng.integers(3, 8)) * min(sw, sh), reverse=True):
            _shape(canvas, rng, float(sub), tuple(int(v) for v in inner), accents, depth + 1)
    elif kind == "lines":
        pts = np.column_stack([rng.uniform(xa, xb, 5), rng.uniform(ya, yb, 5)]).astype(np.int32)
        cv2.polylines(canvas, [pts[: rng.integers(2, 6)]], False, colour, max(1, int(size / 20)), cv2.LINE_AA)
    else:  # dots, or a poster too small to frame
        for _ in range(int(rng.integers(3, 9))):
            centre = (int(rng.uniform(xa, xb)), int(rng.uniform(ya, yb)))
            cv2.circle(canvas, centre, max(1, int(size * rng.uniform(0.05, 0.2))), colour, -1, cv2.LINE_AA)


def surface_texture(seed: int, face: int, kind: str, width: int, height: int, res: float,
                    palette: dict[str, np.ndarray], density: float, noise: float) -> np.ndarray:
    """Albedo image (height, width, 3) float32 in [0, 1] for one face of ``kind``.

    ``kind`` is "floor", "ceiling", "wall" or "object"; ``res`` is texels per metre and
    ``density`` painted shapes per square metre.
    """
    rng = np.random.default_rng([seed, face, 303])
    accents = palette["accents"]
    if kind == "object":
        base = accents[rng.integers(len(accents))] * rng.uniform(0.8, 1.1)
    else:
        base = palette[kind] * rng.uniform(0.92, 1.05)
    base_field = 1.0 + 0.12 * _smooth_field(rng, height, width, 0.3 * res, 3)
    canvas = np.clip(base * base_field * 255, 0, 255).astype(np.uint8)
    if kind in ("floor", "ceiling"):
        tile = palette["tile"][0 if kind == "floor" else 1] * res
        _tiles(canvas, rng, tile, tuple(int(v) for v in (base * 0.45 * 255)))
    area = width * height / res**2
    scale = {"floor": 0.6, "ceiling": 0.35, "wall": 1.0, "object": 1.8}[kind]
    max_size = min(0.6, 0.7 * min(width, height) / res)
    n = int(np.ceil(density * scale * area))
    sizes = np.exp(rng.uniform(np.log(0.02), np.log(max(max_size, 0.03)), n)) * res
    for size in np.sort(sizes)[::-1]:  # large shapes first so small ones stay visible on top
        _shape(canvas, rng, float(size), (0, 0, width, height), accents)
    albedo = canvas.astype(np.float32) / 255.0
    albedo *= 1.0 + 2.0 * noise * _smooth_field(rng, height, width, 0.04 * res, 1)
    albedo += noise * rng.standard_normal((height, width, 1)).astype(np.float32)
    return np.clip(albedo, 0.02, 1.0)


_TANGENTS = {0: (1, 2), 1: (0, 2), 2: (0, 1)}  # face normal axis -> (u axis, v axis)
_ATLAS_WIDTH = 2048


@dataclass(frozen=True)
class Atlas:
    """All lit face textures packed in one image, plus per-face arrays to map points to texels.

    Lambertian shading does not depend on the viewpoint, so it is baked in once per texel and
    a frame is a single bilinear ``cv2.remap`` of this image.
    """

    image: np.ndarray  # (H, W, 3) float32, 8-bit scale
    ua: np.ndarray  # per face: world axis along texture columns
    va: np.ndarray  # per face: world axis along texture rows
    u0: np.ndarray  # per face: world coordinate of column 0's edge
    v0: np.ndarray  # per face: world coordinate of row 0's edge
    su: np.ndarray  # per face: columns per metre
    sv: np.ndarray  # per face: rows per metre (negative: rows run down the z axis)
    last_col: np.ndarray
    last_row: np.ndarray
    ox: np.ndarray  # per face: atlas column offset
    oy: np.ndarray  # per face: atlas row offset

    def lookup(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Atlas (column, row) of surface points (3, N) on faces (N,), pixel centres at integers."""
        pu = np.take_along_axis(points, self.ua[face][None], axis=0)[0]
        pv = np.take_along_axis(points, self.va[face][None], axis=0)[0]
        col = np.clip((pu - self.u0[face]) * self.su[face] - 0.5, 0.0, self.last_col[face]) + self.ox[face]
        row = np.clip((pv - self.v0[face]) * self.sv[face] - 0.5, 0.0, self.last_row[face]) + self.oy[face]
        return col.astype(np.float32), row.astype(np.float32)


def _face_kind(face: int) -> str:
    if face >= 6:
        return "object"
    return {4: "floor", 5: "ceiling"}.get(face, "wall")


def _pack(sizes: list[tuple[int, int]]) -> tuple[list[tuple[int, int]], int]:
    """Shelf packing of (w, h) rectangles, tallest first: offsets (x, y) and the total height."""
    offsets: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf = 0
    for i in sorted(range(len(sizes)), key=lambda k: (-sizes[k][1], k)):
        w, h = sizes[i]
        if x + w > _ATLAS_WIDTH:
            x, y, shelf = 0, y + shelf, 0
        offsets[i] = (x, y)
        x, shelf = x + w, max(shelf, h)
    return offsets, y + shelf


def build_atlas(layout: Layout, params: RoomParams) -> Atlas:
    """Texture, light and pack every face of the layout (room faces 0-5, then object faces)."""
    palette = scene_palette(params.seed)
    res = params.texture_resolution
    n_faces = 6 * layout.n_boxes
    rows: dict[str, list[float]] = {k: [] for k in ("ua", "va", "u0", "v0", "su", "sv", "last_col", "last_row")}
    images = []
    for face in range(n_faces):
        box, axis, side = face // 6, (face % 6) // 2, face % 2
        lo, hi = layout.lo[box], layout.hi[box]
        ua, va = _TANGENTS[axis]
        width = max(2, int(np.ceil((hi[ua] - lo[ua]) * res)))
        height = max(2, int(np.ceil((hi[va] - lo[va]) * res)))
        su = width / (hi[ua] - lo[ua])
        flip = va == 2  # vertical faces: row 0 at the top, like a picture on the wall
        sv = -height / (hi[va] - lo[va]) if flip else height / (hi[va] - lo[va])
        v0 = hi[va] if flip else lo[va]
        albedo = surface_texture(params.seed, face, _face_kind(face), width, height, res, palette,
                                 params.patch_density, params.texture_noise)
        cols, rws = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        points = np.empty((3, height * width))
        points[axis] = hi[axis] if side else lo[axis]
        points[ua] = lo[ua] + cols.ravel() / su
        points[va] = v0 + rws.ravel() / sv
        light = shading(points, face_normal(face), layout, params).reshape(height, width, 1)
        images.append(albedo * light * 255.0)
        for key, value in zip(rows, (ua, va, lo[ua], v0, su, sv, width - 1, height - 1)):
            rows[key].append(value)
    offsets, atlas_h = _pack([(im.shape[1], im.shape[0]) for im in images])
    if atlas_h >= 32767:
        raise UsvcError(f"texture atlas of {atlas_h} rows exceeds cv2.remap's limit; lower texture_resolution")
    atlas = np.zeros((atlas_h, _ATLAS_WIDTH, 3), dtype=np.float32)
    for (x, y), im in zip(offsets, images):
        atlas[y:y + im.shape[0], x:x + im.shape[1]] = im
    arrays = {k: np.array(v, dtype=np.int64 if k in ("ua", "va") else np.float64) for k, v in rows.items()}
    return Atlas(image=atlas, ox=np.array([o[0] for o in offsets], dtype=np.float64),
                 oy=np.array([o[1] for o in offsets], dtype=np.float64), **arrays)
