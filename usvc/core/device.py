"""Where torch runs: one setting (`device`) for every stage that runs a network or a rasteriser
(buffer, train, relocalize, gaussians, render), `usvc localize --device` and
`Relocalizer(device=...)`.

`auto` is CUDA when torch sees a CUDA device, else the CPU; `cpu`, `cuda` and `cuda:N` are used as
given, and a CUDA device that is not there is one clear error. Like `threads`, it is not a DVC
parameter: a map made on a GPU is a valid cache on a CPU machine and the other way round. Each
stage records the device it ran on and its name beside its timings (`<stage>.timing.json`).
Importing this module loads nothing heavy.
"""

from __future__ import annotations

import re
from pathlib import Path

from usvc.core.errors import UsvcError

DEVICE_RULE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")
DEVICE_CHOICES = "auto | cpu | cuda | cuda:N"


def device_problem(setting: object) -> str:
    """Why `setting` is not a device setting ("" when it is one)."""
    if isinstance(setting, str) and DEVICE_RULE.match(setting):
        return ""
    return f"device={setting!r} is not one of {DEVICE_CHOICES}"


def cuda_index(device: str) -> int:
    """The CUDA device a 'cuda' or 'cuda:N' setting names: N, and 0 for 'cuda'."""
    return int(device.split(":", 1)[1]) if ":" in device else 0


def resolve_device(setting: str) -> str:
    """`auto` -> 'cuda' or 'cpu'; 'cpu', 'cuda', 'cuda:N' as given once checked (UsvcError, one line,
    when the CUDA device is not there)."""
    why = device_problem(setting)
    if why:
        raise UsvcError(why)
    import torch

    available = torch.cuda.is_available()
    if setting == "auto":
        return "cuda" if available else "cpu"
    if setting == "cpu":
        return setting
    if not available:
        raise UsvcError(f"device={setting!r}: CUDA is not available to this torch build or machine "
                        "(device=cpu, or auto to use CUDA only where there is one)")
    index = cuda_index(setting)
    if index >= torch.cuda.device_count():
        raise UsvcError(f"device={setting!r}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                        f"cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    return setting


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine() or "unknown CPU"


def device_name(device: str) -> str:
    """What the device is: the CPU's model, or the CUDA card's name."""
    if device == "cpu":
        return _cpu_model()
    import torch

    return torch.cuda.get_device_name(torch.device(device))


def device_record(device: str) -> dict[str, str]:
    """The `device` and `device_name` entries of a stage's timings."""
    return {"device": device, "device_name": device_name(device)}
