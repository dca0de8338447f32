"""Checkpoints of a running fit: everything `jaxnm.fit.fit_normal_map` needs to carry on
from where a fit stopped, and end with the map an uninterrupted fit ends with (bitwise
on the CPU).

A checkpoint is a NumPy ``.npz`` archive written atomically (`jaxnm.io.atomic_write`):

- ``z``: the solver's variables at the accepted point (the current level's map size).
- ``best_slopes``: the slopes of the lowest loss so far (what a stop returns).
- ``state_0000``, ``state_0001``, ...: the array leaves of the solver state, in
  ``jax.tree_util`` order. The state's structure depends only on the problem and the
  options, so a resumed fit rebuilds it from a freshly initialised state and puts these
  arrays in.
- ``meta``: a JSON string: the format and version, the `fit_fingerprint` of the fit, the
  level, the next step, whether the level had ended, the stop so far, the best loss, the
  elapsed seconds and the history (which holds everything the stopping rule looks at).

`fit_normal_map(..., checkpoint=path, resume=True)` refuses a checkpoint whose fingerprint
differs from the fit's in anything that changes the steps' arithmetic (`check_fingerprint`);
the stopping rule's settings (``max_steps``, ``ftol``, ``patience``, ``rtol``, ``atol``)
and the time limit may change.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .problem import FitOptions, FitProblem

__all__ = ["Checkpoint", "save_checkpoint", "load_checkpoint", "fit_fingerprint",
           "check_fingerprint", "ARITHMETIC_OPTIONS"]

_FORMAT = "jaxnm-fit-checkpoint"
_VERSION = 1

#: The `FitOptions` fields that change what the steps compute (a resume must keep them);
#: the others only decide when the fit stops.
ARITHMETIC_OPTIONS = ("solver", "smoothness", "coarse_to_fine", "lsmr_steps", "seed",
                      "init_noise", "texel_sums")


@dataclasses.dataclass
class Checkpoint:
    """A saved fit (see the module).

    - `meta`: the JSON metadata (``fingerprint``, ``level``, ``next_step``,
      ``level_done``, ``stopped``, ``stop_test``, ``best_loss``, ``seconds``,
      ``history``).
    - `z`: (h, w, 2) the solver's variables; `best_slopes`: (h, w, 2) the best slopes.
    - `state`: the array leaves of the solver state.
    """

    meta: dict
    z: np.ndarray
    best_slopes: np.ndarray
    state: list


def _digest(value, h) -> None:
    """Feed ``value`` (dataclasses, arrays, sequences, dicts, scalars, strings) into the
    hash ``h``, with its structure."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(type(value).__name__.encode())
        for f in dataclasses.fields(value):
            h.update(f.name.encode())
            _digest(getattr(value, f.name), h)
    elif isinstance(value, (list, tuple)):
        h.update(f"seq{len(value)}".encode())
        for v in value:
            _digest(v, h)
    elif isinstance(value, dict):
        h.update(f"map{len(value)}".encode())
        for k in sorted(value, key=str):
            h.update(str(k).encode())
            _digest(value[k], h)
    elif value is None or isinstance(value, (bool, int, float, str)):
        h.update(repr(value).encode())
    else:  # arrays (NumPy or JAX) and NumPy scalars
        a = np.ascontiguousarray(np.asarray(value))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())


def _hash(value) -> str:
    h = hashlib.sha256()
    _digest(value, h)
    return h.hexdigest()[:16]


def fit_fingerprint(problem: FitProblem, options: FitOptions, *, strength: float = 1.0,
                    layout=None) -> dict:
    """What identifies a fit's arithmetic: a hash of each field of ``problem`` (but its
    `source`, the file it came from), its map size, the options that change the steps
    (`ARITHMETIC_OPTIONS`), the rendering ``strength`` and a hash of ``layout`` (any value
    standing for how the problem was prepared, e.g. the prepared arrays' shapes)."""
    fields = {f.name: _hash(getattr(problem, f.name)) for f in dataclasses.fields(problem)
              if f.name not in ("source", "map_size")}
    return {"problem": fields, "map_size": [int(s) for s in problem.map_size],
            "options": {k: getattr(options, k) for k in ARITHMETIC_OPTIONS},
            "strength": float(strength), "layout": _hash(layout)}


def _size(s) -> str:
    return "x".join(str(v) for v in s)


def check_fingerprint(path, saved: dict, current: dict) -> None:
    """Raise a one-line `ValueError` naming ``path`` and every difference between the
    checkpoint's fingerprint ``saved`` and the fit's ``current`` (`fit_fingerprint`)."""
    diffs = []
    if saved.get("map_size") != current["map_size"]:
        diffs.append(f"map size {_size(saved.get('map_size', '?'))} in the checkpoint, "
                     f"{_size(current['map_size'])} now")
    old = saved.get("options", {})
    for k, v in current["options"].items():
        if old.get(k) != v:
            diffs.append(f"{k} {old.get(k)!r} in the checkpoint, {v!r} now")
    fields = [k for k, v in current["problem"].items() if saved.get("problem", {}).get(k) != v]
    if fields:
        diffs.append(f"another problem (its {', '.join(fields)} differ)")
    if saved.get("strength") != current["strength"]:
        diffs.append(f"strength {saved.get('strength')} in the checkpoint, "
                     f"{current['strength']} now")
    if not diffs and saved.get("layout") != current["layout"]:
        diffs.append("the problem was prepared differently (other chunks or devices)")
    if diffs:
        raise ValueError(f"{path}: cannot resume this fit: {'; '.join(diffs)}")


def save_checkpoint(path, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` to ``path`` (``.npz``) atomically: a reader sees the previous
    checkpoint or this one, never a part of one."""
    from ..io import atomic_write

    meta = {"format": _FORMAT, "version": _VERSION, **checkpoint.meta,
            "state_leaves": len(checkpoint.state)}
    arrays = {"meta": np.asarray(json.dumps(meta)),
              "z": np.asarray(checkpoint.z), "best_slopes": np.asarray(checkpoint.best_slopes)}
    arrays.update({f"state_{i:04d}": np.asarray(a) for i, a in enumerate(checkpoint.state)})
    with atomic_write(path) as f:
        np.savez(f, **arrays)


def load_checkpoint(path) -> Checkpoint:
    """Read a checkpoint written by `save_checkpoint`; a missing file raises
    `FileNotFoundError`, anything else unreadable a one-line `ValueError` naming ``path``."""
    p = Path(os.fspath(path))
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no checkpoint to resume from")
    try:
        with np.load(p, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("format") != _FORMAT or meta.get("version") != _VERSION:
                raise ValueError(f"not a version {_VERSION} fit checkpoint")
            state = [z[f"state_{i:04d}"] for i in range(meta["state_leaves"])]
            return Checkpoint(meta=meta, z=z["z"], best_slopes=z["best_slopes"], state=state)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{p}: cannot read the checkpoint ({type(e).__name__}: {e})") from None

