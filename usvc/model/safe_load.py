"""`torch.load` restricted to tensors and plain types, with one-line errors of our own.

Torch's own message for a refused file suggests retrying with ``weights_only=False``, which would
run whatever code the file carries; usvc never relays that advice, and never loads that way.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from usvc.model.errors import ModelError


def load_tensors(path: Path, what: str) -> object:
    """The deserialised content of a torch file (tensors, dicts, lists, numbers, strings only)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: {what} file does not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        if zipfile.is_zipfile(path):
            raise ModelError(f"{path}: refused as {what}: it holds Python objects other than tensors and "
                             "plain values, and loading those could run code") from None
        raise ModelError(f"{path}: cannot read {what}: not a torch file (corrupt, truncated or another format)") from None
    except Exception as exc:  # torch's reader errors (RuntimeError from the zip reader, EOFError, ...)
        raise ModelError(f"{path}: cannot read {what}: the file is corrupt or truncated "
                         f"({type(exc).__name__})") from None
