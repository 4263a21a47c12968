"""Typed configuration: Hydra structured-config schemas for every YAML file under conf/.

The YAML files are the single source of values (DVC tracks them directly); these dataclasses
are the schema, so an unknown key or a value of the wrong type fails at compose time, and
`validate` catches values outside their allowed set with a message naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Optional

from hydra.core.config_store import ConfigStore

from usvc.core.errors import UsvcError
from usvc.generate.params import RoomParams


class ConfigError(UsvcError):
    """A configuration value is outside what the stage accepts."""


@dataclass
class SceneConfig:
    name: str = "???"
    format: str = "???"
    path: str = "???"
    split: str = "???"  # "given" (the format's own split) or "every_nth"
    split_n: int = 8
    metric_scale: Optional[float] = None  # metres per scene unit; null = unknown
    working_width: int = 640  # images are resized to this width before anything else
    undistort_fov: str = "crop"  # distorted cameras -> pinhole: crop (no black border) | full (all pixels)
    generated: bool = False  # produced by stages.generate (the miniature scene)


@dataclass
class SfmConfig:
    max_num_features: int = 4096
    matching: str = "auto"  # auto | exhaustive | sequential | poses
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    pose_pairs_per_image: int = 20
    reconstruction: str = "auto"  # auto | triangulate | incremental
    min_points: int = 100
    num_threads: int = -1  # -1 = the top-level threads setting
    seed: int = 0  # COLMAP's RANSAC seed; apart from the global seed so mapping seeds reuse the SfM


@dataclass
class KeypointsConfig:
    tau: float = 1.5
    sigma: float = 0.15
    weights: str = "uniform"  # uniform | reprojection
    reprojection_scale_px: float = 1.0
    min_track_length: int = 2


@dataclass
class ModelConfig:
    name: str = "default"
    encoder: str = "ace"  # ace: the ACE-layout encoder (shipped or encoder_weights) | xfeat: XFeat's backbone
    encoder_width: float = 1.0  # channel multiplier of the ace encoder; 0.5 is model=small
    encoder_weights: Optional[str] = None  # null = the encoder shipped for this width (usvc/weights)
    head_width: int = 512
    head_blocks: int = 1
    # Larger images are scaled down to this short side for mapping and queries (0 = never): the
    # scale of image content the encoder was pretrained at. buffer.short_side, when set, wins.
    max_short_side: int = 0


@dataclass
class BufferConfig:
    size: int = 262144  # cells
    samples_per_image: int = 1024
    short_side: int = 0  # working short side the map is trained and queried at; 0 = the prepared images', at most model.max_short_side
    scale_min: float = 0.6667
    scale_max: float = 1.5
    max_rotation_deg: float = 15.0
    brightness_min: float = 0.9
    brightness_max: float = 1.1
    contrast_min: float = 0.9
    contrast_max: float = 1.1
    keypoint_obs_per_view: int = 1024  # cap on keypoint tuples stored per augmented view (0 = all)
    depth_visibility_tol: float = 0.05  # a non-track keypoint is visible where |depth - z| < tol * z
    rendered_views: bool = False  # add the render stage's Gaussian-splatting views (method=multiview_gs)
    holdout_every: int = 0  # withhold every k-th mapping image from training (a validation split); 0 = none


@dataclass
class TrainConfig:
    iterations: int = 6000
    batch_size: int = 2048
    optimizer: str = "adamw"  # adamw | adabelief
    lr: float = 5e-3  # peak LR of the one-cycle schedule, or the constant LR
    schedule: str = "one_cycle"  # one_cycle | constant
    warmup_fraction: float = 0.3
    weight_decay: float = 0.01
    threshold_start: float = 50.0  # tau (px) goes from threshold_start + threshold_end to threshold_end
    threshold_end: float = 1.0
    depth_min_rel: float = 0.05  # depth bounds in units of the scene's median depth
    depth_max_rel: float = 500.0
    invalid_depth_rel: float = 5.0
    max_reproj_px: float = 1000.0
    reproj_weight: float = 1.0  # lambda_pi (paper eq. 8)
    bundle_weight: float = 0.25  # lambda_B (paper eq. 8, where it is 1.0); 0 = ACE-style single-view training
    bundle_loss: str = "tanh"  # tanh (ACE's soft clamp, shares the threshold schedule) | squared (eq. 7 as printed)
    bundle_groups_per_batch: int = 64  # whole keypoint groups mixed into every batch of pixel samples
    bundle_obs_per_group: int = 16  # observations drawn per group (all of them when fewer)


@dataclass
class RelocalizeConfig:
    backend: str = "opencv"  # opencv | pycolmap
    max_error_px: float = 10.0  # RANSAC inlier threshold at a 480 px short side, scaled to the working size
    min_inliers: int = 10
    min_confidence: float = 0.1  # inlier fraction of the cells below which an answer counts as a failure
    focal_tolerance: float = 0.25  # relative gap between the given and the map-implied focal length that fails; 0 = off
    refine: bool = True  # keypoint-guided iterative refinement (paper 3.2.2)
    refine_radius_px: float = 8.0  # mask radius around each projected keypoint, working-image pixels
    refine_max_iterations: int = 5  # T_max
    refine_delta: float = 1e-3  # stop when |dR|_F + |dt| / median depth < delta
    refine_min_correspondences: int = 20  # fewer masked cells than this: keep the current pose


@dataclass
class GaussiansConfig:
    iterations: int = 400
    width: int = 160  # fit and evaluation width, px (0 = the prepared images' width)
    sh_degree: int = 3
    sh_increase_every: int = 100
    ssim_weight: float = 0.2
    lr_means: float = 1.6e-4  # times the scene extent
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 1.25e-4
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    densify_from: int = 100
    densify_until: int = 300
    densify_every: int = 50
    opacity_reset_every: int = 200  # 0 = never
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    max_screen_radius: float = 0.0  # px, 0 = off
    max_world_scale: float = 0.1  # fraction of the scene extent
    max_gaussians: int = 20000
    initial_opacity: float = 0.1
    holdout_every: int = 8  # every n-th mapping image is held out for PSNR/SSIM; 0 = none
    tile: int = 8
    seed: int = 0


@dataclass
class RenderConfig:
    views: int = 30  # novel views to render
    max_angle_deg: float = 20.0  # orbit angle about the keypoint cluster, from the source view
    max_translation_rel: float = 0.1  # extra camera translation, in units of the cluster's depth
    cluster_radius_rel: float = 0.15  # keypoints within this fraction of the depth of the centre form a cluster
    min_cluster_keypoints: int = 10
    min_visible_keypoints: int = 20  # a sampled pose is kept when at least this many keypoints are visible
    max_tries: int = 20  # per view, before giving up on a source view
    width: int = 0  # render width, px (0 = the prepared images' width)
    depth_tolerance: float = 0.05  # visible where |rendered depth - z| < tol * z
    min_alpha: float = 0.5  # and the rendered opacity there is at least this
    seed: int = 0


@dataclass
class Config:
    seed: int = 0  # mapping seed: buffer sampling, head initialisation, RANSAC at query time
    threads: str = "auto"  # torch/OpenCV/COLMAP/BLAS threads: auto (cores / jobs side by side) or a number
    method: str = "multiview"  # set by the method group: single | multiview | multiview_gs
    data_dir: str = "data"
    results_dir: str = "results"
    scene: SceneConfig = field(default_factory=SceneConfig)
    generate: RoomParams = field(default_factory=RoomParams)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    keypoints: KeypointsConfig = field(default_factory=KeypointsConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    relocalize: RelocalizeConfig = field(default_factory=RelocalizeConfig)
    gaussians: GaussiansConfig = field(default_factory=GaussiansConfig)
    render: RenderConfig = field(default_factory=RenderConfig)


_CHOICES: dict[str, tuple[str, ...]] = {
    "scene.format": ("llff", "transforms", "colmap", "ace", "7scenes", "cambridge", "images"),
    "scene.split": ("given", "every_nth"),
    "scene.undistort_fov": ("crop", "full"),
    "sfm.matching": ("auto", "exhaustive", "sequential", "poses"),
    "sfm.reconstruction": ("auto", "triangulate", "incremental"),
    "keypoints.weights": ("uniform", "reprojection"),
    "train.optimizer": ("adamw", "adabelief"),
    "train.schedule": ("one_cycle", "constant"),
    "relocalize.backend": ("opencv", "pycolmap"),
    "method": ("single", "multiview", "multiview_gs"),
    "train.bundle_loss": ("tanh", "squared"),
    "model.encoder": ("ace", "xfeat"),
}
_POSITIVE: tuple[str, ...] = (
    "scene.split_n", "sfm.max_num_features", "sfm.exhaustive_max_images", "sfm.sequential_overlap",
    "sfm.pose_pairs_per_image", "keypoints.sigma", "keypoints.reprojection_scale_px",
    "keypoints.min_track_length",
    "model.encoder_width", "model.head_width", "buffer.size", "buffer.samples_per_image", "buffer.scale_min",
    "buffer.scale_max", "buffer.brightness_min", "buffer.contrast_min", "train.iterations", "train.batch_size",
    "train.lr", "train.depth_min_rel", "relocalize.max_error_px", "relocalize.min_inliers",
    "train.reproj_weight", "train.bundle_groups_per_batch", "train.bundle_obs_per_group",
    "buffer.depth_visibility_tol", "relocalize.refine_radius_px", "relocalize.refine_max_iterations",
    "relocalize.refine_delta", "relocalize.refine_min_correspondences",
    "gaussians.iterations", "gaussians.sh_increase_every", "gaussians.lr_means", "gaussians.lr_means_final",
    "gaussians.densify_every", "gaussians.densify_grad_threshold", "gaussians.percent_dense",
    "gaussians.max_world_scale", "gaussians.max_gaussians", "gaussians.initial_opacity", "gaussians.tile",
    "render.views", "render.max_tries", "render.depth_tolerance", "render.min_cluster_keypoints",
    "render.min_visible_keypoints", "render.cluster_radius_rel",
)


def _get(cfg: Any, dotted: str) -> Any:
    node = cfg
    for part in dotted.split("."):
        node = getattr(node, part)
    return node


def _known_keys() -> list[str]:
    top = [f.name for f in fields(Config)]
    return top + [f"{g}.{f.name}" for g, schema in GROUP_SCHEMAS.items() for f in fields(schema)]


def _check_keys(cfg: Any) -> None:
    """Every key must be one of the schema's: Hydra's `+key=value` (and `++`) can add keys that the
    schema does not have, which the stages would otherwise ignore or trip over deep inside."""
    import difflib

    from omegaconf import DictConfig

    if not isinstance(cfg, DictConfig):
        return
    known = _known_keys()
    found = [k for k in cfg.keys() if k != "hydra"]
    found += [f"{g}.{k}" for g in GROUP_SCHEMAS if isinstance(cfg.get(g), DictConfig) for k in cfg[g].keys()]
    for key in found:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ConfigError(f"config key {key} is not a setting of usvc{hint}")


def validate(cfg: Any) -> None:
    """Reject unknown keys and values outside their allowed set (Hydra has checked the types)."""
    _check_keys(cfg)
    for key, choices in _CHOICES.items():
        value = _get(cfg, key)
        if value not in choices:
            raise ConfigError(f"config key {key}={value!r} is not one of {list(choices)}")
    for key in _POSITIVE:
        if not _get(cfg, key) > 0:
            raise ConfigError(f"config key {key}={_get(cfg, key)!r} must be > 0")
    if cfg.keypoints.tau < 0:
        raise ConfigError(f"config key keypoints.tau={cfg.keypoints.tau!r} must be >= 0")
    if cfg.scene.working_width < 0:
        raise ConfigError(f"config key scene.working_width={cfg.scene.working_width!r} must be >= 0 (0 keeps the size)")
    for lo, hi in (("buffer.scale_min", "buffer.scale_max"), ("buffer.brightness_min", "buffer.brightness_max"),
                   ("buffer.contrast_min", "buffer.contrast_max")):
        if _get(cfg, lo) > _get(cfg, hi):
            raise ConfigError(f"config key {lo}={_get(cfg, lo)!r} exceeds {hi}={_get(cfg, hi)!r}")
    if not 0 <= cfg.relocalize.min_confidence <= 1:
        raise ConfigError(f"config key relocalize.min_confidence={cfg.relocalize.min_confidence!r} must be in [0, 1]")
    if cfg.relocalize.focal_tolerance < 0:
        raise ConfigError(f"config key relocalize.focal_tolerance={cfg.relocalize.focal_tolerance!r} must be >= 0 (0: no check)")
    if not 0 <= cfg.train.warmup_fraction < 1:
        raise ConfigError(f"config key train.warmup_fraction={cfg.train.warmup_fraction!r} must be in [0, 1)")
    if cfg.buffer.short_side < 0 or cfg.model.head_blocks < 0 or cfg.model.max_short_side < 0:
        raise ConfigError("config keys buffer.short_side, model.head_blocks and model.max_short_side must be >= 0")
    if cfg.train.bundle_weight < 0 or cfg.buffer.keypoint_obs_per_view < 0:
        raise ConfigError("config keys train.bundle_weight and buffer.keypoint_obs_per_view must be >= 0")
    if not 0 <= cfg.gaussians.sh_degree <= 3:
        raise ConfigError(f"config key gaussians.sh_degree={cfg.gaussians.sh_degree!r} must be 0..3")
    if not 0 < cfg.gaussians.initial_opacity < 1 or not 0 <= cfg.gaussians.ssim_weight <= 1:
        raise ConfigError("config keys gaussians.initial_opacity must be in (0, 1) and gaussians.ssim_weight in [0, 1]")
    for key in ("gaussians.width", "gaussians.densify_from", "gaussians.densify_until", "gaussians.opacity_reset_every",
                "gaussians.holdout_every", "gaussians.max_screen_radius", "render.width", "render.max_angle_deg",
                "render.max_translation_rel", "render.min_alpha"):
        if _get(cfg, key) < 0:
            raise ConfigError(f"config key {key}={_get(cfg, key)!r} must be >= 0")
    try:
        from usvc.pipeline.threads import resolve

        resolve(cfg.threads)
    except ValueError as err:
        raise ConfigError(f"config key {err}") from None
    if cfg.scene.metric_scale is not None and not cfg.scene.metric_scale > 0:
        raise ConfigError(f"config key scene.metric_scale={cfg.scene.metric_scale!r} must be > 0 or null")


def register_configs() -> None:
    """Schemas for the primary config and each group, referenced from the YAML defaults lists."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="scene", name="base_scene", node=SceneConfig)
    cs.store(group="generate", name="base_generate", node=RoomParams)
    cs.store(group="sfm", name="base_sfm", node=SfmConfig)
    cs.store(group="keypoints", name="base_keypoints", node=KeypointsConfig)
    cs.store(group="model", name="base_model", node=ModelConfig)
    cs.store(group="buffer", name="base_buffer", node=BufferConfig)
    cs.store(group="train", name="base_train", node=TrainConfig)
    cs.store(group="relocalize", name="base_relocalize", node=RelocalizeConfig)
    cs.store(group="gaussians", name="base_gaussians", node=GaussiansConfig)
    cs.store(group="render", name="base_render", node=RenderConfig)


GROUP_SCHEMAS: dict[str, type] = {
    "scene": SceneConfig,
    "generate": RoomParams,
    "sfm": SfmConfig,
    "keypoints": KeypointsConfig,
    "model": ModelConfig,
    "buffer": BufferConfig,
    "train": TrainConfig,
    "relocalize": RelocalizeConfig,
    "gaussians": GaussiansConfig,
    "render": RenderConfig,
}


def schema_fields(schema: type) -> list[str]:
    return [f.name for f in fields(schema)]


def compose_for_script(scene: str, overrides: list[str]) -> Any:
    """The config a stage would see for ``scene=<scene> <overrides>``, for scripts outside Hydra's
    entry points (benchmarks): the same schema and the same validation."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    register_configs()
    conf_dir = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf_dir), version_base=None):
        cfg = compose(config_name="config", overrides=[f"scene={scene}", *overrides])
    validate(cfg)
    return cfg
