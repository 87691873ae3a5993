"""How much memory a new allocation may take, checked before the allocation is made.

A request that cannot fit (an extraction grid, a frame of 100000 x 100000 pixels) is refused with
one line naming what needs how much, instead of a traceback from the allocator minutes later or the
machine swapping itself to a halt.
"""

from __future__ import annotations

import os

from .errors import EngineError


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable, else free pages), or None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB"


def check_memory(need: float, what: str, advice: str) -> None:
    """EngineError when `need` bytes exceed the memory available now: '<what> needs about N GiB of
    memory, but only M GiB is available: <advice>'. Passes when the available memory is unknown."""
    free = available_memory()
    if free is not None and need > free:
        raise EngineError(f"{what} needs about {gib(need)} of memory, but only {gib(free)} is available: {advice}")
