"""Traced programs kept on disk, beside JAX's persistent compilation cache.

JAX's persistent cache (`jaxnm.runtime.use_compilation_cache`) spares a second process the
compiler, but not the tracing and lowering that come before it: JAX must build the
program to look it up. For `render`'s and a fit's `prepare`'s programs that is most of a
warm start (a warm ``prepare`` on an H100: 0.8 s of tracing and 0.4 s of lowering, 0.2 s
of reading the compiled programs). `cached_jit` is `jax.jit` plus a second cache: the
first process to run a program with given argument shapes, dtypes and static options
exports it (`jax.export`, the lowered StableHLO) into ``<compilation cache>/jaxnm-traced``,
and later processes call the exported program instead of tracing the Python function.

The cache is used only where it is safe and pays:
- only while JAX's persistent compilation cache is on (the CLI and the scripts; a library
  user opts in with `use_compilation_cache`), and where JAX can serialize programs (the
  ``flatbuffers`` package);
- only for calls with concrete array arguments on one device: inside the caller's `jit`,
  `grad` or `vmap` (traced arguments), or with arrays spread over several devices, the
  call is plain `jax.jit`'s;
- an entry's key holds the function's name, the static options, the arguments' tree,
  shapes and dtypes, the x64 mode, the backend and device kind, the JAX and jaxlib
  versions and a hash of jaxnm's own source files, so a program is never reused across a
  change of the code that made it. An unreadable entry is exported again.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
from pathlib import Path

import jax
import numpy as np

__all__ = ["cached_jit", "traced_cache_dir", "SUBDIR", "TRACED_ENV"]

#: The folder inside the compilation cache that holds the traced programs.
SUBDIR = "jaxnm-traced"

#: Environment variable: ``off`` keeps traced programs off the disk (the compilation cache
#: itself stays as `jaxnm.runtime.CACHE_ENV` says).
TRACED_ENV = "JAXNM_TRACED_CACHE"


def traced_cache_dir() -> Path | None:
    """Where `cached_jit` keeps traced programs: ``SUBDIR`` inside JAX's persistent
    compilation cache folder, or None while that cache is off, ``$JAXNM_TRACED_CACHE`` is
    ``off`` or JAX cannot serialize programs here."""
    base = jax.config.jax_compilation_cache_dir
    if not base or _off() or not _can_serialize():
        return None
    return Path(base) / SUBDIR


def _off() -> bool:
    return os.environ.get(TRACED_ENV, "").strip().lower() in ("off", "0", "false", "no")


@functools.cache
def _can_serialize() -> bool:
    try:
        import flatbuffers  # noqa: F401  (what jax.export's serialization needs)
    except ImportError:
        return False
    return True


@functools.cache
def _code_fingerprint() -> str:
    """A hash of jaxnm's source files and the versions of what traces its programs."""
    import equinox
    import jaxlib
    import lineax
    import optimistix

    h = hashlib.sha256()
    for mod in (jax, jaxlib, equinox, lineax, optimistix):
        h.update(f"{mod.__name__}={getattr(mod, '__version__', '?')};".encode())
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def cached_jit(fun=None, *, static_argnames: tuple[str, ...] = ()):
    """`jax.jit(fun, static_argnames=...)` whose traced program is also kept on disk (see
    the module). Dynamic arguments are passed positionally and static ones by keyword;
    any other call is plain `jax.jit`'s. ``.clear_cache()`` forgets the compiled programs
    in this process (the files stay)."""
    if fun is None:
        return functools.partial(cached_jit, static_argnames=static_argnames)
    return _CachedJit(fun, tuple(static_argnames))


class _CachedJit:
    def __init__(self, fun, static_argnames):
        self._jit = jax.jit(fun, static_argnames=static_argnames)
        self._static = static_argnames
        self._name = f"{fun.__module__}.{fun.__qualname__}"
        self._calls: dict = {}  # key -> (compiled callable, output tree)
        functools.update_wrapper(self, fun)

    def __call__(self, *args, **kwargs):
        folder = traced_cache_dir()
        if folder is None or any(k not in self._static for k in kwargs):
            return self._jit(*args, **kwargs)
        leaves, in_tree = jax.tree_util.tree_flatten(args)
        avals = _avals(leaves)
        if avals is None:  # traced, on several devices, or not an array
            return self._jit(*args, **kwargs)
        # (static options are hashable, as `jax.jit` requires; their repr names the file)
        key = (tuple(sorted(kwargs.items())), in_tree, avals, bool(jax.config.jax_enable_x64),
               jax.default_backend())
        entry = self._calls.get(key)
        if entry is None:
            entry = self._calls[key] = self._load_or_export(folder, key, args, kwargs)
        fn, out_tree = entry
        return jax.tree_util.tree_unflatten(out_tree, fn(*leaves))

    def _load_or_export(self, folder: Path, key, args, kwargs):
        statics, in_tree, avals, x64, backend = key
        described = (self._name, [(k, repr(v)) for k, v in statics], str(in_tree),
                     [(shape, str(dtype), weak) for shape, dtype, weak in avals], x64, backend,
                     jax.devices()[0].device_kind, _code_fingerprint())
        digest = hashlib.sha256(repr(described).encode()).hexdigest()[:40]
        path = folder / f"{digest}.bin"
        try:
            out_tree, blob = pickle.loads(path.read_bytes())
            exported = jax.export.deserialize(bytearray(blob))
        except Exception:  # absent, or unreadable: trace it again
            exported, out_tree = self._export(args, kwargs)
            try:
                folder.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_bytes(pickle.dumps((out_tree, bytes(exported.serialize()))))
                os.replace(tmp, path)
            except OSError:
                pass  # a read-only cache: this process still uses the program
        return jax.jit(exported.call), out_tree

    def _export(self, args, kwargs):
        """The program as a function of the flat arguments, exported, and its output tree."""
        _, in_tree = jax.tree_util.tree_flatten(args)
        trees = []

        def flat(*leaves):
            out = self._jit(*jax.tree_util.tree_unflatten(in_tree, leaves), **kwargs)
            out_leaves, out_tree = jax.tree_util.tree_flatten(out)
            trees.append(out_tree)
            return out_leaves

        leaves = jax.tree_util.tree_leaves(args)
        exported = jax.export.export(jax.jit(flat))(*leaves)
        return exported, trees[0]

    def clear_cache(self) -> None:
        self._calls.clear()
        self._jit.clear_cache()

    def lower(self, *args, **kwargs):
        return self._jit.lower(*args, **kwargs)


def _avals(leaves) -> tuple | None:
    """Each leaf's (shape, dtype, weak type) as `jax.jit` would see it, or None where a
    leaf is traced, lives on several devices or is not an array."""
    out = []
    for x in leaves:
        if isinstance(x, jax.core.Tracer):
            return None
        if isinstance(x, jax.Array):
            if len(x.sharding.device_set) != 1:
                return None
            out.append((x.shape, x.dtype, bool(getattr(x, "weak_type", False))))
        elif isinstance(x, (np.ndarray, np.generic)):
            out.append((np.shape(x), jax.dtypes.canonicalize_dtype(x.dtype), False))
        else:
            return None
    return tuple(out)
