"""Keep freed memory in the process heap, so XLA's buffers are not paged in again on every call.

XLA's CPU runtime `malloc`s a compiled program's temporary buffers on every call and frees
them afterwards. glibc serves a large request (above a threshold that adapts up to 32 MiB)
with a fresh `mmap` and unmaps it when it is freed, and it returns free memory at the top of
the heap to the kernel once more than the trim threshold has gathered there. Either way the
next call touches pages the kernel must map and zero again, one fault per 4 KiB page. On the
2-core CI machine a jitted 512² night-eye raster (`invglare bench`, case `eye_raster`) took
9 300 page faults and 28 ms of system time per call, out of 42 ms; with both thresholds
raised it took none, and 26 ms.

The cost is that the heap keeps its high-water mark: memory freed by one call is kept for the
next rather than handed back to the system. The ``invglare`` command raises the thresholds
for itself; a program using the library calls :func:`retain_freed_memory` once at start.
"""

from __future__ import annotations

import ctypes
import os
import sys

# mallopt parameter numbers (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: mallopt takes an int: the largest threshold there is (allocations above it still use mmap).
_LARGEST = 2**31 - 1
#: Set to "default" to leave the C library's allocator as it is.
ENV_VAR = "INVGLARE_MALLOC"


def retain_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process; True if both were set.

    Does nothing (and returns False) off Linux, on a C library without glibc's `mallopt`,
    or when the environment variable ``INVGLARE_MALLOC`` is ``default``. Calling it again
    is harmless. See the module docstring for why and what it costs.

    **Example:**

    ```python
    import invglare._core.allocator

    invglare._core.allocator.retain_freed_memory()  # before the first jitted call
    ```
    """
    if not sys.platform.startswith("linux") or os.environ.get(ENV_VAR, "") == "default":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library this process already runs on
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    # Both are needed: with only the mmap threshold raised, freed buffers at the top of the
    # heap are still trimmed; with only the trim threshold, large buffers are still mmapped.
    mmap_ok = mallopt(_M_MMAP_THRESHOLD, _LARGEST) == 1
    trim_ok = mallopt(_M_TRIM_THRESHOLD, _LARGEST) == 1
    return mmap_ok and trim_ok
