"""Process settings for training on a CPU: the allocator's reuse of freed tensor memory.

(The OpenMP wait policy is the other one; it must be in the environment before torch is imported, so the entry point
sets it on its first lines.)
"""

from __future__ import annotations

import ctypes
import os

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD = 32 * 2**20  # glibc's largest accepted value on 64-bit
_TRIM_THRESHOLD = 2**31 - 1


def reuse_freed_memory() -> bool:
    """Serve blocks up to 32 MB from the heap and never trim it (glibc), so a tensor freed in one training step is
    reused by the next instead of being unmapped and faulted in again page by page: measured 12-16k fewer page faults
    per torch_ref forward+backward at 30k@256 and 5-10 % shorter medians on a 2-core VM. Peak memory is unchanged;
    the process keeps its high-water mark instead of returning it between steps.

    `SPLATRIG_MALLOC=system` in the environment keeps glibc's defaults. Returns whether the setting was applied
    (False off glibc)."""
    if os.environ.get("SPLATRIG_MALLOC", "").lower() == "system":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))
