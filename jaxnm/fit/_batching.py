"""How prepared views are put together into batches: their lights, their pixels ordered by
the taps they read, padding, chunks; host-side (NumPy) helpers of `jaxnm.fit.prepare` and
`jaxnm.fit.distributed`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import numpy as np

from ..gbuffer import GBuffer
from ..shading import Lights

__all__ = ["check_chunk", "chunking", "host", "light_key", "map_pixels", "stack_lights",
           "stack_rows", "tap_groups"]


def stack_lights(lights: Sequence[Lights]) -> Lights:
    """One view's targets' ``lights`` stacked along a new leading axis (NumPy), or a
    `ValueError` where their kinds or counts differ."""
    structs = {jax.tree_util.tree_structure(light) for light in lights}
    shapes = {tuple(x.shape for x in jax.tree_util.tree_leaves(light)) for light in lights}
    if len(structs) != 1 or len(shapes) != 1:
        raise ValueError("fit: all targets of one view must have lights of the same kinds and "
                         "counts (e.g. each one directional light), so they can be batched")
    # on the host: `host` takes them there anyway, and a jnp.stack compiles per shape
    return jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]), *lights)


def check_chunk(chunk) -> None:
    """Raise a `ValueError` unless ``chunk`` is a positive number of pixel-targets or None."""
    if chunk is not None and chunk < 1:
        raise ValueError(f"prepare: chunk must be a positive number of pixel-targets or None, "
                         f"got {chunk}")


def host(tree):
    """``tree`` with every leaf a NumPy array (a host copy, or a view on the CPU), float64
    ones in float32: a fit's arithmetic, with ``jax_enable_x64`` on or off."""
    def leaf(x):
        x = np.asarray(x)
        return x.astype(np.float32) if x.dtype == np.float64 else x
    return jax.tree_util.tree_map(leaf, tree)


def map_pixels(gb: GBuffer, fn, eye=lambda x: x) -> GBuffer:
    """Apply ``fn`` to every per-pixel field of ``gb`` and ``eye`` to the eye position."""
    out = jax.tree_util.tree_map(fn, dataclasses.replace(gb, eye=None))
    return dataclasses.replace(out, eye=None if gb.eye is None else eye(gb.eye))


def light_key(lights: Lights):
    """What views must share to be batched together: their stacked lights' structure and
    leaf shapes (but the target axis)."""
    leaves, tree = jax.tree_util.tree_flatten(lights)
    return tree, tuple(x.shape[1:] for x in leaves)


def chunking(count: int, per_chunk: int | None) -> tuple[int, int]:
    """(chunks, padded count): ``count`` pixels cut into chunks of at most ``per_chunk``,
    padded to a multiple of the number of chunks (fewer than one extra pixel per chunk)."""
    if count == 0:
        return 1, 0
    n = 1 if per_chunk is None else -(-count // per_chunk)
    return n, n * -(-count // n)


def tap_groups(view) -> tuple[np.ndarray, np.ndarray]:
    """The indices of ``view``'s pixels (a `jaxnm.fit.prepare.View`) that read one mip level
    (4 non-zero taps) and of the others (see `jaxnm.fit.prepare.assemble`)."""
    w = np.asarray(view.gbuffer.plan.weight)
    one = (np.all(w[:, 4:] == 0, axis=-1) if view.gbuffer.plan.num_taps == 8
           else np.zeros(len(w), bool))
    return np.flatnonzero(one), np.flatnonzero(~one)


def stack_rows(views: list, members: Sequence[int], parts: Sequence, ka: int, kb: int,
                t_max: int) -> dict:
    """The host arrays of a `ViewBatch` whose rows are ``views[v]`` for ``v`` in ``members``:
    each view's pixels ordered by `tap_groups` (``parts``) and padded to ``ka`` + ``kb``, its
    targets to ``t_max``. Takes the views over (each entry is set to None once copied)."""
    stacked = None  # filled view by view, each view released once copied
    for i, (v, (a, b)) in enumerate(zip(members, parts)):
        view, views[v] = views[v], None
        fill = int(a[0] if len(a) else b[0])  # a real pixel, copied into the padding
        order = np.concatenate([a, np.full(ka - len(a), fill), b, np.full(kb - len(b), fill)])
        real = np.concatenate([np.ones(len(a), bool), np.zeros(ka - len(a), bool),
                               np.ones(len(b), bool), np.zeros(kb - len(b), bool)])
        t = view.images.shape[0]
        tsel = np.minimum(np.arange(t_max), t - 1)  # padded targets repeat the last one
        used = real[None, :, None] & (np.arange(t_max) < t)[:, None, None]
        row = dict(gbuffer=map_pixels(view.gbuffer, lambda x: x[order]),
                   pixels=np.where(real, view.pixels[order], -1).astype(np.int32),
                   images=view.images[np.ix_(tsel, order)],
                   weights=view.weights[np.ix_(tsel, order)] * used.astype(np.float32),
                   lights=jax.tree_util.tree_map(lambda x: x[tsel], view.lights))
        del view
        if stacked is None:
            stacked = jax.tree_util.tree_map(
                lambda x: np.empty((len(members),) + x.shape, x.dtype), row)
        jax.tree_util.tree_map(lambda out, x: out.__setitem__(i, x), stacked, row)
        del row
    return stacked
