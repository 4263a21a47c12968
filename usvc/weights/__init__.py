"""Encoder weights shipped with usvc, produced by `usvc pretrain-encoder` (see the JSON beside each).

`model.encoder_weights` may point elsewhere, e.g. at ACE's published `ace_encoder_pretrained.pt`.
"""

from __future__ import annotations

from pathlib import Path

from usvc.errors import UsvcError

WEIGHTS_DIR = Path(__file__).resolve().parent
SHIPPED = {1.0: "encoder_default.pt", 0.5: "encoder_small.pt"}


def shipped_encoder_path(width: float) -> Path:
    name = SHIPPED.get(float(width))
    if name is None:
        raise UsvcError(f"no shipped encoder has width {width:g} (shipped: {sorted(SHIPPED)}); "
                        "pass the encoder weights file explicitly")
    path = WEIGHTS_DIR / name
    if not path.is_file():
        raise UsvcError(f"shipped encoder {path} is missing; rebuild it with "
                        f"`usvc pretrain-encoder --width {width:g} --out {path}` (see README)")
    return path


def encoder_weights_path(width: float, weights: str | Path | None) -> Path:
    """The configured weights file, or the shipped one for `width` when none is configured."""
    return Path(weights) if weights else shipped_encoder_path(width)


def load_configured_encoder(width: float, weights: str | Path | None):
    """(frozen Encoder, its weights path) for a `model` config: the one place stages resolve it."""
    from usvc.model.encoder import load_encoder_weights

    path = encoder_weights_path(width, weights)
    return load_encoder_weights(path, width=width), path
