"""Procedural surface textures, lit and packed into one atlas that frames are sampled from.

Textures are corner-rich, never periodic over a whole face, and distinct per face: each face
draws its shapes from its own seeded generator, so no two surfaces (and no two seeds) share a
pattern that SIFT could confuse. Shapes span 2 cm to tens of cm so they stay visible at the
0.5-4 m viewing distances of the room.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np

from usvc.core.errors import UsvcError
from usvc.generate.params import MAX_FACE_TEXELS, RoomParams
from usvc.generate.room import Layout, face_normal, shading

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
    accents = np.array([_hsv(rng.random(), rng.uniform(0.2, 0.95), rng.uniform(0.2, 0.95))
                        for _ in range(16)])
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
    h, w = canvas.shape[:2]
    xa, ya = int(np.clip(cx - sw / 2, 0, w - 1)), int(np.clip(cy - sh / 2, 0, h - 1))
    xb, yb = int(np.clip(cx + sw / 2, xa + 1, w)), int(np.clip(cy + sh / 2, ya + 1, h))
    colour = _colour(rng, accents)
    if kind == "rect":
        thickness = -1 if rng.random() < 0.7 else max(1, int(size / 15))  # filled, or an outline
        cv2.rectangle(canvas, (xa, ya), (xb - 1, yb - 1), colour, thickness)
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
    base_field = 1.0 + 0.1 * _smooth_field(rng, height, width, 0.3 * res, 1)  # uneven paint, not rainbow
    base_field = base_field + 0.03 * _smooth_field(rng, height, width, 0.3 * res, 3)
    canvas = np.clip(base * base_field * 255, 0, 255).astype(np.uint8)
    if kind in ("floor", "ceiling"):
        tile = palette["tile"][0 if kind == "floor" else 1] * res
        _tiles(canvas, rng, tile, tuple(int(v) for v in (base * 0.45 * 255)))
    area = width * height / res**2
    scale = {"floor": 0.6, "ceiling": 0.35, "wall": 1.0, "object": 2.5}[kind]
    max_size = min(0.45, 0.7 * min(width, height) / res)
    n = int(np.ceil(density * scale * area))
    sizes = np.exp(rng.uniform(np.log(0.02), np.log(max(max_size, 0.03)), n)) * res
    for size in np.sort(sizes)[::-1]:  # large shapes first so small ones stay visible on top
        _shape(canvas, rng, float(size), (0, 0, width, height), accents)
    albedo = canvas.astype(np.float32) / 255.0
    albedo *= 1.0 + 2.0 * noise * _smooth_field(rng, height, width, 0.04 * res, 1)
    albedo += noise * rng.standard_normal((height, width, 1)).astype(np.float32)
    return np.clip(albedo, 0.02, 1.0)


_TANGENTS = {0: (1, 2), 1: (0, 2), 2: (0, 1)}  # face normal axis -> (u axis, v axis)
_ATLAS_WIDTH = MAX_FACE_TEXELS
_LIGHT_STEP = 4  # texels between irradiance samples


@dataclass(frozen=True)
class Atlas:
    """All lit face textures packed in one image, plus per-face arrays to map points to texels.

    Lambertian shading does not depend on the viewpoint, so it is baked in once per texel and
    a frame is a single bilinear ``cv2.remap`` of this image.
    """

    image: np.ndarray  # (H, W, 3) float32, 8-bit scale
    ua: np.ndarray  # per face: world axis along texture columns
    va: np.ndarray  # per face: world axis along texture rows
    su: np.ndarray  # per face: columns per metre (negative: columns run down the u axis)
    sv: np.ndarray  # per face: rows per metre (negative: rows run down the z axis)
    u_shift: np.ndarray  # per face: u0 * su + 0.5 with u0 the u of column 0's edge, so col = u * su - u_shift
    v_shift: np.ndarray  # per face: v0 * sv + 0.5
    last_col: np.ndarray
    last_row: np.ndarray
    ox: np.ndarray  # per face: atlas column offset
    oy: np.ndarray  # per face: atlas row offset

    def lookup(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Atlas (column, row) float32 maps of surface points (3, ...) on faces (...).

        Atlas pixel centres are at integer coordinates (cv2.remap's convention); each face's
        coordinates are clamped to its own texels so bilinear lookups never bleed across faces.
        """
        u_is_y, v_is_y = self.ua[face] == 1, self.va[face] == 1  # u is x or y; v is y or z
        pu = np.where(u_is_y, points[1], points[0])
        pv = np.where(v_is_y, points[1], points[2])
        col = np.clip(pu * self.su[face] - self.u_shift[face], 0.0, self.last_col[face]) + self.ox[face]
        row = np.clip(pv * self.sv[face] - self.v_shift[face], 0.0, self.last_row[face]) + self.oy[face]
        return col, row


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


def _face_light(layout: Layout, params: RoomParams, face: int, u_edge: float, su: float, v_edge: float,
                sv: float, width: int, height: int) -> np.ndarray:
    """(height, width, 1) irradiance of a face's texels, computed every few texels and upsampled.

    Irradiance is smooth except at shadow edges, which this softens to about a centimetre.
    """
    box, axis, side = face // 6, (face % 6) // 2, face % 2
    ua, va = _TANGENTS[axis]
    cw, ch = max(2, -(-width // _LIGHT_STEP)), max(2, -(-height // _LIGHT_STEP))
    cols, rows = np.meshgrid((np.arange(cw) + 0.5) * width / cw, (np.arange(ch) + 0.5) * height / ch)
    points = np.empty((3, ch * cw))
    points[axis] = layout.hi[box, axis] if side else layout.lo[box, axis]
    points[ua] = u_edge + cols.ravel() / su
    points[va] = v_edge + rows.ravel() / sv
    coarse = shading(points, face_normal(face), layout, params).reshape(ch, cw)
    return cv2.resize(coarse, (width, height), interpolation=cv2.INTER_LINEAR)[..., None]


def build_atlas(layout: Layout, params: RoomParams) -> Atlas:
    """Texture, light and pack every face of the layout (room faces 0-5, then object faces)."""
    palette = scene_palette(params.seed)
    res = params.texture_resolution
    keys = ("ua", "va", "su", "sv", "u_shift", "v_shift", "last_col", "last_row")
    table: dict[str, list[float]] = {k: [] for k in keys}
    images = []
    for face in range(6 * layout.n_boxes):
        box, axis = face // 6, (face % 6) // 2
        lo, hi = layout.lo[box], layout.hi[box]
        ua, va = _TANGENTS[axis]
        width = max(2, int(np.ceil((hi[ua] - lo[ua]) * res)))
        height = max(2, int(np.ceil((hi[va] - lo[va]) * res)))
        upright = va == 2  # vertical faces: row 0 at the top and columns running to the viewer's right
        flip_u = upright and np.cross(-face_normal(face), [0.0, 0.0, 1.0])[ua] < 0
        su = (-width if flip_u else width) / (hi[ua] - lo[ua])
        sv = (-height if upright else height) / (hi[va] - lo[va])
        u0, v0 = (hi[ua] if flip_u else lo[ua]), (hi[va] if upright else lo[va])
        albedo = surface_texture(params.seed, face, _face_kind(face), width, height, res, palette,
                                 params.patch_density, params.texture_noise)
        light = _face_light(layout, params, face, u0, su, v0, sv, width, height)
        images.append(albedo * light * 255.0)
        for key, value in zip(keys, (ua, va, su, sv, u0 * su + 0.5, v0 * sv + 0.5, width - 1, height - 1)):
            table[key].append(value)
    offsets, atlas_h = _pack([(im.shape[1], im.shape[0]) for im in images])
    if atlas_h >= 32767:
        raise UsvcError(f"texture atlas of {atlas_h} rows exceeds cv2.remap's limit; "
                        "lower texture_resolution")
    atlas = np.zeros((atlas_h, _ATLAS_WIDTH, 3), dtype=np.float32)
    for (x, y), im in zip(offsets, images):
        atlas[y:y + im.shape[0], x:x + im.shape[1]] = im
    arrays = {k: np.array(v, dtype=np.int8 if k in ("ua", "va") else np.float32) for k, v in table.items()}
    return Atlas(image=atlas, ox=np.array([o[0] for o in offsets], dtype=np.float32),
                 oy=np.array([o[1] for o in offsets], dtype=np.float32), **arrays)
