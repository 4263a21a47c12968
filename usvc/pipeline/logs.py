"""Third-party logging: quiet unless asked for."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any


def quiet_third_party(verbose: bool = False) -> None:
    """COLMAP's per-image INFO lines (glog) only when asked for (``--verbose``, ``hydra.verbose=true``)."""
    import pycolmap

    pycolmap.logging.minloglevel = 0 if verbose else 1  # 1: warnings and errors


def script_logging(verbose: bool = False) -> None:
    """Logging for a script run from the command line (benchmarks): ours at INFO, third parties quiet."""
    import logging

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    quiet_third_party(verbose)
    sys.excepthook = _one_line_for_usvc_errors


def _one_line_for_usvc_errors(kind: type[BaseException], error: BaseException, trace: Any) -> None:
    """A script's bad input (a UsvcError: what is wrong and where) as one line, not a traceback; the
    exit status stays 1. Anything else as Python prints it."""
    from usvc.core.errors import UsvcError

    if isinstance(error, UsvcError):
        print(f"{Path(sys.argv[0]).name}: {error}", file=sys.stderr)
        return
    sys.__excepthook__(kind, error, trace)
