"""The model's user-facing error, so stages report bad weight or map files in one line."""

from usvc.core.errors import UsvcError


class ModelError(UsvcError):
    """Encoder weights or a scene map cannot be used: the message names the file and the fault."""
