"""The C allocator of a pstoolkit process: keep freed memory for reuse instead of handing it back.

By default glibc serves blocks above a threshold (128 KiB, raised as such blocks are freed) with
fresh ``mmap`` pages and gives freed memory at the top of the heap back to the system. Every new
array of a few MiB then costs a page fault per 4 KiB page on first touch, and the simulator makes
and drops such arrays (event blocks, shadow tables, exposures) by the hundred; on a virtual machine a
fault costs several µs. ``keep_freed_memory`` raises both thresholds, so freed blocks are reused
without faults. The process's resident size then stays near its peak until it exits, which suits a
command-line run, so the CLI sets it at start (``pstoolkit.cli.main``) and a library import does not.
"""

from __future__ import annotations

import ctypes
import sys

# mallopt(3) parameters and the values set: blocks up to MMAP_THRESHOLD_BYTES come from the heap, and
# the heap's free top is kept up to TRIM_THRESHOLD_BYTES
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 256 << 20
TRIM_THRESHOLD_BYTES = 1 << 30


def keep_freed_memory() -> bool:
    """Set glibc's ``mallopt`` thresholds as the module docstring says; True where they were set
    (glibc on Linux), False elsewhere (nothing changed)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        # the process's own symbols, which hold the C library's: ctypes.util.find_library would run
        # ldconfig in a subprocess (about 4 ms at every start of the CLI)
        mallopt = ctypes.CDLL(None).mallopt
    except AttributeError:  # a C library without mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    mapped = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    return mapped and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
