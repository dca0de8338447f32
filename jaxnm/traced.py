"""Traced programs kept on disk, beside JAX's persistent compilation cache.

JAX's persistent cache (`jaxnm.runtime.use_compilation_cache`) spares a second process the
compiler, but not the tracing and lowering that come before it: JAX must build the
program to look it up. For `render`'s and a fit's programs that is most of a warm start
(a warm ``prepare`` on an H100: 0.8 s of tracing and 0.4 s of lowering, 0.2 s of reading
the compiled programs). `cached_jit` is `jax.jit` plus a second cache (`cached_filter_jit`
the same for `equinox.filter_jit`, the fit's LM step): the
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
  shapes and dtypes, the x64 mode, the backend and device kind, the versions of JAX,
  jaxlib, equinox, lineax and optimistix and a hash of jaxnm's own source files, so a
  program is never reused across a change of the code that made it. An unreadable entry
  is exported again; options known only by their address, outputs that do not survive
  pickling and programs JAX cannot export are not stored (those calls are plain jit's).

The files are pickles: the folder is trusted as JAX's compilation cache is.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import io
import os
import pickle
from pathlib import Path

import jax
import numpy as np

__all__ = ["cached_jit", "cached_filter_jit", "traced_cache_dir", "SUBDIR", "TRACED_ENV"]

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
        entry = self._calls.get(key, False)
        if entry is False:
            described = repr((self._name, [(k, repr(v)) for k, v in key[0]], str(in_tree),
                              [(sh, str(dt), w) for sh, dt, w in avals], key[3:],
                              jax.devices()[0].device_kind, _code_fingerprint()))
            entry = self._calls[key] = _load_or_export(
                folder, described, lambda: self._export(in_tree, leaves, kwargs))
        if entry is None:
            return self._jit(*args, **kwargs)
        fn, out_tree = entry
        return jax.tree_util.tree_unflatten(out_tree, fn(*leaves))

    def _export(self, in_tree, leaves, kwargs):
        """The program as a function of the flat arguments, exported, and its output tree."""
        trees = []

        def flat(*leaves):
            out = self._jit(*jax.tree_util.tree_unflatten(in_tree, leaves), **kwargs)
            out_leaves, out_tree = jax.tree_util.tree_flatten(out)
            trees.append(out_tree)
            return out_leaves

        exported = jax.export.export(jax.jit(flat))(*leaves)
        return exported, trees[0]

    def clear_cache(self) -> None:
        self._calls.clear()
        self._jit.clear_cache()


def cached_filter_jit(fun=None, *, donate: str = "none"):
    """`equinox.filter_jit(fun, donate=donate)` (``"none"`` or ``"all-except-first"``) whose
    traced program is also kept on disk as `cached_jit`'s: the arguments' arrays are the
    program's inputs, everything else in them (hashable, with a repr that names no memory
    address) belongs to the key; outputs that are not arrays come back as they were traced.
    Other calls (traced arguments, unhashable options) are plain `equinox.filter_jit`'s.
    ``.lower(*args)`` lowers the program a call would run (to compile it ahead)."""
    if fun is None:
        return functools.partial(cached_filter_jit, donate=donate)
    if donate not in ("none", "all-except-first"):
        raise ValueError(f"cached_filter_jit: donate must be 'none' or 'all-except-first', "
                         f"got {donate!r}")
    return _CachedFilterJit(fun, donate)


class _CachedFilterJit:
    def __init__(self, fun, donate):
        import equinox as eqx

        self._eqx = eqx.filter_jit(fun, donate=donate)
        self._fun = fun
        self._donate = donate
        self._name = f"{fun.__module__}.{fun.__qualname__}"
        self._calls: dict = {}  # key -> (callable, (output static part, tree), donated)
        functools.update_wrapper(self, fun)

    def _entry(self, args):
        """``(callable, leaves, output static part, output tree)`` for ``args``, or None
        where the call is not for the disk cache."""
        import equinox as eqx

        folder = traced_cache_dir()
        if folder is None:
            return None
        dynamic, static = eqx.partition(args, eqx.is_array)
        leaves, tree = jax.tree_util.tree_flatten(dynamic)
        avals = _avals(leaves)
        if avals is None:
            return None
        options, options_tree = jax.tree_util.tree_flatten(static)
        key = (tuple(options), options_tree, tree, avals, bool(jax.config.jax_enable_x64),
               jax.default_backend())
        try:
            entry = self._calls.get(key, False)
        except TypeError:  # an unhashable option
            return None
        if entry is None:  # known not to be for the disk
            return None
        if entry is False:
            described = repr((self._name, self._donate, options, str(options_tree),
                              str(tree), [(sh, str(dt), w) for sh, dt, w in avals],
                              key[4:], jax.devices()[0].device_kind, _code_fingerprint()))
            first = len(jax.tree_util.tree_leaves(eqx.filter(args[0], eqx.is_array)))
            donated = (tuple(range(first, len(leaves))) if self._donate == "all-except-first"
                       else ())
            loaded = _load_or_export(folder, described,
                                     lambda: self._export(tree, static, leaves), donated)
            entry = self._calls[key] = None if loaded is None else (*loaded, frozenset(donated))
            if entry is None:
                return None
        fn, (out_static, out_tree), donated = entry
        return fn, leaves, out_static, out_tree, donated

    def _export(self, tree, static, leaves):
        """The program as a function of the arguments' arrays, exported, and its output's
        static part and tree."""
        import equinox as eqx

        box = []

        def flat(*leaves):
            args = eqx.combine(jax.tree_util.tree_unflatten(tree, leaves), static)
            out_dynamic, out_static = eqx.partition(self._fun(*args), eqx.is_array)
            out_leaves, out_tree = jax.tree_util.tree_flatten(out_dynamic)
            box.append((out_static, out_tree))
            return out_leaves

        exported = jax.export.export(jax.jit(flat))(*leaves)
        return exported, box[0]

    def __call__(self, *args):
        import equinox as eqx

        entry = self._entry(args)
        if entry is None:
            return self._eqx(*args)
        fn, leaves, out_static, out_tree, donated = entry
        out = fn(*_committed(leaves, donated))
        return eqx.combine(jax.tree_util.tree_unflatten(out_tree, out), out_static)

    def lower(self, *args):
        entry = self._entry(args)
        if entry is None:
            return self._eqx.lower(*args)
        fn, leaves, _, _, donated = entry
        return fn.lower(*_committed(leaves, donated))

    def clear_cache(self) -> None:
        self._calls.clear()


def _load_or_export(folder: Path, described: str, export, donated=()):
    """``(jax.jit of the exported program's call, meta)`` for the program ``described`` (its
    key as text): read from its file in ``folder``, or made by ``export() -> (exported,
    meta)`` and stored (``meta``: what the caller needs besides the program, e.g. the output
    tree). None where it is not for the disk: an option known only by its address (the key
    would differ in every process), or a program JAX cannot export (a host callback, say)."""
    if " at 0x" in described:
        return None
    path = folder / f"{hashlib.sha256(described.encode()).hexdigest()[:40]}.bin"
    try:
        try:
            meta, blob = _loads(path.read_bytes())
            exported = jax.export.deserialize(bytearray(blob))
        except Exception:  # absent, or unreadable: trace it again
            exported, meta = export()
            flat_meta = jax.tree_util.tree_flatten(meta)
            _store(path, (meta, bytes(exported.serialize())),
                   lambda back: jax.tree_util.tree_flatten(back[0]) == flat_meta)
    except Exception:
        return None
    return jax.jit(exported.call, donate_argnums=donated), meta


def _committed(leaves, which) -> list:
    """``leaves``, those at the indices ``which`` committed to their device. An exported
    program's call is lowered with its arguments' placements, so a fit step whose first
    state was made on the host (uncommitted) and whose next states are the step's own
    outputs (committed) would compile twice (0.7 s on the CPU). The donated arguments are
    the state; after the first step they are committed already (committing an array costs
    ~20 us, too much to do for every argument of every call)."""
    out = list(leaves)
    for i in which:
        x = out[i]
        if not isinstance(x, jax.Array):
            x = jax.device_put(x)
        if not x.committed:
            out[i] = jax.device_put(x, x.sharding)
    return out


class _Pickler(pickle.Pickler):
    """Pickles module-level singletons that pytree definitions hold (equinox's ``MISSING``
    marker) by name, so that they come back as the same object."""

    def persistent_id(self, obj):
        kind = type(obj)
        if kind.__module__.startswith("equinox") and kind.__name__ == "_Missing":
            return (kind.__module__, "MISSING")
        return None


class _Unpickler(pickle.Unpickler):
    def persistent_load(self, pid):
        module, name = pid
        return getattr(importlib.import_module(module), name)


def _store(path: Path, payload: tuple, same) -> None:
    """``payload`` pickled into ``path`` (atomically), if it comes back as it went (``same``
    of the unpickled payload); else, or where the folder is not writable, nothing: the
    process still uses its program, and a later one traces it again."""
    try:
        blob = _dumps(payload)
        if not same(_loads(blob)):
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(blob)
        os.replace(tmp, path)
    except Exception:
        pass


def _dumps(obj) -> bytes:
    buf = io.BytesIO()
    _Pickler(buf).dump(obj)
    return buf.getvalue()


def _loads(blob: bytes):
    return _Unpickler(io.BytesIO(blob)).load()


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
