"""The process around the computation: the persistent compilation cache, deterministic
GPU arithmetic, CUDA graphs for a GPU's loops, handing freed memory back to the system
between phases, and XLA's CPU worker threads each on a core of its own.

These change process-wide state (JAX's configuration, ``XLA_FLAGS``, the C allocator), so
the command line and the scripts call them; a library user opts in. Nothing here changes
a result, except in its last bits where `use_wide_vectors` lets XLA vectorise differently.

XLA's CPU programs allocate their buffers afresh on every call; where glibc hands them back
to the system in between, every call pays the page faults of touching them again.
`keep_freed_memory` tells glibc (at run time, ``mallopt``) to keep them in its heap, and
JAX to run CPU programs in the calling thread, whose heap can hold the largest of them.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

__all__ = ["CACHE_ENV", "DETERMINISTIC_FLAG", "compilation_cache_dir", "use_compilation_cache",
           "use_deterministic_ops", "deterministic_ops", "GRAPHS_FLAG", "use_gpu_graphs",
           "release_memory", "keep_freed_memory", "MEMORY_ENV", "keep_freed_memory_unless_disabled",
           "PIN_ENV", "pin_worker_threads", "WIDE_VECTORS_FLAG", "VECTORS_ENV",
           "use_wide_vectors"]

#: Environment variable naming the cache folder; ``off`` (or empty) turns the cache off.
CACHE_ENV = "JAXNM_COMPILATION_CACHE"

#: The values of jaxnm's environment switches that mean "off".
_OFF = ("off", "0", "false", "no")


def compilation_cache_dir() -> Path | None:
    """Where `use_compilation_cache` keeps compiled programs: ``$JAXNM_COMPILATION_CACHE``
    if set (``off`` or empty: nowhere), else ``$XDG_CACHE_HOME/jaxnm/xla`` (by default
    ``~/.cache/jaxnm/xla``)."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", *_OFF) else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxnm" / "xla"


def use_compilation_cache(directory=None, *, min_compile_seconds: float = 0.05) -> Path | None:
    """Turn on JAX's persistent compilation cache, so a second run of the same program (a
    repeated ``jaxnm fit``, a script, a notebook) loads its compiled XLA programs from disk
    instead of compiling them again. The command line and the scripts call this; a library
    user opts in.

    **Arguments:**
    - `directory`: the cache folder; None for `compilation_cache_dir` (which honours
      ``$JAXNM_COMPILATION_CACHE``, ``off`` to disable).
    - `min_compile_seconds`: programs that compile faster than this are not stored.

    **Returns:** the folder in use, or None when the cache is off. Does nothing (and
    returns the folder already in use) if JAX's cache was configured elsewhere.
    """
    import jax

    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    path = compilation_cache_dir() if directory is None else Path(directory)
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # read-only home, etc.: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


#: The XLA flag that makes GPU scatter-adds (the texture gather's transpose in a fit's
#: gradient) and reductions run in a fixed order.
DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def _add_flag(flag: str) -> None:
    flags = os.environ.get("XLA_FLAGS", "")
    if flag not in flags.split():
        os.environ["XLA_FLAGS"] = f"{flags} {flag}".strip()


def use_deterministic_ops() -> None:
    """Ask XLA for run-to-run identical results on a GPU: two identical fits then give
    bit-identical maps (on the CPU they already do). Adds `DETERMINISTIC_FLAG` to
    ``XLA_FLAGS``, which JAX reads when it first initialises a backend: the command line
    calls this before any JAX computation; from Python, call it first thing (or set the
    flag yourself). The cost on a GPU is slower scatter-adds, hence slower gradients.
    """
    _add_flag(DETERMINISTIC_FLAG)


def deterministic_ops() -> bool:
    """Whether `DETERMINISTIC_FLAG` is in ``XLA_FLAGS`` (`use_deterministic_ops`)."""
    return DETERMINISTIC_FLAG in os.environ.get("XLA_FLAGS", "").split()


#: The XLA flag that puts while loops and conditionals into CUDA graphs (XLA's command
#: buffers; the other kinds are XLA's defaults): a loop's condition is then evaluated on
#: the device instead of being copied to the host on every trip.
GRAPHS_FLAG = ("--xla_gpu_enable_command_buffer="
               "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL")


def use_gpu_graphs() -> None:
    """Run a GPU's loops and conditionals inside CUDA graphs (`GRAPHS_FLAG`): faster
    frames, slower fit steps. Measured on an H100 (README, GPU; deterministic ops on):
    ``render`` of the 20k torus at 512^2 1.62-1.81 -> 1.11-1.33 ms and of the 200k torus
    at 1024^2 2.23-2.35 -> 1.74-2.02 ms (the rasterizer's round loop no longer waits for
    the host), but the fit benchmark's LM step 9.2 -> 10.1-10.9 ms. So it is an opt-in for
    programs that mostly render; like `use_deterministic_ops`, call it before any JAX
    computation (``XLA_FLAGS`` is read when a backend starts). No effect on the CPU."""
    _add_flag(GRAPHS_FLAG)


#: The XLA flag that lets its CPU code generator use 512-bit vectors (AVX-512), where by
#: default it prefers 256-bit ones.
WIDE_VECTORS_FLAG = "--xla_cpu_prefer_vector_width=512"

#: Environment variable: ``off`` keeps XLA's default vector width in the command line and the
#: scripts (see `use_wide_vectors`).
VECTORS_ENV = "JAXNM_WIDE_VECTORS"


def use_wide_vectors() -> bool:
    """Let XLA's CPU code generator use the CPU's 512-bit vectors (`WIDE_VECTORS_FLAG`), on
    a CPU that has them (AVX-512). On the 2-core VM of the README's tables (an AMD EPYC with
    AVX-512), `render`'s two programs compiled both ways and alternated in one process:
    frames 0.93-0.96x at 512^2 and 1024^2 (4k sphere, 20k and 200k tori), 0.1 s more
    compilation. Results change in their last bits only: the loops are vectorised
    differently, and where a product and a sum become one fused multiply-add changes with
    them (as between two GPUs' drivers; normals within 2 ulps, the same coverage, depth,
    triangle ids, uv and derivatives on the benchmark's scenes); the tests pass either way.

    Adds the flag to ``XLA_FLAGS``, which JAX reads when it first initialises a backend: call
    it before any JAX computation (after that, and where ``$JAXNM_WIDE_VECTORS`` is ``off``
    or the CPU has no AVX-512, it does nothing). The command line and the scripts call it; a
    library user opts in. Returns whether the flag is in ``XLA_FLAGS``."""
    if WIDE_VECTORS_FLAG in os.environ.get("XLA_FLAGS", "").split():
        return True
    if os.environ.get(VECTORS_ENV, "").strip().lower() in _OFF:
        return False
    if not _has_avx512() or _backends_initialised():
        return False
    _add_flag(WIDE_VECTORS_FLAG)
    return True


def _has_avx512() -> bool:
    """Whether the CPU has AVX-512 (Linux: ``/proc/cpuinfo``; False elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return "avx512f" in line.split()
    except OSError:
        pass
    return False


def release_memory(*, drop_compiled: bool = False, collect: bool = True) -> None:
    """Hand freed memory back to the system between the phases of a job: XLA's compiler
    frees hundreds of megabytes that glibc's allocator would otherwise keep in its arenas,
    and the next phase's peak would stack on them (a no-op where glibc is not the
    allocator; ~40 ms). ``drop_compiled`` also drops every compiled program (after a phase
    whose programs are not run again, such as a fit's solver steps);
    ``collect`` first runs Python's garbage collector (~80 ms: needed where Python objects
    hold the memory, not after a compilation)."""
    import gc

    if drop_compiled:
        import jax

        jax.clear_caches()
    if collect or drop_compiled:
        gc.collect()
    trim = _libc_function("malloc_trim")
    if trim is not None:
        trim(0)


#: Environment variable: ``off`` leaves the C allocator and JAX's dispatch as they are in the
#: command line and the scripts (see `keep_freed_memory`).
MEMORY_ENV = "JAXNM_KEEP_FREED_MEMORY"


def keep_freed_memory(*, trim_threshold_mb: int = 256, run_in_caller: bool = True) -> bool:
    """Keep the memory that XLA's CPU programs free for their next call, instead of handing
    it back to the system and page-faulting it in again on every call.

    Two settings, process-wide and permanent:

    - glibc's allocator maps no buffer on its own (``mallopt(M_MMAP_MAX, 0)``): every buffer
      comes from a heap, and freed memory stays there for reuse; the main heap is trimmed
      only past ``trim_threshold_mb`` free at its top (`release_memory` still trims it).
    - With ``run_in_caller``, JAX runs CPU programs in the thread that calls them
      (``jax_cpu_enable_async_dispatch=False``): XLA allocates a program's temporaries in
      one block in the thread that runs it, and glibc's per-thread heaps cannot hold a
      block over 64 MB (a 1024x1024 gradient's is ~70 MB), which it then maps afresh on
      each call; the calling (main) thread's heap can. The price: Python no longer
      traces and compiles the next program while the last one runs (a cold fit of the
      benchmark problem compiles ~0.25 s longer), and small frames take ~0.2 ms more.

    ``run_in_caller`` only takes effect before JAX initialises its CPU backend (the first
    computation): call this first thing. Called later, buffers up to 64 MB are kept and a
    `RuntimeWarning` says so. (A single heap shared by all threads, ``M_ARENA_MAX=1``,
    would also keep the block, but made compiling 30 % slower.)

    Measured on the 2-core VM (2026-11-26, fresh processes, JAX 0.10.2): forward+backward
    w.r.t. the map of a 1024x1024 frame 43-58 -> 31-35 ms (4k sphere), 50-55 -> 37-41 ms
    (20k torus), 63-65 -> 48-51 ms (200k torus), each call's ~14,500 page faults gone;
    `render` of the 200k torus at 512x512 20-27 -> 14-15 ms (6,000 faults a frame gone,
    by the first setting alone); small frames the same or ~0.2 ms slower; `jaxnm fit`'s
    peak 872-881 MB against 830-866 MB.

    **Returns:** True where the settings asked for took effect; False where glibc is not
    the C allocator (nothing changed) or JAX's backend was already initialised.
    """
    if not isinstance(trim_threshold_mb, int) or trim_threshold_mb < 0:
        raise ValueError("keep_freed_memory: trim_threshold_mb must be a non-negative int, "
                         f"got {trim_threshold_mb!r}")
    mallopt = _libc_function("mallopt")
    if mallopt is None:
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # glibc's <malloc.h>
    done = [bool(mallopt(m_mmap_max, 0)),
            bool(mallopt(m_trim_threshold, trim_threshold_mb << 20))]
    if not run_in_caller:
        return all(done)
    import jax

    if _backends_initialised():
        import warnings

        warnings.warn("keep_freed_memory: JAX's backend is already initialised, so its CPU "
                      "programs keep running in worker threads, whose heaps cannot keep "
                      "buffers over 64 MB: call keep_freed_memory() before the first JAX "
                      "computation", RuntimeWarning, stacklevel=2)
        return False
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    return all(done)


def keep_freed_memory_unless_disabled() -> bool:
    """`keep_freed_memory` unless ``$JAXNM_KEEP_FREED_MEMORY`` is ``off``, or JAX has already
    started (the command line and the scripts call this first thing; run in a process that
    has computed before, such as ``jaxnm.cli.main`` from a notebook, it leaves the
    process's allocator as it is). Returns whether it was applied."""
    if os.environ.get(MEMORY_ENV, "").strip().lower() in _OFF:
        return False
    if _backends_initialised():
        return False
    return keep_freed_memory()


#: Environment variable: ``off`` leaves XLA's CPU worker threads free to move between cores
#: in the command line and the scripts (see `pin_worker_threads`).
PIN_ENV = "JAXNM_PIN_THREADS"

#: The name (``/proc/self/task/*/comm``) of the threads of XLA's CPU intra-op pool.
_WORKER_PREFIX = "tf_XLAEigen"


def pin_worker_threads(prefix: str = _WORKER_PREFIX) -> int:
    """Put each of XLA's CPU worker threads on a core of its own (Linux; thread affinity),
    and leave them there.

    A frame is a hundred-odd small XLA kernels, each split between the pool's threads (one
    per core) and joined again. Where the system's scheduler lets two of those threads
    share a core for a while, each join waits for the one that is not running. On the
    2-core VM of the README's tables (a Firecracker guest) that made ``render`` of the 4k
    sphere at 512x512 bimodal, 3.4-3.7 ms a frame in some stretches and 5-8 ms in others,
    process by process and phase by phase (the "slow phases" of
    `docs/performance_history.md`); three processes each way, medians 4.1-6.3 ms and the
    slowest tenth 5.7-6.3 ms unpinned, 3.6-3.8 and 4.0-4.3 ms pinned (the 20k torus's
    slowest tenth 8.2-8.7 -> 5.4-6.1 ms, the 200k torus's 14-15 -> 12.1-12.4 ms). One core
    alone: 4.8-5.0 ms. This starts JAX's backends: call `keep_freed_memory` and
    `use_deterministic_ops` first. The command line and the scripts call it; a library
    user opts in.

    ``prefix``: the name the threads' names start with (XLA's CPU pool by default;
    ``scripts/bench.py`` pins Mitsuba's ``llvm-worker`` threads the same way).

    **Returns:** how many threads it pinned: 0 where ``$JAXNM_PIN_THREADS`` is ``off``, the
    system cannot pin threads, or the pool has more threads than the process has cores.
    """
    if os.environ.get(PIN_ENV, "").strip().lower() in _OFF:
        return 0
    if not hasattr(os, "sched_setaffinity") or not os.path.isdir("/proc/self/task"):
        return 0
    if prefix == _WORKER_PREFIX:
        import jax

        jax.devices("cpu")  # the CPU client starts its pool with it
    workers = []
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                if f.read().startswith(prefix):
                    workers.append(int(tid))
        except OSError:  # a thread that ended meanwhile
            continue
    cpus = sorted(os.sched_getaffinity(0))
    if not workers or len(workers) > len(cpus):
        return 0
    pinned = 0
    for cpu, tid in zip(cpus, sorted(workers)):
        try:
            os.sched_setaffinity(tid, {cpu})
        except OSError:
            continue
        pinned += 1
    return pinned


def _backends_initialised() -> bool:
    """Whether JAX has initialised its backends (False where this JAX cannot say)."""
    from jax._src import xla_bridge

    probe = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(probe()) if probe is not None else bool(getattr(xla_bridge, "_backends", {}))


@functools.cache
def _libc_function(name: str):
    """The C library's function ``name`` if the C library is glibc, else None; looked up
    once (finding the library runs ``ldconfig``)."""
    import ctypes
    import ctypes.util

    lib = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(lib) if lib else None
    except OSError:
        return None
    if libc is None or not hasattr(libc, "gnu_get_libc_version"):
        return None
    return getattr(libc, name, None)
