"""jaxnm.runtime: process-wide settings (each checked in a fresh process)."""

import os
import subprocess
import sys

import numpy as np
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

for mb in (16, 100):
    n = mb << 20
    p = libc.malloc(n)
    ctypes.memset(p, 1, n)  # touched: resident
    before = resident()
    libc.free(p)
    print("RELEASED", mb, before - resident())
"""

# A jitted program whose temporaries (~80 MB: several 10M-float intermediates) are more than
# a worker thread's heap can hold; prints the minor page faults of its third call. Each
# call's result is deleted before the next call: left to the garbage collector, it was at
# times still held when the next call allocated, which then grew the heap by ~80 MB of
# fresh pages (one probe in ten, keep mode; none in 25 with the explicit delete).
_FAULT_PROBE = """
import resource, sys
from jaxnm import runtime
if sys.argv[1] == "keep":
    assert runtime.keep_freed_memory() is True
import jax, jax.numpy as jnp
f = jax.jit(lambda x: jnp.cumsum(jnp.sin(x)) * jnp.cumsum(jnp.cos(x))[::-1])
x = jnp.linspace(0.0, 1.0, 10_000_000)
faults = []
for _ in range(7):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    f(x).block_until_ready().delete()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
# the median of the calls after two: kept, the heap still grows in some processes on the
# second call, and now and then a later call faults a part of it in again (1 process in
# ~15 on the 2-core VM), while by default every call faults every page
print("FAULTS", sorted(faults[2:])[2])
"""


def _run(probe: str, mode: str, **env: str) -> str:
    return subprocess.run([sys.executable, "-c", probe, mode], capture_output=True,
                          text=True, timeout=120, check=True,
                          env={**os.environ, **env}).stdout


def _glibc_only():
    from jaxnm.runtime import _libc_function

    if not sys.platform.startswith("linux") or _libc_function("mallopt") is None:
        pytest.skip("glibc's allocator")


def test_keep_freed_memory_keeps_freed_buffers_resident():
    """By default glibc maps a 16 or 100 MiB buffer on its own and unmaps it when freed (the
    next buffer of that size is page-faulted in again); after `keep_freed_memory` it comes
    from the heap and stays resident for reuse."""
    _glibc_only()

    def released(mode):
        lines = [ln.split() for ln in _run(_ALLOC_PROBE, mode).splitlines()
                 if ln.startswith("RELEASED")]
        return {int(mb): int(n) for _, mb, n in lines}

    default, keep = released("default"), released("keep")
    assert default[16] >= 15 << 20 and default[100] >= 99 << 20
    assert keep[16] < 1 << 20 and keep[100] < 1 << 20


def test_keep_freed_memory_spares_a_programs_page_faults():
    """A jitted program's ~80 MB of temporaries: page-faulted in on every call by default
    (XLA allocates them in a worker thread, whose heap cannot hold them), not after
    `keep_freed_memory` (the program runs in the calling thread, from the main heap).
    On the CPU backend, whatever JAX would pick (a GPU holds its temporaries on the card:
    no host page faults either way)."""
    _glibc_only()

    def faults(mode):
        return int(_run(_FAULT_PROBE, mode, JAX_PLATFORMS="cpu").split("FAULTS")[1])

    default, keep = faults("default"), faults("keep")
    assert default > 10_000  # ~80 MB of 4 KiB pages
    assert keep < default / 20


def test_keep_freed_memory_leaves_the_dispatch_unless_asked_in_time():
    """JAX's CPU dispatch stays asynchronous with the env switch off, with
    ``run_in_caller=False``, and when called after the backend is up (with a warning)."""
    probe = """
import os, sys, warnings
import jax, jax.numpy as jnp
from jaxnm import runtime
if sys.argv[1] == "env-off":
    os.environ[runtime.MEMORY_ENV] = "off"
    assert runtime.keep_freed_memory_unless_disabled() is False
elif sys.argv[1] == "heap-only":
    assert runtime.keep_freed_memory(run_in_caller=False) is True
else:
    jnp.ones(3).block_until_ready()  # the backend is up: too late for the dispatch
    assert runtime.keep_freed_memory_unless_disabled() is False  # quietly left alone
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert runtime.keep_freed_memory() is False
    assert any("before the first JAX computation" in str(x.message) for x in w), w
print("ASYNC", jax.config.values["jax_cpu_enable_async_dispatch"])
"""
    for mode in ("env-off", "heap-only", "late"):
        assert "ASYNC True" in _run(probe, mode), mode


def test_keep_freed_memory_rejects_a_bad_threshold():
    from jaxnm.runtime import keep_freed_memory

    for bad in (-1, 1.5, "256"):
        with pytest.raises(ValueError, match="non-negative int"):
            keep_freed_memory(trim_threshold_mb=bad)


def test_gpu_flags_are_added_once_and_accepted_by_xla():
    """`use_gpu_graphs` and `use_deterministic_ops` each add their flag once, keep the
    flags already set, and XLA accepts them (it aborts on an unknown command-buffer kind)."""
    probe = """
import os
from jaxnm import runtime
runtime.use_gpu_graphs(); runtime.use_gpu_graphs(); runtime.use_deterministic_ops()
import jax, jax.numpy as jnp
print("SUM", float(jax.jit(lambda x: jnp.sin(x).sum())(jnp.ones(4))))
print("FLAGS", os.environ["XLA_FLAGS"])
"""
    out = _run(probe, "", XLA_FLAGS="--xla_gpu_deterministic_ops=true")
    flags = out.split("FLAGS")[1].split()
    assert sorted(flags) == sorted(["--xla_gpu_deterministic_ops=true",
                                    "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,"
                                    "CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"])
    assert abs(float(out.split("SUM")[1].split()[0]) - 4 * 0.8414709848) < 1e-5


def test_deterministic_ops_reads_the_flag(monkeypatch):
    from jaxnm import runtime

    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_deterministic_ops=false")
    assert not runtime.deterministic_ops()
    monkeypatch.setenv("XLA_FLAGS", "--foo " + runtime.DETERMINISTIC_FLAG)
    assert runtime.deterministic_ops()
    monkeypatch.delenv("XLA_FLAGS")
    assert not runtime.deterministic_ops()


_PIN_PROBE = """
import json, os, sys
from jaxnm import runtime
n = runtime.pin_worker_threads()
import jax, jax.numpy as jnp
assert float(jax.jit(lambda x: jnp.sum(x * 2))(jnp.ones(8))) == 16.0
workers = [int(t) for t in os.listdir("/proc/self/task")
           if open(f"/proc/self/task/{t}/comm").read().startswith("tf_XLAEigen")]
print("PINNED", json.dumps({"returned": n, "workers": [sorted(os.sched_getaffinity(t))
      for t in workers], "process": sorted(os.sched_getaffinity(0))}))
"""


def _pin_probe(**env: str) -> dict:
    import json

    out = _run(_PIN_PROBE, "", **env)
    return json.loads(out.split("PINNED ", 1)[1])


def test_pin_worker_threads_puts_each_worker_on_a_core_of_its_own():
    if not sys.platform.startswith("linux"):
        pytest.skip("thread affinity through /proc and sched_setaffinity")
    r = _pin_probe()
    workers, cpus = r["workers"], set(r["process"])
    assert workers, "no XLA worker threads found"
    if len(workers) > len(cpus):
        assert r["returned"] == 0 and all(set(w) == cpus for w in workers)
        return
    assert r["returned"] == len(workers)
    assert all(len(w) == 1 and set(w) <= cpus for w in workers)
    assert len({w[0] for w in workers}) == len(workers)  # distinct cores
    # the process itself (its main thread, threads started later) keeps the cores it had
    assert cpus == os.sched_getaffinity(0)


def test_pin_worker_threads_can_be_turned_off():
    if not sys.platform.startswith("linux"):
        pytest.skip("thread affinity through /proc and sched_setaffinity")
    r = _pin_probe(JAXNM_PIN_THREADS="off")
    assert r["returned"] == 0
    assert all(set(w) == set(r["process"]) for w in r["workers"])


_VECTORS_PROBE = """
import json, os, sys
import numpy as np
from jaxnm import runtime
if sys.argv[1] == "late":
    import jax
    jax.numpy.ones(2).block_until_ready()  # the backend has started
calls = [runtime.use_wide_vectors(), runtime.use_wide_vectors()]
if sys.argv[1] == "early":  # (the late probe only checks the flags)
    import jaxnm
    from jaxnm.procedural import default_scene
    out = jaxnm.render(default_scene(width=96, height=96),
                       outputs=("triangle_id", "depth", "uv", "normal", "color"))
    np.savez(sys.argv[2], **{k: np.asarray(v) for k, v in out.items()})
print("RESULT", json.dumps({"calls": calls, "flags": os.environ.get("XLA_FLAGS", "").split()}))
"""


def _vectors_probe(mode: str, path, **env: str) -> dict:
    import json

    env = {"XLA_FLAGS": "", **env}
    out = _run(_VECTORS_PROBE.replace("sys.argv[2]", repr(str(path))), mode, **env)
    return json.loads(out.split("RESULT", 1)[1])


def test_wide_vectors_change_nothing_but_the_last_bits(tmp_path):
    """`use_wide_vectors` adds its flag once, before JAX starts, where the CPU has AVX-512
    (not once JAX has started, nor with ``$JAXNM_WIDE_VECTORS=off``); XLA accepts it, and
    a frame rendered with it has the same triangle ids, depth and uv as one without,
    normals within 4 float32 ulps and colours within what that makes of the highlight."""
    from jaxnm.runtime import WIDE_VECTORS_FLAG, _has_avx512

    wide = _vectors_probe("early", tmp_path / "wide.npz")
    off = _vectors_probe("early", tmp_path / "off.npz", JAXNM_WIDE_VECTORS="off")
    late = _vectors_probe("late", tmp_path / "late.npz")
    assert off == {"calls": [False, False], "flags": []}
    assert late == {"calls": [False, False], "flags": []}
    if not _has_avx512():
        assert wide == {"calls": [False, False], "flags": []}
        pytest.skip("no AVX-512 on this CPU: the flag is not added")
    assert wide == {"calls": [True, True], "flags": [WIDE_VECTORS_FLAG]}
    a, b = np.load(tmp_path / "wide.npz"), np.load(tmp_path / "off.npz")
    for name in ("triangle_id", "depth", "uv"):
        assert np.array_equal(a[name], b[name]), name
    assert (a["triangle_id"] >= 0).sum() > 1000  # the torus fills much of the frame
    ulp = np.spacing(np.float32(1.0))
    assert np.max(np.abs(a["normal"] - b["normal"])) <= 4 * ulp
    # Blinn-Phong's highlight (shininess 48) scales a normal's change by up to 48x
    assert np.max(np.abs(a["color"] - b["color"])) <= 4 * 48 * ulp
