"""The process around the computation: the persistent compilation cache, deterministic
GPU arithmetic, and handing freed memory back to the system between phases.

These change process-wide state (JAX's configuration, ``XLA_FLAGS``, the C allocator), so
the command line and the scripts call them; a library user opts in. Nothing here changes
a result.

XLA's CPU programs allocate their buffers afresh on every call; where glibc hands them back
to the system in between, every call pays the page faults of touching them again.
`keep_freed_memory` tells glibc (at run time, ``mallopt``) to keep them: what does it is
the heap's top padding, with the thresholds above which it would map or trim memory.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

__all__ = ["CACHE_ENV", "DETERMINISTIC_FLAG", "compilation_cache_dir", "use_compilation_cache",
           "use_deterministic_ops", "release_memory", "keep_freed_memory"]

#: Environment variable naming the cache folder; ``off`` (or empty) turns the cache off.
CACHE_ENV = "JAXNM_COMPILATION_CACHE"


def compilation_cache_dir() -> Path | None:
    """Where `use_compilation_cache` keeps compiled programs: ``$JAXNM_COMPILATION_CACHE``
    if set (``off`` or empty: nowhere), else ``$XDG_CACHE_HOME/jaxnm/xla`` (by default
    ``~/.cache/jaxnm/xla``)."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "false", "no") else Path(env)
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


def use_deterministic_ops() -> None:
    """Ask XLA for run-to-run identical results on a GPU: two identical fits then give
    bit-identical maps (on the CPU they already do). Adds `DETERMINISTIC_FLAG` to
    ``XLA_FLAGS``, which JAX reads when it first initialises a backend: the command line
    calls this before any JAX computation; from Python, call it first thing (or set the
    flag yourself). The cost on a GPU is slower scatter-adds, hence slower gradients.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if DETERMINISTIC_FLAG not in flags.split():
        os.environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()


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


def keep_freed_memory(*, top_pad_mb: int = 64, trim_threshold_mb: int = 256,
                      mmap_threshold_mb: int = 32) -> bool:
    """Tell glibc's allocator to keep freed memory for reuse instead of handing it back to
    the system: buffers up to ``mmap_threshold_mb`` come from the heap, the heap grows by
    ``top_pad_mb`` more than asked, and is trimmed only past ``trim_threshold_mb`` free at
    its top (`release_memory` still trims it). Process-wide and permanent; returns False
    (and changes nothing) where glibc is not the allocator.

    Measured on the 2-core VM (2026-11-26, fresh processes): forward+backward of the 200k
    torus at 512x512 under the caller's `jax.jit` 36.7 -> 25.7 ms, its forward 28 -> 17 ms
    (as fast as `render` outside a jit), for 20-120 MB more peak memory; the 4k and 20k
    meshes and `render` itself the same. The page faults are the cost it removes: every
    call touches its fresh buffers again (see the README's speed notes).
    """
    sizes = dict(top_pad_mb=top_pad_mb, trim_threshold_mb=trim_threshold_mb,
                 mmap_threshold_mb=mmap_threshold_mb)
    for name, mb in sizes.items():
        if not isinstance(mb, int) or mb < 0:
            raise ValueError(f"keep_freed_memory: {name} must be a non-negative int, got {mb!r}")
    if mmap_threshold_mb > 32:
        raise ValueError("keep_freed_memory: glibc caps the mmap threshold at 32 MiB at run "
                         f"time, got {mmap_threshold_mb}")
    mallopt = _libc_function("mallopt")
    if mallopt is None:
        return False
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3  # glibc's <malloc.h>
    mib = 1 << 20
    done = [bool(mallopt(option, mb * mib)) for option, mb in (  # each set, whatever fails
        (m_mmap_threshold, mmap_threshold_mb), (m_trim_threshold, trim_threshold_mb),
        (m_top_pad, top_pad_mb))]
    return all(done)


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
