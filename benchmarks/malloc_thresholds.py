"""glibc's allocator thresholds, fixed for a benchmark process (``throughput.py``)."""

from __future__ import annotations

import ctypes
import os

#: glibc mallopt parameters: heap memory above this is not returned to the system; blocks above this come from mmap
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3


def fix_malloc_thresholds(trim: int = 1 << 30, mmap: int = 32 << 20) -> bool:
    """Fix glibc's trim and mmap thresholds for the whole process (``--malloc fixed``).

    By default glibc raises both thresholds as the process frees large blocks, so a process's first training
    run keeps giving memory back and faulting it in again, and the runs after it do not: measured in one
    process, plain PPO's update took 64.3 s when it ran first and 48.1 s when it ran after PPO_GoCu (40,960
    steps; docs/results.md, "What a step costs"). Fixed thresholds give every run the same allocator, in this process and (through
    ``MALLOC_TRIM_THRESHOLD_`` and ``MALLOC_MMAP_THRESHOLD_``) in the processes it starts. :return: whether glibc
    took both settings
    """
    # child processes (PPO_GoCu's worker process) read the same settings from the environment at their start
    os.environ["MALLOC_TRIM_THRESHOLD_"], os.environ["MALLOC_MMAP_THRESHOLD_"] = str(trim), str(mmap)
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(M_TRIM_THRESHOLD, trim)) and bool(libc.mallopt(M_MMAP_THRESHOLD, mmap))
