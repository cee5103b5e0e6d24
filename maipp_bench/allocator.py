"""Keep freed memory in the process: the CLIs' fix for glibc's page-fault storm.

glibc serves every allocation above its mmap threshold (32 MiB at most) with a fresh
``mmap`` and gives it back with ``munmap`` on free. TI rollouts and large env batches
allocate and free activations of 50-150 MiB many times per second, so the kernel zeroes
and maps every page of them again each time: on the 2-core box, TI evaluation spent
nearly half its wall time in the kernel (``sys`` 44 s of 94 s for 30 episodes). Serving large
blocks from the heap and never trimming it lets freed blocks be reused; the arithmetic
is untouched, so results stay bit-identical (``benchmarks/allocator.py`` measures it).

The CLIs (``maipp_bench.eval``, ``maipp_bench.train``) and the workload benchmarks
(``paired_subset.py``, ``train_throughput.py``) call :func:`keep_freed_memory` at start;
importing the package changes nothing. The price: a process keeps its peak memory until
it exits (freed blocks are kept for reuse, not given back). Users opt out by setting
glibc's own ``MALLOC_MMAP_MAX_`` in the environment (which is then respected, e.g.
``MALLOC_MMAP_MAX_=65536`` restores the default); other glibc tunables set by the user
(``MALLOC_TRIM_THRESHOLD_``, ``GLIBC_TUNABLES``) are overridden unless it is set too.
"""

from __future__ import annotations

import ctypes
import os

# mallopt(3) parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_THRESHOLD = 2**31 - 1  # an int; the heap's top is given back only past 2 GiB
OPT_OUT_VARIABLE = "MALLOC_MMAP_MAX_"


def keep_freed_memory() -> bool:
    """Serve large blocks from the heap and keep freed memory for reuse (glibc only).

    Returns True when applied; False where there is no glibc ``mallopt`` (macOS,
    Windows, musl) or the user set ``MALLOC_MMAP_MAX_``. Idempotent; it affects this
    process and its forked children (spawned children call it themselves).
    """
    if OPT_OUT_VARIABLE in os.environ:
        return False
    try:  # the C library this process already runs on (no ldconfig lookup)
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mallopt returns 1 on success, 0 on error.
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))
