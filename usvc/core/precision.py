"""Arithmetic precision of the network's matrix products: `auto | bf16 | fp32`.

`bf16` runs the encoder's and the head's layers under `torch.autocast` with bfloat16 (products of
bf16 inputs accumulated in fp32, results rounded to bf16); what needs fp32 stays fp32: the head's
last layer output is cast back before the homogeneous division, the losses, the division by depth,
the optimizer's state and the master weights (autocast casts copies), and PnP's inputs.

`auto` picks bf16 only where it is native and measured faster:

- CUDA: the device supports bf16 (`torch.cuda.is_bf16_supported()`);
- CPU: the processor has AVX512-BF16 or AMX (asked of torch's CPU feature checks, or the kernel's
  flags where torch has no such check), and a one-time probe on this machine (bf16 against fp32
  products at the head's shape, once per process) finds bf16 at least `PROBE_MIN_SPEEDUP` times
  faster. Without native bf16, torch emulates it: about 20x slower than fp32 on an AVX2-only CPU,
  so `auto` never picks it there and the probe is not even run.

The decision is made by capability first, so a machine without native bf16 always resolves `auto`
to fp32, whatever the timing noise; the probe only guards against a CPU that reports the flag but
runs bf16 slowly (a hypervisor, an old oneDNN).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from collections.abc import Iterator
from pathlib import Path

PRECISIONS = ("auto", "bf16", "fp32")
PROBE_MIN_SPEEDUP = 1.3  # bf16 must beat fp32 by this factor at the head's shape for `auto`
_CPU_FLAGS = ("avx512_bf16", "amx_bf16")

log = logging.getLogger(__name__)


def _cpuinfo_flags() -> set[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def cpu_has_native_bf16() -> bool:
    """AVX512-BF16 or AMX on this CPU (torch's own checks, else the kernel's CPU flags)."""
    import torch

    checks = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    if all(callable(c) for c in checks):
        return any(bool(c()) for c in checks)
    return bool(_cpuinfo_flags() & set(_CPU_FLAGS))


def product_seconds(dtype, reps: int = 8, rows: int = 3072, width: int = 256, blocks: int = 3) -> float:
    """Seconds of `reps` (rows x width) by (width x width) products in `dtype`: the fastest of
    `blocks` runs (a peak, so that a neighbour's burst on a shared machine does not lower it)."""
    import torch

    gen = torch.Generator().manual_seed(0)
    a = torch.randn(rows, width, generator=gen).to(dtype)
    b = torch.randn(width, width, generator=gen).to(dtype)
    a @ b  # warm-up: oneDNN picks and caches its kernel
    best = float("inf")
    for _ in range(blocks):
        t0 = time.perf_counter()
        for _ in range(reps):
            a @ b
        best = min(best, time.perf_counter() - t0)
    return best


@functools.lru_cache(maxsize=1)
def cpu_bf16_speedup() -> float:
    """fp32 time / bf16 time of a 3,072 x 256 by 256 x 256 product on this CPU (measured once per
    process, best of three; about 50 ms)."""
    import torch

    speedup = product_seconds(torch.float32) / product_seconds(torch.bfloat16)
    log.debug("bf16 probe: %.2fx the fp32 product rate", speedup)
    return speedup


def resolve_precision(setting: str, device: str = "cpu") -> str:
    """`auto` -> 'bf16' or 'fp32' for `device` (see the module doc); 'bf16' and 'fp32' as given."""
    if setting not in PRECISIONS:
        raise ValueError(f"precision={setting!r} is not one of {list(PRECISIONS)}")
    if setting != "auto":
        return setting
    import torch

    kind = torch.device(device).type
    if kind == "cuda":
        return "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "fp32"
    if kind != "cpu" or not cpu_has_native_bf16():
        return "fp32"
    return "bf16" if cpu_bf16_speedup() >= PROBE_MIN_SPEEDUP else "fp32"


@contextlib.contextmanager
def autocast(precision: str, device: str = "cpu", cache: bool = True) -> Iterator[None]:
    """Run the enclosed layers at `precision` ('bf16' or 'fp32', as `resolve_precision` returns).
    `cache=False` for a region captured as a CUDA graph (autocast's weight cache must not be)."""
    import torch

    if precision not in ("bf16", "fp32"):
        raise ValueError(f"resolve precision={precision!r} first (bf16 or fp32)")
    with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=precision == "bf16",
                        cache_enabled=cache):
        yield
