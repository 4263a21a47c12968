"""Writing an encoder weight file the same way ACE's is laid out, plus a provenance record.

The state dict is plain tensors (loadable with `weights_only=True`, strict keys) stored in fp16
to halve the file; loading casts back to fp32. The JSON beside it says how it was made.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from usvc.core.atomic import atomic_file
from usvc.model.encoder import Encoder, encoder_fingerprint


def save_encoder_weights(path: Path, encoder: Encoder, provenance: dict[str, Any]) -> dict[str, Any]:
    path = Path(path)
    state = {k: v.detach().to("cpu", torch.float16).clone() for k, v in encoder.state_dict().items()}
    with atomic_file(path) as tmp:
        torch.save(state, tmp)
    # The fingerprint is of the weights as they will be loaded (fp16-rounded, then fp32).
    reloaded = Encoder(encoder.width)
    reloaded.load_state_dict(state, strict=True)
    record = {**provenance, "file": path.name, "width": encoder.width,
              "fingerprint": encoder_fingerprint(reloaded),
              "parameters": int(sum(p.numel() for p in encoder.parameters())),
              "megabytes": round(path.stat().st_size / 2**20, 2)}
    with atomic_file(path.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(record, indent=2) + "\n")
    return record
