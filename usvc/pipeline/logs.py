"""Third-party logging: quiet unless asked for."""

from __future__ import annotations


def quiet_third_party(verbose: bool = False) -> None:
    """COLMAP's per-image INFO lines (glog) only when asked for (``--verbose``, ``hydra.verbose=true``)."""
    import pycolmap

    pycolmap.logging.minloglevel = 0 if verbose else 1  # 1: warnings and errors


def script_logging(verbose: bool = False) -> None:
    """Logging for a script run from the command line (benchmarks): ours at INFO, third parties quiet."""
    import logging

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    quiet_third_party(verbose)
