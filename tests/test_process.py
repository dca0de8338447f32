"""A library leaves the process alone: importing jaxnm, rendering and fitting change none of
the process's settings (checked in a fresh process, against its own state before)."""

import json
import subprocess
import sys
from pathlib import Path

# Records the process state, runs jaxnm (import, a render, a fit), records it again, and
# then checks glibc's allocator by behaviour: a freed 100 MB block (beyond glibc's largest
# dynamic mmap threshold, 32 MB) goes back to the system unless someone told the allocator
# to keep it (`mallopt(M_MMAP_MAX, 0)` would).
_PROBE = r"""
import json, os, signal, sys, threading

def state():
    tasks = sorted(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else []
    affinity = {}
    for tid in tasks:
        try:
            affinity[tid] = sorted(os.sched_getaffinity(int(tid)))
        except OSError:  # a thread that ended meanwhile
            pass
    return {"xla_flags": os.environ.get("XLA_FLAGS"),
            "sigint": repr(signal.getsignal(signal.SIGINT)),
            "sigterm": repr(signal.getsignal(signal.SIGTERM)), "affinities": affinity}

before = state()
process_cpus = sorted(os.sched_getaffinity(0))
import jax
jax_config = lambda: {k: jax.config.values.get(k, "<absent>") for k in (
    "jax_cpu_enable_async_dispatch", "jax_compilation_cache_dir", "jax_enable_compilation_cache",
    "jax_persistent_cache_min_compile_time_secs", "jax_enable_x64")}
config_before = jax_config()

import jaxnm
from jaxnm.fit import FitOptions
after_import = state()
scene = jaxnm.default_scene(width=64, height=64)
jaxnm.render(scene)["color"].block_until_ready()
problem, gt, _ = jaxnm.default_problem(render_size=64, map_size=16, views=1)
res = jaxnm.fit_normal_map(problem, FitOptions(max_steps=2), progress=False)
after = state()

import ctypes
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
n = 100 << 20
p = libc.malloc(n)
ctypes.memset(p, 1, n)
held = resident()
libc.free(p)
released = held - resident()
print("RESULT " + json.dumps({
    "before": before, "after_import": after_import, "after": after,
    "process_cpus": process_cpus, "config_before": config_before, "config_after": jax_config(),
    "released_mb": released / 2**20, "steps": len(res.history)}))
"""


def test_import_render_and_fit_leave_the_process_alone():
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                         timeout=300, check=True).stdout
    r = json.loads(out.split("RESULT ", 1)[1])
    assert r["steps"] >= 2  # the fit ran
    for when in ("after_import", "after"):
        for key in ("xla_flags", "sigint", "sigterm"):
            assert r[when][key] == r["before"][key], (when, key)
        # every thread, JAX's workers included, free to run on every core of the process
        assert r[when]["affinities"], when
        for tid, cpus in r[when]["affinities"].items():
            assert cpus == r["process_cpus"], (when, tid, cpus)
    assert r["config_after"] == r["config_before"]
    assert r["released_mb"] > 90  # the allocator still hands large blocks back


def test_the_library_does_not_reach_into_jax_internals_or_the_process():
    """No ``jax._src`` import, no allocator, signal, affinity or XLA-flag call in the library
    (the command line, `jaxnm.cli`, may opt in to what it documents: deterministic GPU ops,
    its SIGINT handler, and handing freed memory back between its phases)."""
    root = Path(__file__).resolve().parents[1] / "jaxnm"
    forbidden = ("jax._src", "mallopt", "malloc_trim", "sched_setaffinity", "signal.signal",
                 "os.environ[", "os.environ.update", "putenv")
    found = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        for word in forbidden:
            if word in text and not ("cli" in path.parts and word in (
                    "os.environ[", "signal.signal", "malloc_trim")):
                found.append(f"{path.relative_to(root.parent)}: {word}")
    assert found == []
