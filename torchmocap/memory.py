"""Memory a computation needs, checked before it starts.

A setting that asks for more memory than the machine has (``tracker.num_particles=1000000000``,
a clip resampled to a million frames per second) would otherwise fail late: an allocator error
deep in a frame, or — where the system overcommits memory — the kernel's out-of-memory killer
ending the process without a message. The callers estimate what they will hold at least (a
lower bound: the arrays they are sure to allocate) and :func:`check_memory` refuses an estimate
above what is available, naming the setting.

Available memory: on CUDA the device's free memory (``torch.cuda.mem_get_info``); on the CPU
the kernel's ``MemAvailable`` (``/proc/meminfo``), lowered to what a cgroup memory limit leaves
(containers, SLURM jobs), else the free physical pages.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

__all__ = ["MemoryBudgetError", "available_memory", "check_memory", "format_bytes"]


class MemoryBudgetError(ValueError):
    """A setting asks for more memory than is available (names the setting)."""


def format_bytes(n: float) -> str:
    """``n`` bytes as a short decimal size (``64.0 GB``, ``512 MB``)."""
    for unit, f in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= f:
            return f"{n / f:.3g} {unit}"
    return f"{int(n)} B"


def _cgroup_room() -> int | None:
    """Bytes a cgroup (v2 or v1) memory limit leaves this process, or None without one."""
    for limit, usage in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                         ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                          "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            lim = Path(limit).read_text().strip()
            used = int(Path(usage).read_text().strip())
        except (OSError, ValueError):
            continue
        if lim.isdigit() and int(lim) < 1 << 60:  # "max" or a huge number: no limit
            return max(int(lim) - used, 0)
    return None


def available_memory(device: torch.device | str | None = None) -> int:
    """Bytes that can still be allocated on ``device`` (default: the CPU)."""
    dev = torch.device("cpu" if device is None else device)
    if dev.type == "cuda":
        return int(torch.cuda.mem_get_info(dev)[0])
    avail = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return 1 << 62  # unknown: do not refuse
    room = _cgroup_room()
    return avail if room is None else min(avail, room)


def check_memory(nbytes: float, what: str, setting: str,
                 device: torch.device | str | None = None) -> None:
    """Refuse a computation whose arrays need at least ``nbytes`` when fewer are available.

    Args:
        nbytes: the lower bound of what it will hold.
        what: what needs it (``"200000000 particles of 40 DoFs and their forward kinematics"``).
        setting: the setting to change, named first in the message.
        device: where it is allocated.

    Raises:
        MemoryBudgetError: ``nbytes`` exceeds :func:`available_memory`.
    """
    free = available_memory(device)
    if nbytes > free:
        where = "cpu" if device is None else str(device)
        raise MemoryBudgetError(f"{setting}: {what} need at least {format_bytes(nbytes)}, but "
                                f"{format_bytes(free)} are available ({where}); lower it")
