"""Encoder weights shipped with usvc, produced by `usvc pretrain-encoder` (see the JSON beside each).

`model.encoder_weights` may point elsewhere, e.g. at ACE's published `ace_encoder_pretrained.pt`.
"""

from __future__ import annotations

from pathlib import Path

from usvc.core.errors import UsvcError

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
    """The configured weights file, or the shipped one for `width` when none is configured.

    A bare file name (no folder) that is not a file in the working directory names a file shipped
    in this folder, e.g. `encoder_small_real.pt` (`model=small_real`)."""
    if not weights:
        return shipped_encoder_path(width)
    path = Path(weights)
    if path.parent == Path(".") and not path.exists() and (WEIGHTS_DIR / path.name).is_file():
        return WEIGHTS_DIR / path.name
    return path


def load_configured_encoder(width: float, weights: str | Path | None, kind: str = "ace"):
    """(frozen encoder, its weights path) for a `model` config: the one place stages and the
    relocalizer resolve it. `kind` is `model.encoder`: ace (ACE layout, at `width`) or xfeat."""
    from usvc.model.encoder import load_encoder_weights

    if kind == "xfeat":
        from usvc.model.xfeat_encoder import load_xfeat_encoder, shipped_xfeat_weights

        path = Path(weights) if weights else shipped_xfeat_weights()
        return load_xfeat_encoder(path), path
    if kind != "ace":
        raise UsvcError(f"unknown encoder kind {kind!r} (known: ace, xfeat)")
    path = encoder_weights_path(width, weights)
    return load_encoder_weights(path, width=width), path
