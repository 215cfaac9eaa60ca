"""Keep freed memory in the process on glibc, so that CPU generation stops page-faulting.

PyTorch's CPU allocator hands every tensor to `malloc`. Generation frees and re-allocates
multi-megabyte activations thousands of times per batch, and glibc's defaults give such
blocks back to the kernel (blocks above the mmap threshold are unmapped on `free`, and the
heap top is trimmed); the next allocation then page-faults on every 4 KiB page it touches.
On this project's 2-core machine that costs ~15 % of a bf16 batch-32 generation
(tools/bench_generate.py, `--default-allocator` to compare). Raising both thresholds keeps
those pages mapped and reused: the resident memory stays at its peak instead of shrinking.

The setting is process-wide, so the library never applies it on import; the `segmo`
commands that generate, the benchmark and `SegMo` users who want it call
`keep_freed_memory()` once.
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt parameters (glibc <malloc.h>).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# glibc refuses an mmap threshold above HEAP_MAX_SIZE / 2 = 32 MiB on 64-bit systems.
MMAP_THRESHOLD = 32 * 1024 * 1024
TRIM_THRESHOLD = 256 * 1024 * 1024


def keep_freed_memory() -> bool:
    """Ask glibc to keep freed blocks of up to 32 MiB (and up to 256 MiB at the heap top)
    for reuse. True when both settings took effect; False where the C library is not
    glibc (macOS, musl, Windows), which changes nothing."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt if name else None
    except (OSError, AttributeError):
        mallopt = None
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
            and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1)
