"""The model's user-facing error, so stages report bad weight or map files in one line."""

from usvc.core.errors import UsvcError


class ModelError(UsvcError):
    """Encoder weights or a scene map cannot be used: the message names the file and the fault."""


def first_line(exc: BaseException) -> str:
    """`Type: first line of the message` of an exception, for one-line error reports."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
