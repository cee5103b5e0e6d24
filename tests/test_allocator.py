"""keep_freed_memory: large blocks come from the heap (not mmapped), and the opt-out."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from maipp_bench.allocator import OPT_OUT_VARIABLE, keep_freed_memory

_LIBC, _VERSION = platform.libc_ver()
glibc = pytest.mark.skipif(
    _LIBC != "glibc" or tuple(int(v) for v in _VERSION.split(".")[:2]) < (2, 33),
    reason="glibc >= 2.33 (mallopt, mallinfo2)")

# glibc's own account of the bytes it holds in mmapped blocks (mallinfo2's hblkhd) around
# a 64 MiB allocation: the default maps such a block apart, the CLIs' setting serves it
# from the heap.
PROBE = """
import ctypes, sys
from maipp_bench.allocator import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "apply" else False
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks",
                "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
mallinfo2 = ctypes.CDLL(None).mallinfo2
mallinfo2.restype = Info
before = mallinfo2().hblkhd
block = bytearray(64 * 2**20)
print(applied, (mallinfo2().hblkhd - before) // 2**20)
"""


def _probe(mode: str) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k != OPT_OUT_VARIABLE}
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    return out[0], int(out[1])


@glibc
def test_large_blocks_come_from_the_heap() -> None:
    assert _probe("default") == ("False", 64)  # glibc maps the 64 MiB block apart
    assert _probe("apply") == ("True", 0)  # kept: served from the heap


def test_opt_out_variable_is_respected(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(OPT_OUT_VARIABLE, "65536")
    assert keep_freed_memory() is False
