"""Facts about the machine this process runs on (standard library only)."""

from __future__ import annotations

import os
from typing import Iterable


def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware; at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def memory_bytes(field: str) -> int | None:
    """A /proc/meminfo field in bytes (e.g. "MemTotal", "MemAvailable"); None where it cannot be read."""
    try:
        with open("/proc/meminfo", encoding="utf-8") as fh:
            return next(int(line.split()[1]) for line in fh if line.startswith(f"{field}:")) * 1024
    except (OSError, StopIteration, ValueError, IndexError):
        return None


def oversubscription_note(threads: Iterable[int], cores: int | None = None) -> str | None:
    """The sentence that thread counts above the cores here oversubscribe the CPU, or None if none is.

    The one wording of that warning: `bench` adds it to its report, `run` prints it on stderr.
    """
    cores = cores or available_cores()
    over = [n for n in dict.fromkeys(threads) if n > cores]
    if not over:
        return None
    counts = ", ".join(map(str, over))
    if len(over) == 1:
        return f"A thread count above the {cores} cores here ({counts}) oversubscribes the CPU."
    return f"Thread counts above the {cores} cores here ({counts}) oversubscribe the CPU."
