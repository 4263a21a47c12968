"""Handheld-like camera paths: smooth arcs around the room centre with smooth seeded jitter.

Mapping sequences run on elliptic arcs at different wall distances and heights; together they
cover the full circle. The query sequence runs between them (another distance and height), so
it sees the same surfaces from viewpoints that no mapping frame has. Poses are camera-to-world
in OpenCV camera axes (x right, y down, z forward) in the z-up metric world of ``room``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usvc.core.errors import UsvcError
from usvc.generate.params import RoomParams
from usvc.generate.room import CAMERA_Z_RANGE, Layout

MIN_CLEARANCE = 0.3  # metres from any wall or box surface
WALL_MARGINS = (0.8, 1.1)  # horizontal camera distance from the walls: outermost, innermost arc
LOOK_BEYOND = 1.2  # metres past the room centre, opposite the camera's phase, looked at
TARGET_Z = 0.85
QUERY_ARC_DEG = 120.0
MAP_ARC_OVERLAP_DEG = 20.0  # mapping arcs split the circle and overlap by this much
_POSITION_JITTER, _HEIGHT_JITTER, _TARGET_JITTER = 0.05, 0.04, 0.15  # metres at jitter = 1
_PHASE_JITTER_DEG, _ROLL_JITTER_DEG = 2.0, 3.0


@dataclass(frozen=True)
class Sequence:
    """One continuous recording: its dataset name ("seq-01"), split, and (n, 4, 4) poses."""

    name: str
    split: str
    cam_to_world: np.ndarray


def smooth_noise(rng: np.random.Generator, n: int, dims: int) -> np.ndarray:
    """(n, dims) smooth noise bounded by 1: a few slow sines (0.4-4 cycles over the sequence)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    out = np.zeros((n, dims))
    for low, high, weight in ((0.4, 1.2, 0.45), (0.8, 2.0, 0.35), (2.0, 4.0, 0.2)):
        freq, phase = rng.uniform(low, high, dims), rng.uniform(0.0, 2 * np.pi, dims)
        out += weight * np.sin(2 * np.pi * freq * t + phase)
    return out


def look_at(centre: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes) looking from centre at target, rolled about z."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.column_stack([x, y, z]) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _arc(rng: np.random.Generator, layout: Layout, jitter: float, margin: float, height: float,
         start_deg: float, arc_deg: float, n: int) -> np.ndarray:
    """(n, 4, 4) camera-to-world poses along one jittered elliptic arc."""
    centre = layout.centre
    semi = centre[:2] - margin  # ellipse semi-axes keep ``margin`` from the walls
    phase = np.radians(start_deg + arc_deg * np.linspace(0.0, 1.0, n))
    phase += np.radians(_PHASE_JITTER_DEG) * jitter * smooth_noise(rng, n, 1)[:, 0]
    xy = centre[:2] + semi * np.column_stack([np.cos(phase), np.sin(phase)])
    xy += _POSITION_JITTER * jitter * smooth_noise(rng, n, 2)
    z = height + _HEIGHT_JITTER * jitter * smooth_noise(rng, n, 1)[:, 0]
    # Aim by phase, not position, so the view turns evenly even where the ellipse nears the centre.
    target_xy = centre[:2] - LOOK_BEYOND * np.column_stack([np.cos(phase), np.sin(phase)])
    target_xy += _TARGET_JITTER * jitter * smooth_noise(rng, n, 2)
    target_z = TARGET_Z + _TARGET_JITTER * jitter * smooth_noise(rng, n, 1)[:, 0]
    roll = np.radians(_ROLL_JITTER_DEG) * jitter * smooth_noise(rng, n, 1)[:, 0]
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        eye = np.array([xy[i, 0], xy[i, 1], z[i]])
        poses[i, :3, :3] = look_at(eye, np.array([target_xy[i, 0], target_xy[i, 1], target_z[i]]), roll[i])
        poses[i, :3, 3] = eye
    return poses


def make_sequences(params: RoomParams, layout: Layout) -> list[Sequence]:
    """Mapping sequences (split "train", seq-01..) then the query sequence (split "test")."""
    n_map = params.n_map_sequences
    z_lo, z_hi = CAMERA_Z_RANGE[0], min(CAMERA_Z_RANGE[1], params.room_z - 0.55)
    sequences = []
    for k in range(n_map):
        frac = k / (n_map - 1) if n_map > 1 else 0.0
        margin = WALL_MARGINS[0] + frac * (WALL_MARGINS[1] - WALL_MARGINS[0])
        height = z_lo + (z_hi - z_lo) * (0.1 if k % 2 == 0 else 0.9)
        rng = np.random.default_rng([params.seed, 404, k])
        start, span = k * 360.0 / n_map, 360.0 / n_map + MAP_ARC_OVERLAP_DEG
        poses = _arc(rng, layout, params.jitter, margin, height, start, span, params.frames_per_map_sequence)
        sequences.append(Sequence(f"seq-{k + 1:02d}", "train", poses))
    rng = np.random.default_rng([params.seed, 404, n_map])
    poses = _arc(rng, layout, params.jitter, float(np.mean(WALL_MARGINS)), 0.5 * (z_lo + z_hi),
                 180.0 / n_map + MAP_ARC_OVERLAP_DEG, QUERY_ARC_DEG, params.n_query_frames)
    sequences.append(Sequence(f"seq-{n_map + 1:02d}", "test", poses))
    for seq in sequences:
        worst = min(layout.clearance(p[:3, 3]) for p in seq.cam_to_world)
        if worst < MIN_CLEARANCE:
            raise UsvcError(f"{seq.name} passes {worst:.3f} m from a surface (< {MIN_CLEARANCE} m); "
                            "use a larger room or less jitter")
    return sequences
