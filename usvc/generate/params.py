"""Parameters of one procedural room scene.

Every field is a plain int/float/bool/str so the dataclass can be registered with Hydra's
ConfigStore as a structured config. The same parameters always produce the same files.
"""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.errors import UsvcError


@dataclass
class RoomParams:
    """The miniature room (usvc/generate): scene, texture, lighting, trajectory and rendering
    settings (metres, pixels, seconds), the options of the generate step (the `generate` config
    group). Seeded, so the same values give byte-identical images."""

    seed: int = 0  # the room, its textures and trajectories follow from this seed
    # Camera: pinhole, fx = fy = focal, principal point at the image centre (W/2, H/2).
    width: int = 320  # image width, px
    height: int = 240  # image height, px
    focal: float = 260.0  # focal length, px
    # Room interior extent; the world frame is z-up with the floor at z = 0.
    room_x: float = 4.0  # room length, m
    room_y: float = 3.0  # room width, m
    room_z: float = 2.6  # room height, m
    n_objects: int = 4  # boxes standing on the floor (the first one in the room centre)
    n_wall_objects: int = 3  # thin boxes hanging on walls (shelves, pictures)
    # Textures.
    texture_resolution: float = 256.0  # texels per metre
    patch_density: float = 14.0  # painted shapes per square metre of surface
    texture_noise: float = 0.04  # std of the per-texel albedo noise (albedo is in [0, 1])
    image_noise: float = 1.0  # std of the per-pixel sensor noise in 8-bit levels
    # Lighting: ambient + Lambertian point lights under the ceiling, hard box shadows.
    ambient: float = 0.4  # ambient light level
    light_intensity: float = 0.65  # intensity of each point light
    n_lights: int = 2  # point lights under the ceiling
    shadows: bool = True  # hard shadows of the boxes
    # Trajectories.
    n_map_sequences: int = 2  # mapping sequences (camera arcs)
    frames_per_map_sequence: int = 30  # frames per mapping sequence
    n_query_frames: int = 20  # query frames (a separate arc)
    jitter: float = 1.0  # scale of the smooth handheld jitter (0 = perfectly smooth arcs)
    # Rendering: shade at supersample x the resolution, then area-average down.
    supersample: int = 2  # shading samples per pixel side (1..4), area-averaged down

    def problems(self) -> list[str]:
        return room_problems(self)


MIN_ROOM_XY = 2.8  # the camera arcs keep 0.8-1.1 m from the walls
MIN_ROOM_Z = 2.2
MAX_FACE_TEXELS = 2048  # the texture atlas width (usvc.generate.textures)  # cameras fly at 1.2-1.65 m, above every free-standing box


def room_problems(params: RoomParams) -> list[str]:
    """Reject settings the layout and trajectory guarantees (clearance, overlap) do not cover."""
    problems = []
    if params.width < 8 or params.height < 8:
        problems.append(f"image size {params.width}x{params.height} is below 8x8")
    if params.focal <= 0:
        problems.append(f"focal must be positive, got {params.focal}")
    if min(params.room_x, params.room_y) < MIN_ROOM_XY or params.room_z < MIN_ROOM_Z:
        problems.append(
            f"room {params.room_x}x{params.room_y}x{params.room_z} m is smaller than "
            f"{MIN_ROOM_XY}x{MIN_ROOM_XY}x{MIN_ROOM_Z} m"
        )
    if params.n_objects < 0 or params.n_wall_objects < 0:
        problems.append("object counts must be non-negative")
    if params.texture_resolution < 16 or params.texture_resolution > 1024:
        problems.append(f"texture_resolution must be in [16, 1024], got {params.texture_resolution}")
    longest = max(params.room_x, params.room_y, params.room_z) * params.texture_resolution
    if longest > MAX_FACE_TEXELS:
        problems.append(
            f"the longest wall needs {longest:.0f} texels (room side x texture_resolution), "
            f"more than the texture atlas width {MAX_FACE_TEXELS}; lower texture_resolution"
        )
    if params.n_lights < 1 or params.light_intensity < 0 or params.ambient < 0:
        problems.append("need n_lights >= 1 and non-negative light_intensity and ambient")
    if params.n_map_sequences < 1 or params.frames_per_map_sequence < 2 or params.n_query_frames < 1:
        problems.append("need >= 1 mapping sequence of >= 2 frames and >= 1 query frame")
    if params.supersample not in (1, 2, 3, 4):
        problems.append(f"supersample must be 1, 2, 3 or 4, got {params.supersample}")
    if params.jitter < 0 or params.jitter > 2:
        problems.append(f"jitter must be in [0, 2], got {params.jitter}")
    return problems


def validate(params: RoomParams) -> None:
    problems = room_problems(params)
    if problems:
        raise UsvcError("invalid RoomParams: " + "; ".join(problems))
