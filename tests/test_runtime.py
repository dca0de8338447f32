"""jaxnm.runtime: process-wide settings (each checked in a fresh process)."""

import subprocess
import sys

import pytest

_ALLOC_PROBE = """
import ctypes, sys
from jaxnm import runtime
if sys.argv[1] == "keep":
    assert runtime.keep_freed_memory() is True
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]

def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096

n = 16 << 20
p = libc.malloc(n)
ctypes.memset(p, 1, n)  # touched: resident
before = resident()
libc.free(p)
print("RELEASED", before - resident())
"""


def _released(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _ALLOC_PROBE, mode], capture_output=True,
                         text=True, timeout=120, check=True).stdout
    return int(out.split("RELEASED")[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_keep_freed_memory_keeps_a_freed_buffer_resident():
    """By default glibc maps a 16 MiB buffer on its own and unmaps it when freed (the next
    buffer of that size is page-faulted in again); after `keep_freed_memory` it comes from
    the heap and stays resident for reuse."""
    from jaxnm.runtime import _libc_function

    if _libc_function("mallopt") is None:
        pytest.skip("the C library is not glibc")
    assert _released("default") >= 15 << 20
    assert _released("keep") < 1 << 20


def test_keep_freed_memory_rejects_what_glibc_would_not_take():
    from jaxnm.runtime import keep_freed_memory

    with pytest.raises(ValueError, match="32 MiB"):
        keep_freed_memory(mmap_threshold_mb=64)
    with pytest.raises(ValueError, match="non-negative int"):
        keep_freed_memory(top_pad_mb=-1)
