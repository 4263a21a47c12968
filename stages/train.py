"""Stage: fit the scene's regression head on the buffer (ACE reprojection loss) -> map.pt."""

import logging
import time

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from usvc.buffer.build import HELDOUT_FILE, check_buffer_encoder, read_buffer, read_buffer_attrs
from usvc.core.atomic import atomic_dir
from usvc.core.errors import UsvcError
from usvc.model.head import Regressor, save_map
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, scene_paths, stage_main, stage_outputs
from usvc.sfm.median_depth import median_scene_depth
from usvc.sfm.tracks import read_tracks
from usvc.train.trainer import train_head
from usvc.weights import load_configured_encoder

log = logging.getLogger("usvc")
register_configs()


def focal_range(K: np.ndarray) -> list[float]:
    """[low, high] of the mapping cameras' focal lengths over their long side (2 x the principal
    point's larger coordinate: prepared images are centred), from the SfM intrinsics (N,3,3): the
    relocalizer refuses a photo whose estimated focal length is far outside it."""
    K = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
    ratios = np.sqrt(K[:, 0, 0] * K[:, 1, 1]) / (2.0 * np.maximum(K[:, 0, 2], K[:, 1, 2]))
    ratios = ratios[np.isfinite(ratios) & (ratios > 0)]
    if ratios.size == 0:
        raise UsvcError("train: the SfM cameras have no valid intrinsics to record in the map")
    return [round(float(ratios.min()), 4), round(float(ratios.max()), 4)]


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    paths = scene_paths(cfg)
    buffer_file = paths.buffer / "buffer.h5"
    # Every input is read and checked before the long step: the encoder the map will carry must
    # be the one whose features fill the buffer.
    encoder, weights = load_configured_encoder(cfg.model.encoder_width, cfg.model.encoder_weights,
                                               cfg.model.encoder)
    attrs = read_buffer_attrs(buffer_file)
    check_buffer_encoder(buffer_file, attrs, encoder, weights)
    buf = read_buffer(buffer_file)
    heldout_file = paths.buffer / HELDOUT_FILE
    heldout = read_buffer(heldout_file) if heldout_file.is_file() else None
    tracks = read_tracks(paths.sfm / "tracks.h5")
    median_depth = median_scene_depth(tracks)
    head, summary = train_head(buf, median_depth, group_options(cfg, "train"), head_width=cfg.model.head_width,
                               head_blocks=cfg.model.head_blocks, seed=cfg.seed, heldout=heldout)
    metadata = {"scene": cfg.scene.name, "short_side": int(attrs["short_side"]), "median_depth": median_depth,
                "encoder_file": weights.name, "model": cfg.model.name, "method": cfg.method,
                "train": OmegaConf.to_container(cfg.train), "precision": summary["precision"], "seed": cfg.seed,
                "iterations": summary["iterations"], "final_loss": summary["final_loss"],  # no timings: same bytes
                "focal_range": focal_range(tracks.K)}
    out, metrics_path = stage_outputs(cfg, "train", artifact="map")
    with atomic_dir(out) as tmp:
        # The kept keypoints travel with the map: query-time refinement projects them (paper 3.2.2).
        save_map(tmp / "map.pt", Regressor(encoder, head), metadata,
                 keypoints_xyz=buf.keypoint_xyz if buf.has_keypoints else None)
        map_mb = (tmp / "map.pt").stat().st_size / 2**20
    stats = {**summary, "map_megabytes": map_mb, "seconds": time.perf_counter() - t0,
             "peak_memory_mb": peak_memory_mb()}
    write_json(metrics_path, stats)
    log.info("train %s: map %.2f MB, %.1f s", cfg.scene.name, map_mb, stats["seconds"])


if __name__ == "__main__":
    main()
