"""Room geometry, exact ray casting and Lambertian lighting.

World frame: metres, z up, floor at z = 0; the room interior is the axis-aligned box
[0, room_x] x [0, room_y] x [0, room_z]. Every object is an axis-aligned box inside it.
Box 0 is the room itself; box b has the six faces 6b + 2*axis + side (side 0: the face at
``lo[axis]``, side 1: the face at ``hi[axis]``). Room faces face inwards, object faces outwards.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from usvc.generate.params import RoomParams

log = logging.getLogger(__name__)

CAMERA_Z_RANGE = (1.2, 1.65)  # camera heights; free-standing boxes stay below CENTRE_BOX_MAX_Z
CENTRE_BOX_MAX_Z = 0.8
WALL_BAND_DEPTH = 0.35  # floor boxes away from the centre hug a wall within this depth
_PLACEMENT_TRIES = 200


@dataclass(frozen=True)
class Layout:
    """Axis-aligned boxes (row 0 = room interior) and point-light positions."""

    lo: np.ndarray  # (B, 3) box minimum corners
    hi: np.ndarray  # (B, 3) box maximum corners
    lights: np.ndarray  # (L, 3)

    @property
    def n_boxes(self) -> int:
        return len(self.lo)

    @property
    def centre(self) -> np.ndarray:
        return 0.5 * (self.lo[0] + self.hi[0])

    def clearance(self, point: np.ndarray) -> float:
        """Distance from a point inside the room to the nearest wall or object surface."""
        p = np.asarray(point, dtype=np.float64)
        dist = float(min((p - self.lo[0]).min(), (self.hi[0] - p).min()))
        for lo, hi in zip(self.lo[1:], self.hi[1:]):
            gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
            dist = min(dist, float(np.linalg.norm(gap)))
        return dist


def _overlaps(lo: np.ndarray, hi: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]],
              margin: float) -> bool:
    return any(np.all(lo < bh + margin) and np.all(blo < hi + margin) for blo, bh in boxes)


def _wall_box(rng: np.random.Generator, room: np.ndarray, along: float, depth: float, gap: float,
              z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """A box against a random wall: ``along`` wide, ``depth`` deep, ``gap`` away from the wall."""
    wall = int(rng.integers(4))
    axis, side = wall // 2, wall % 2  # the wall's normal axis (x or y) and which end
    other = 1 - axis
    start = rng.uniform(0.05, room[other] - along - 0.05)
    lo, hi = np.zeros(3), np.zeros(3)
    lo[other], hi[other] = start, start + along
    if side == 0:
        lo[axis], hi[axis] = gap, gap + depth
    else:
        lo[axis], hi[axis] = room[axis] - gap - depth, room[axis] - gap
    lo[2], hi[2] = z0, z1
    return lo, hi


def make_layout(params: RoomParams) -> Layout:
    """Place the boxes and lights for ``params.seed``; cameras later fly in the free band."""
    rng = np.random.default_rng([params.seed, 101])
    room = np.array([params.room_x, params.room_y, params.room_z])
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    for i in range(params.n_objects):
        for _ in range(_PLACEMENT_TRIES):
            if i == 0:  # a low table-like box in the middle, below the camera heights
                half = np.append(rng.uniform(0.15, 0.35, 2), 0.0)
                centre = np.append(room[:2] / 2 + rng.uniform(-0.08, 0.08, 2), 0.0)
                lo, hi = centre - half, centre + half
                hi[2] = rng.uniform(0.35, CENTRE_BOX_MAX_Z)
            else:  # cupboards and crates along the walls, possibly taller than the cameras
                lo, hi = _wall_box(rng, room, rng.uniform(0.3, 1.0), rng.uniform(0.2, WALL_BAND_DEPTH - 0.05),
                                   rng.uniform(0.0, 0.05), 0.0, rng.uniform(0.3, 1.5))
            if not _overlaps(lo, hi, boxes, 0.05):
                boxes.append((lo, hi))
                break
        else:
            log.warning("could not place floor object %d without overlap; skipped", i)
    for i in range(params.n_wall_objects):
        for _ in range(_PLACEMENT_TRIES):
            height = rng.uniform(0.2, 0.7)
            z0 = rng.uniform(0.9, room[2] - 0.3 - height)
            depth = 0.02 if rng.random() < 0.5 else rng.uniform(0.1, 0.25)  # picture or shelf
            lo, hi = _wall_box(rng, room, rng.uniform(0.3, 0.9), depth, 0.0, z0, z0 + height)
            if not _overlaps(lo, hi, boxes, 0.05):
                boxes.append((lo, hi))
                break
        else:
            log.warning("could not place wall object %d without overlap; skipped", i)
    lights = np.column_stack([
        rng.uniform(0.25, 0.75, params.n_lights) * room[0],
        rng.uniform(0.25, 0.75, params.n_lights) * room[1],
        np.full(params.n_lights, room[2] - 0.2),
    ])
    lo = np.array([np.zeros(3)] + [b[0] for b in boxes])
    hi = np.array([room] + [b[1] for b in boxes])
    return Layout(lo=lo, hi=hi, lights=lights)


def _safe_inverse(dirs: np.ndarray) -> np.ndarray:
    """1/d with exact zeros nudged, so slab tests never compute 0 * inf."""
    tiny = np.asarray(1e-12, dtype=dirs.dtype)
    return 1.0 / np.where(np.abs(dirs) < tiny, tiny, dirs)


def pixel_rects(layout: Layout, cam_to_world: np.ndarray, focal: float, width: int,
                height: int) -> list[tuple[int, int, int, int] | None]:
    """Per box, the pixel rows/columns (r0, r1, c0, c1) its projection can cover; None = all.

    A ray can only hit a box wholly in front of the camera inside the bounding rectangle of its
    projected corners, so ray casting tests just that window. Box 0 (the room) is always None.
    """
    rot, centre = cam_to_world[:3, :3], cam_to_world[:3, 3]
    rects: list[tuple[int, int, int, int] | None] = [None]
    for lo, hi in zip(layout.lo[1:], layout.hi[1:]):
        corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, 8).T
        cam = (corners - centre) @ rot
        if (cam[:, 2] <= 1e-6).all():
            rects.append((0, 0, 0, 0))  # behind the camera
            continue
        if (cam[:, 2] <= 1e-6).any():
            rects.append(None)
            continue
        u = focal * cam[:, 0] / cam[:, 2] + width / 2
        v = focal * cam[:, 1] / cam[:, 2] + height / 2
        c0, c1 = int(np.clip(np.floor(u.min()) - 2, 0, width)), int(np.clip(np.ceil(u.max()) + 2, 0, width))
        r0, r1 = int(np.clip(np.floor(v.min()) - 2, 0, height)), int(np.clip(np.ceil(v.max()) + 2, 0, height))
        rects.append((r0, r1, c0, c1))
    return rects


def cast(origin: np.ndarray, dirs: np.ndarray, layout: Layout,
         rects: list[tuple[int, int, int, int] | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + t * dirs`` (dirs (3, H, W)) from inside the room: (t, face).

    The room is convex and closed, so every ray hits something; t is in units of ``dirs``.
    ``rects`` (from :func:`pixel_rects`) limits each box's test to a window of the grid.
    """
    inv = _safe_inverse(dirs)
    positive = dirs > 0
    rel_lo = (layout.lo - origin).astype(dirs.dtype)
    rel_hi = (layout.hi - origin).astype(dirs.dtype)
    exits = [np.maximum(rel_lo[0, a] * inv[a], rel_hi[0, a] * inv[a]) for a in range(3)]
    t = np.minimum(exits[0], exits[1])
    axis = np.where(exits[2] <= t, 2, exits[1] < exits[0]).astype(np.int16)
    np.minimum(t, exits[2], out=t)
    side = np.where(axis == 0, positive[0], np.where(axis == 1, positive[1], positive[2]))
    face = 2 * axis + side  # the room exits through the hi plane of an axis it moves up along
    for b in range(1, layout.n_boxes):
        rect = rects[b] if rects is not None else None
        win = (slice(None),) if rect is None else (slice(rect[0], rect[1]), slice(rect[2], rect[3]))
        inv_w, t_w, face_w = inv[(slice(None), *win)], t[win], face[win]
        if t_w.size == 0:
            continue
        t1 = rel_lo[b][:, None, None] * inv_w
        t2 = rel_hi[b][:, None, None] * inv_w
        tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
        near = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
        far = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        hit = (near <= far) & (near > 0) & (near < t_w)
        if not hit.any():
            continue
        t_w[hit] = near[hit]
        entry = tmin[:, hit].argmax(axis=0)  # the slab entered last is the face hit
        moving_down = np.take_along_axis(inv_w[:, hit], entry[None], axis=0)[0] < 0
        face_w[hit] = 6 * b + 2 * entry + moving_down  # moving down, a box is entered at its hi plane
    return t, face


def face_normal(face: int) -> np.ndarray:
    """Unit normal of a face, pointing into the free space the cameras see it from."""
    box, axis, side = face // 6, (face % 6) // 2, face % 2
    n = np.zeros(3)
    outward = 1.0 if side == 1 else -1.0
    n[axis] = -outward if box == 0 else outward
    return n


def _blocked(points: np.ndarray, light: np.ndarray, layout: Layout) -> np.ndarray:
    """Whether the segment from each point (3, N) to the light passes through an object box."""
    dirs = light[:, None] - points
    inv = _safe_inverse(dirs)
    blocked = np.zeros(points.shape[1], dtype=bool)
    for b in range(1, layout.n_boxes):
        t1 = (layout.lo[b][:, None] - points) * inv
        t2 = (layout.hi[b][:, None] - points) * inv
        near = np.minimum(t1, t2).max(axis=0)
        far = np.maximum(t1, t2).min(axis=0)
        blocked |= (near <= far) & (far > 0) & (near < 1)
    return blocked


def shading(points: np.ndarray, normal: np.ndarray, layout: Layout, params: RoomParams) -> np.ndarray:
    """Ambient + Lambertian irradiance of surface points (3, N) with one normal; view-independent."""
    total = np.full(points.shape[1], params.ambient, dtype=np.float32)
    lifted = points + 1e-3 * normal[:, None].astype(points.dtype)  # off the surface for shadow rays
    for light in layout.lights:
        to_light = light[:, None] - points
        d2 = (to_light * to_light).sum(axis=0)
        cos = np.maximum(normal @ to_light / np.sqrt(d2), 0.0)
        lit = params.light_intensity * cos / (1.0 + d2 / 4.0)  # soft inverse-square falloff
        if params.shadows and layout.n_boxes > 1:
            lit[_blocked(lifted, light, layout)] = 0.0
        total += lit.astype(np.float32)
    return total
