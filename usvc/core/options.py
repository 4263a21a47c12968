"""Checks shared by the options dataclasses of every step: each `problems()` returns one line per
value outside what its step accepts (the config composer prefixes the group: `train.lr=0 must be > 0`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


def one_of(opts: Any, name: str, choices: Iterable[Any]) -> list[str]:
    value, allowed = getattr(opts, name), tuple(choices)
    return [] if value in allowed else [f"{name}={value!r} is not one of {list(allowed)}"]


def positive(opts: Any, *names: str) -> list[str]:
    return [f"{n}={getattr(opts, n)!r} must be > 0" for n in names if not getattr(opts, n) > 0]


def non_negative(opts: Any, *names: str) -> list[str]:
    return [f"{n}={getattr(opts, n)!r} must be >= 0" for n in names if getattr(opts, n) < 0]


def in_range(opts: Any, name: str, low: float, high: float, high_open: bool = False) -> list[str]:
    value = getattr(opts, name)
    ok = low <= value < high if high_open else low <= value <= high
    return [] if ok else [f"{name}={value!r} must be in [{low:g}, {high:g}{')' if high_open else ']'}"]


def ordered(opts: Any, low: str, high: str) -> list[str]:
    a, b = getattr(opts, low), getattr(opts, high)
    return [] if a <= b else [f"{low}={a!r} exceeds {high}={b!r}"]


def check(opts: Any, group: str) -> None:
    """Raise one UsvcError listing every value `opts` (a step's options) does not accept."""
    from usvc.core.errors import UsvcError

    problems = opts.problems()
    if problems:
        raise UsvcError("; ".join(f"{group} option {p}" for p in problems))
