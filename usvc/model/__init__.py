"""ACE-style scene coordinate regression network: frozen encoder, per-scene head, map files."""

from usvc.model.encoder import (
    OUTPUT_STRIDE,
    Encoder,
    cell_centers,
    encoder_fingerprint,
    encoder_flops,
    load_encoder_weights,
)
from usvc.model.errors import ModelError
from usvc.model.head import (
    Head,
    Regressor,
    homogeneous_scale,
    load_head,
    load_map,
    map_keypoints,
    read_map_header,
    save_map,
)
from usvc.model.preprocess import resize_to_short_side, to_network_input

__all__ = [
    "OUTPUT_STRIDE",
    "Encoder",
    "Head",
    "ModelError",
    "Regressor",
    "cell_centers",
    "encoder_fingerprint",
    "encoder_flops",
    "homogeneous_scale",
    "load_encoder_weights",
    "load_head",
    "load_map",
    "map_keypoints",
    "read_map_header",
    "resize_to_short_side",
    "save_map",
    "to_network_input",
]
