"""keep_freed_memory: large blocks come from the heap (no new mapping), and the opt-out."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from maipp_bench.allocator import OPT_OUT_VARIABLE, keep_freed_memory

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")

# Counts the process's memory mappings around a 64 MiB allocation: glibc's default maps
# it apart (one more mapping), the CLIs' setting serves it from the heap.
PROBE = """
import sys
from maipp_bench.allocator import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "apply" else False
maps = lambda: sum(1 for _ in open("/proc/self/maps"))
before = maps()
block = bytearray(64 * 2**20)
print(applied, maps() - before)
"""


def _probe(mode: str) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k != OPT_OUT_VARIABLE}
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    return out[0], int(out[1])


@glibc
def test_large_blocks_come_from_the_heap() -> None:
    assert _probe("default") == ("False", 1)  # the probe sees glibc's own mmap
    applied, new_maps = _probe("apply")
    assert applied == "True" and new_maps == 0


def test_opt_out_variable_is_respected(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(OPT_OUT_VARIABLE, "65536")
    assert keep_freed_memory() is False
