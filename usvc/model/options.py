"""Options of the network: encoder and head (the `model` config group)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from usvc.core.options import non_negative, one_of, positive

ENCODERS = ("ace", "xfeat")


@dataclass
class ModelOptions:
    """The network: encoder and head. The defaults are the ACE-architecture encoder (width 1.0)
    shipped in usvc/weights (encoder_weights: null uses it); set encoder_weights=<path> to use another
    file with the same layout (e.g. ACE's published one)."""

    name: str = "default"  # the model's name in the map's metadata
    encoder: str = "ace"  # ace: the ACE-layout encoder (shipped, or encoder_weights) | xfeat: XFeat's backbone
    encoder_width: float = 1.0  # channel multiplier of the ace encoder (unused by xfeat); 0.5 is model=small
    encoder_weights: Optional[str] = None  # encoder file (a bare name: one shipped in usvc/weights); null = the encoder shipped for this width
    head_width: int = 512  # channels of the regression head's layers
    head_blocks: int = 1  # residual blocks after the first
    max_short_side: int = 192  # larger images are scaled down to this short side (the shipped encoders learned at 240: 192 gives each cell more context); 0 = never; buffer.short_side wins when set

    def problems(self) -> list[str]:
        out = one_of(self, "encoder", ENCODERS) + positive(self, "encoder_width", "head_width")
        return out + non_negative(self, "head_blocks", "max_short_side")
