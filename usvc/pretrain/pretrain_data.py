"""Pretraining corpus for the encoder: many procedural rooms rendered in memory with exact depth.

No weights can be downloaded here, so the default encoder is learnt from scenes this project
generates. Each room varies layout, texture statistics, lighting and focal length; every frame
comes with its world coordinates per pixel (from rendered depth), the supervision that lets
an encoder learn locally distinctive features on a CPU budget.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from usvc.generate.params import MAX_FACE_TEXELS, RoomParams
from usvc.generate.room import make_layout
from usvc.generate.textures import build_atlas
from usvc.generate.trajectory import make_sequences
from usvc.generate.writer import Renderer, pixel_rays
from usvc.model.preprocess import luma01

log = logging.getLogger(__name__)


@dataclass
class CorpusScene:
    """Frames of one room: luma in [0, 1], world xyz per pixel (fp16), camera centre mean."""

    seed: int
    gray: np.ndarray  # (F, H, W) float32
    xyz: np.ndarray  # (F, H, W, 3) float16 world coordinates of the pixel centres
    center: np.ndarray  # (3,) mean camera position, the head's scene centre
    partners: list[np.ndarray] | None = None  # real captures: per frame, the frames sharing most tracks


def corpus_params(seed: int, frames_per_scene: int, width: int = 320, height: int = 240) -> RoomParams:
    """A varied room; seed >= 1000 by convention, so no corpus room equals the miniature scene (seed 0)."""
    rng = np.random.default_rng(seed)
    n_seq = 2
    room = (float(rng.uniform(3.2, 6.0)), float(rng.uniform(2.9, 5.0)), float(rng.uniform(2.3, 3.2)))
    texels = min(float(rng.uniform(128, 400)), (MAX_FACE_TEXELS - 8) / max(room))
    return replace(
        RoomParams(),
        seed=seed, width=width, height=height,
        focal=float(rng.uniform(0.6, 1.05) * width),
        room_x=room[0], room_y=room[1], room_z=room[2],
        n_objects=int(rng.integers(1, 8)), n_wall_objects=int(rng.integers(0, 7)),
        texture_resolution=texels, patch_density=float(rng.uniform(4, 26)),
        texture_noise=float(rng.uniform(0.01, 0.09)), image_noise=float(rng.uniform(0.5, 2.5)),
        ambient=float(rng.uniform(0.2, 0.6)), light_intensity=float(rng.uniform(0.35, 0.95)),
        n_lights=int(rng.integers(1, 4)), shadows=bool(rng.random() < 0.7),
        n_map_sequences=n_seq, frames_per_map_sequence=max(2, frames_per_scene // n_seq),
        n_query_frames=1, jitter=float(rng.uniform(0.5, 1.5)), supersample=1,
    )


def render_scene(params: RoomParams) -> CorpusScene:
    layout = make_layout(params)
    renderer = Renderer(params, layout, build_atlas(layout, params))
    rays = pixel_rays(params.width, params.height, params.focal)  # (3, H, W), z = 1
    grays, xyzs, centres = [], [], []
    mapping = [seq for seq in make_sequences(params, layout) if seq.split == "train"]
    for seq_i, seq in enumerate(mapping):
        for k, cam_to_world in enumerate(seq.cam_to_world):
            rgb, depth = renderer.render(cam_to_world, noise_seed=params.seed * 100_000 + seq_i * 1000 + k)
            cam = rays * depth[None]
            world = np.einsum("ij,jhw->hwi", cam_to_world[:3, :3], cam) + cam_to_world[:3, 3]
            grays.append(luma01(rgb, rgb=True))
            xyzs.append(world.astype(np.float16))
            centres.append(cam_to_world[:3, 3])
    return CorpusScene(seed=params.seed, gray=np.stack(grays), xyz=np.stack(xyzs),
                       center=np.mean(centres, axis=0))


def build_corpus(n_scenes: int, first_seed: int, frames_per_scene: int) -> list[CorpusScene]:
    scenes = []
    for seed in tqdm(range(first_seed, first_seed + n_scenes), desc="corpus", unit="room"):
        scenes.append(render_scene(corpus_params(seed, frames_per_scene)))
    n_frames = sum(len(s.gray) for s in scenes)
    log.info("pretraining corpus: %d rooms, %d frames", len(scenes), n_frames)
    return scenes
